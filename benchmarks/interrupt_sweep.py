"""Ctrl-C and SIGTERM at evenly spaced moments of a real ``kalmansfm demo`` rerun: is the result ever wrong?

For each signal and each of N moments from S to 1.1 × the run's measured wall time (S = 0 by default;
``--start 0.85`` packs the moments around the final swap), a fresh copy of
an earlier run folder is rerun into (8 frames, seed 3 → 8 frames, seed 1) and the signal is sent at
that moment.  Every outcome must be one of:

* ``earlier``: the folder is byte-identical to the earlier run, no temporary beside it, exit 130
  (SIGINT) or 143 (SIGTERM) — or killed by that signal before Python had set up its handlers — and
  at most one stderr line, no traceback;
* ``new``: the folder holds the complete new run (its files are exactly those its summary lists,
  plus report.html), no temporary, exit 0 or the interrupt code with a line saying the new results
  were written.

Anything else is counted as ``WRONG``.  Usage (prints a table and the counts; deterministic apart from
the timing of the machine)::

    python benchmarks/interrupt_sweep.py [--points 26] [--start 0.85]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
ENV = {**os.environ, "PYTHONPATH": str(SRC)}
COMMAND = [sys.executable, "-m", "kalmansfm", "demo", "--frames", "8", "--seed", "1", "--quiet"]


def default_sigint() -> None:
    """In the child: Ctrl-C acts, even when this script was started in the background (which ignores SIGINT)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def classify(folder: Path, earlier: dict[str, bytes], code: int, err: str, sent: int) -> str:
    leftovers = [p.name for p in folder.parent.iterdir() if p.name.startswith(f".{folder.name}.")]
    lines = [line for line in err.splitlines() if line.strip() and "\r" not in line]
    if leftovers or "Traceback" in err or len(lines) > 1:
        return "WRONG"
    stopped = code in (128 + sent, -sent)
    if folder.exists() and snapshot(folder) == earlier:
        return "earlier" if stopped else "WRONG"
    try:
        summary = json.loads((folder / "summary.json").read_text())
    except (OSError, ValueError):
        return "WRONG"
    present = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}
    complete = present - {"report.html"} == set(summary["files"]) and summary["tracking"]["frames"] == 8
    said = code == 0 or (stopped and "new results were written" in err)
    return "new" if complete and "seed 1" in summary["input"] and said else "WRONG"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=26)
    parser.add_argument("--start", type=float, default=0.0, help="first moment, as a fraction of the wall time")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="kalmansfm-sweep-"))
    base = work / "earlier"
    subprocess.run([sys.executable, "-m", "kalmansfm", "demo", "--out", str(base), "--frames", "8", "--seed", "3",
                    "--quiet"], env=ENV, check=True, capture_output=True)
    earlier = snapshot(base)
    timed = work / "timed"
    shutil.copytree(base, timed)
    started = time.perf_counter()
    subprocess.run([*COMMAND, "--out", str(timed)], env=ENV, check=True, capture_output=True)
    wall = time.perf_counter() - started
    print(f"load average {os.getloadavg()[0]:.2f}; one rerun takes {wall:.2f} s; {args.points} moments per signal "
          f"from {args.start:g} to 1.1 x that")
    counts: dict[str, int] = {}
    for sent in (signal.SIGINT, signal.SIGTERM):
        for k in range(args.points):
            moment = wall * (args.start + (1.1 - args.start) * k / (args.points - 1))
            folder = work / f"{sent.name}-{k}"
            shutil.copytree(base, folder)
            process = subprocess.Popen([*COMMAND, "--out", str(folder)], env=ENV, preexec_fn=default_sigint,
                                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            time.sleep(moment)
            process.send_signal(sent)
            _, err = process.communicate(timeout=300)
            outcome = classify(folder, earlier, process.returncode, err, int(sent))
            counts[outcome] = counts.get(outcome, 0) + 1
            last = err.strip().splitlines()[-1] if err.strip() else ""
            print(f"{sent.name:7s} {moment:6.2f} s  exit {process.returncode:4d}  {outcome:7s}  {last[:110]}")
            shutil.rmtree(folder, ignore_errors=True)
    print("outcomes:", ", ".join(f"{name} {n}" for name, n in sorted(counts.items())))
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
