"""A user's first minutes (issue 29): the first command after install against the second.

Usage::

    python benchmarks/bench_first_run.py [--pairs 2]

Each pair of runs shares one fresh, empty ``NUMBA_CACHE_DIR`` (the state of a new install: no
compiled kernel anywhere), so the first run of a pair pays every compilation it needs and the
second loads from the cache. Measured, as wall time of a fresh process each:

* ``kalmansfm demo -q`` (the built-in scene) — target: first ≤ 2× the second;
* ``kalmansfm fuse`` of a synthetic known-camera scene of 400 points × 8 views
  (``kalmansfm.scenes.known_cameras``, written as an observations ``tracks.csv`` and a
  ``cameras.csv``) — target: first ≤ 5 s;
* ``kalmansfm demo --input slow.flv -q`` (656 frames; needs ``../shared/data``): the run folder's
  size, target ≤ 25 MB, and the share of the run spent writing (from ``summary.json``'s timings).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from kalmansfm.io.cameras import cameras_csv
from kalmansfm.io.tracks import observations_csv
from kalmansfm.scenes.known_cameras import known_camera_scene

ROOT = Path(__file__).resolve().parents[1]
SLOW_CLIP = ROOT / ".." / "shared" / "data" / "opencv_samples" / "slow.flv"


def timed(command: list[str], cache: Path) -> float:
    """Wall seconds of ``python -m kalmansfm COMMAND`` in a fresh process using ``cache``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "kalmansfm", *command], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - started


def load() -> str:
    """The 1-minute load average, as the tables quote it."""
    return f"{os.getloadavg()[0]:.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=2, help="pairs of (first, second) runs per command")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="kalmansfm-first-run-"))
    scene = known_camera_scene(points=400, views=8, seed=0)
    (work / "tracks.csv").write_text(observations_csv(scene.observations, list(range(8))), encoding="utf-8")
    (work / "cameras.csv").write_text(cameras_csv(scene.cameras), encoding="utf-8")
    commands = {
        "demo (built-in scene)": ["demo", "-q"],
        "fuse 400 points x 8 views": ["fuse", str(work / "tracks.csv"), "--cameras", str(work / "cameras.csv"), "-q"],
    }
    print("| command | pair | first (s) | second (s) | first / second | load |\n|---|---:|---:|---:|---:|---:|")
    for name, command in commands.items():
        for pair in range(args.pairs):
            cache = Path(tempfile.mkdtemp(prefix="numba-cache-", dir=work))
            times = [timed([*command, "--out", str(work / f"{name[:4]}-{pair}-{k}")], cache) for k in (1, 2)]
            print(f"| {name} | {pair + 1} | {times[0]:.2f} | {times[1]:.2f} | {times[0] / times[1]:.2f} | {load()} |")
    if SLOW_CLIP.exists():
        out = work / "slow"
        seconds = timed(["demo", "--input", str(SLOW_CLIP), "--out", str(out), "-q"], work / "slow-cache")
        summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
        steps = dict(summary["timings_s"])
        size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
        print(f"\nslow.flv demo (first run, empty cache, report included): {seconds:.2f} s wall; run folder "
              f"{size / 1e6:.1f} MB; steps {', '.join(f'{k} {v:.2f} s' for k, v in steps.items())}; "
              f"writing {steps.get('writing', 0.0) / summary['total_s']:.0%} of the run's own time "
              f"({summary['total_s']:.2f} s, the report apart); load {load()}")
    else:
        print(f"\n{SLOW_CLIP} not found: the long-clip row needs ../shared/data")


if __name__ == "__main__":
    main()
