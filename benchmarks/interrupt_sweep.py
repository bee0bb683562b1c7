"""Signals at chosen and random moments of real ``kalmansfm demo`` reruns, and concurrent runs into one ``--out``.

Is the result ever wrong?  Three parts, each printing one row per case and the counts:

1. **Moments** (``--points N``, ``--start S``): for SIGINT and SIGTERM and each of N evenly spaced
   moments from S to 1.1 × the run's measured wall time (``--start 0.85`` packs them around the
   final swap), a fresh copy of an earlier run folder is rerun into (8 frames, seed 3 → 8 frames,
   seed 1) and the signal is sent at that moment.
2. **Random moments** (``--random N``, ``--seed``): the same with N moments and signals drawn at
   random (SIGINT or SIGTERM, moment uniform in 0 … 1.1 × the wall time).
3. **Concurrent runs** (``--concurrent N``): two reruns (seeds 1 and 2) into the same copy, the
   second started after a random delay, and in every other case a random signal to one of them;
   plus, every third case, a run into ``new/b`` (a folder it creates) stopped by SIGTERM while a
   second run writes ``new/a``: ``new/`` and ``new/a`` must survive.

Beside every output folder lie files that only look like our temporaries (``.NAME.backup.tmp``,
``.NAME.12345.tmp``, ``.NAME.99999-0123abcd.tmp``) and a sibling folder of the user's: each must
be byte-identical afterwards (**deletes**).  A process that has not ended 300 s after the signal is
a **hang**.  Every outcome must be one of:

* ``earlier``: the folder is byte-identical to the earlier run, exit 130 (SIGINT) or 143 (SIGTERM)
  — or killed by that signal before Python had set up its handlers — and at most one stderr line,
  no traceback;
* ``new``: the folder holds a complete new run (its files are exactly those its summary lists,
  plus report.html), no temporary, exit 0 or the interrupt code with a line saying the new results
  were written; for two runs, the folder holds one of them, each process's line is true of it.

Anything else is counted as ``WRONG`` (the reason is printed).  Usage::

    python benchmarks/interrupt_sweep.py [--points 26] [--start 0.85] [--random 20] [--concurrent 10] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
ENV = {**os.environ, "PYTHONPATH": str(SRC)}
DEMO = [sys.executable, "-m", "kalmansfm", "demo", "--frames", "8", "--quiet"]
LOOK_ALIKES = (".{name}.backup.tmp", ".{name}.12345.tmp", ".{name}.99999-0123abcd.tmp")
HANG_S = 300


def default_sigint() -> None:
    """In the child: Ctrl-C acts, even when this script was started in the background (which ignores SIGINT)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def snapshot(folder: Path) -> dict[str, bytes]:
    if not folder.exists():
        return {}
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def plant(folder: Path) -> None:
    """Put the user's files beside ``folder`` that a run must never touch."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    for pattern in LOOK_ALIKES:
        entry = folder.parent / pattern.format(name=folder.name)
        entry.mkdir(exist_ok=True)
        (entry / "precious.txt").write_text(f"the user's file in {entry.name}")
    mine = folder.parent / "users-notes"
    mine.mkdir(exist_ok=True)
    (mine / "notes.txt").write_text("the user's notes")


def planted_names(folder: Path) -> list[str]:
    return [pattern.format(name=folder.name) for pattern in LOOK_ALIKES]


def planted_intact(folder: Path) -> bool:
    for name in planted_names(folder):
        if (folder.parent / name / "precious.txt").read_text() != f"the user's file in {name}":
            return False
    return (folder.parent / "users-notes" / "notes.txt").read_text() == "the user's notes"


def leftovers(folder: Path) -> list[str]:
    planted = set(planted_names(folder))
    return [p.name for p in folder.parent.iterdir() if p.name.startswith(f".{folder.name}.") and p.name not in planted]


def run_of(folder: Path) -> str | None:
    """``seed N`` of the complete demo run in ``folder``, or None when it is not one complete run."""
    try:
        summary = json.loads((folder / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    present = {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}
    if present - {"report.html"} != set(summary["files"]) or summary["tracking"]["frames"] != 8:
        return None
    return summary["input"].split("(")[1].split(",")[0]  # "built-in scene (seed 1, 8 frames)" -> "seed 1"


def one_line(err: str) -> bool:
    lines = [line for line in err.splitlines() if line.strip() and "\r" not in line]
    return "Traceback" not in err and len(lines) <= 1


def said_written(code: int, err: str, sent: int | None) -> bool:
    return code == 0 or (sent is not None and code == 128 + sent and "new results were written" in err)


def stopped(code: int, sent: int | None) -> bool:
    return sent is not None and code in (128 + sent, -sent)


def classify(folder: Path, earlier: dict[str, bytes], code: int, err: str, sent: int) -> tuple[str, str]:
    if leftovers(folder):
        return "WRONG", f"left {leftovers(folder)}"
    if not planted_intact(folder):
        return "WRONG", "deleted a file of the user's beside the folder"
    if not one_line(err):
        return "WRONG", "more than one line or a traceback"
    if folder.exists() and snapshot(folder) == earlier:
        return ("earlier", "") if stopped(code, sent) else ("WRONG", "the earlier run, but the exit code says otherwise")
    if run_of(folder) == "seed 1" and said_written(code, err, sent):
        return "new", ""
    return "WRONG", f"folder {run_of(folder)!r}, exit {code}"


def start(argv: list[str]) -> subprocess.Popen:
    return subprocess.Popen(argv, env=ENV, preexec_fn=default_sigint, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def finish(process: subprocess.Popen) -> tuple[int | None, str]:
    try:
        _, err = process.communicate(timeout=HANG_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
        return None, "HANG"
    return process.returncode, err


def signal_case(work: Path, base: Path, earlier: dict[str, bytes], tag: str, sent: signal.Signals,
                moment: float) -> tuple[str, str, int | None, str]:
    folder = work / tag / "run"
    shutil.copytree(base, folder)
    plant(folder)
    process = start([*DEMO, "--seed", "1", "--out", str(folder)])
    time.sleep(moment)
    process.send_signal(sent)
    code, err = finish(process)
    if code is None:
        return "HANG", "no end 300 s after the signal", None, ""
    outcome, why = classify(folder, earlier, code, err, int(sent))
    shutil.rmtree(work / tag, ignore_errors=True)
    return outcome, why, code, err


def concurrent_case(work: Path, base: Path, earlier: dict[str, bytes], k: int, wall: float,
                    rng: random.Random) -> tuple[str, str]:
    folder = work / f"concurrent-{k}" / "run"
    shutil.copytree(base, folder)
    plant(folder)
    first = start([*DEMO, "--seed", "1", "--out", str(folder)])
    time.sleep(rng.uniform(0.0, wall))
    second = start([*DEMO, "--seed", "2", "--out", str(folder)])
    sent = None
    if k % 2:
        sent = rng.choice([signal.SIGINT, signal.SIGTERM])
        target = rng.choice([first, second])
        time.sleep(rng.uniform(0.0, wall))
        target.send_signal(sent)
    results = {}
    for name, process in (("seed 1", first), ("seed 2", second)):
        code, err = finish(process)
        if code is None:
            return "HANG", f"{name} did not end"
        got = int(sent) if sent is not None and process is target else None
        results[name] = (code, err, got)
    if leftovers(folder):
        return "WRONG", f"left {leftovers(folder)}"
    if not planted_intact(folder):
        return "WRONG", "deleted a file of the user's beside the folder"
    for name, (code, err, got) in results.items():
        if not one_line(err):
            return "WRONG", f"{name}: more than one line or a traceback: {err!r}"
        if got is None and code != 0:
            return "WRONG", f"{name}: exit {code} without a signal: {err.strip()}"
        if got is not None and not (said_written(code, err, got) or stopped(code, got)):
            return "WRONG", f"{name}: exit {code} after signal {got}"
    final = run_of(folder)
    writers = [name for name, (code, err, got) in results.items() if said_written(code, err, got)]
    if final is None:
        outcome = ("earlier", "") if snapshot(folder) == earlier and not writers else ("WRONG", "not one complete run")
    elif final in writers:
        outcome = ("new", "")
    else:
        outcome = ("WRONG", f"the folder holds {final}, but only {writers} said they wrote it")
    shutil.rmtree(work / f"concurrent-{k}", ignore_errors=True)
    return outcome


def parents_case(work: Path, k: int, wall: float, rng: random.Random) -> tuple[str, str]:
    """``demo --out new/b`` stopped while ``demo --out new/a`` writes: new/ and new/a must survive, the line be true."""
    root = work / f"parents-{k}"
    first = start([*DEMO, "--seed", "1", "--out", str(root / "new" / "b")])
    time.sleep(rng.uniform(0.0, 0.5 * wall))
    second = start([*DEMO, "--seed", "2", "--out", str(root / "new" / "a")])
    time.sleep(rng.uniform(0.5 * wall, 1.2 * wall))
    first.send_signal(signal.SIGTERM)
    code_b, err_b = finish(first)
    code_a, _ = finish(second)
    if code_a is None or code_b is None:
        return "HANG", "a run did not end"
    if code_a != 0 or run_of(root / "new" / "a") != "seed 2":
        return "WRONG", f"new/a: exit {code_a}, folder {run_of(root / 'new' / 'a')!r}"
    b = root / "new" / "b"
    if said_written(code_b, err_b, int(signal.SIGTERM)):
        outcome = ("new", "") if run_of(b) == "seed 1" else ("WRONG", "new/b said written but is not complete")
    elif "earlier results were left as they were" in err_b and not b.exists():
        outcome = ("earlier", "")
    else:
        outcome = ("WRONG", f"new/b: exit {code_b}, {err_b.strip()!r}, exists {b.exists()}")
    if leftovers(b) or leftovers(root / "new" / "a"):
        outcome = ("WRONG", f"left {leftovers(b) + leftovers(root / 'new' / 'a')}")
    shutil.rmtree(root, ignore_errors=True)
    return outcome


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=26, help="evenly spaced moments per signal (0: none)")
    parser.add_argument("--start", type=float, default=0.0, help="first moment, as a fraction of the wall time")
    parser.add_argument("--random", type=int, default=0, help="cases with a random signal at a random moment")
    parser.add_argument("--concurrent", type=int, default=0, help="cases of two runs into one folder")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random moments")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    work = Path(tempfile.mkdtemp(prefix="kalmansfm-sweep-"))
    base = work / "earlier"
    subprocess.run([*DEMO, "--out", str(base), "--seed", "3"], env=ENV, check=True, capture_output=True)
    earlier = snapshot(base)
    timed = work / "timed"
    shutil.copytree(base, timed)
    started = time.perf_counter()
    subprocess.run([*DEMO, "--seed", "1", "--out", str(timed)], env=ENV, check=True, capture_output=True)
    wall = time.perf_counter() - started
    print(f"load average {os.getloadavg()[0]:.2f}; one rerun takes {wall:.2f} s")
    counts: dict[str, int] = {}

    def record(part: str, outcome: str, why: str, detail: str) -> None:
        counts[outcome] = counts.get(outcome, 0) + 1
        print(f"{part:44s} {outcome:7s} {why or detail}"[:200])

    cases = [(sent, wall * (args.start + (1.1 - args.start) * k / max(args.points - 1, 1)))
             for sent in (signal.SIGINT, signal.SIGTERM) for k in range(args.points)]
    cases += [(rng.choice([signal.SIGINT, signal.SIGTERM]), rng.uniform(0.0, 1.1 * wall)) for _ in range(args.random)]
    for k, (sent, moment) in enumerate(cases):
        outcome, why, code, err = signal_case(work, base, earlier, f"signal-{k}", sent, moment)
        last = err.strip().splitlines()[-1] if err.strip() else ""
        record(f"{sent.name:7s} at {moment:6.2f} s  exit {code}", outcome, why, last)
        if outcome != "new" and outcome != "earlier":
            print("    stderr:", repr(err[-1500:]))
    for k in range(args.concurrent):
        outcome, why = concurrent_case(work, base, earlier, k, wall, rng)
        record(f"two runs, {'a signal' if k % 2 else 'no signal'} ({k})", outcome, why, "")
        if k % 3 == 0:
            outcome, why = parents_case(work, k, wall, rng)
            record(f"new/b stopped while new/a is written ({k})", outcome, why, "")
    print("outcomes:", ", ".join(f"{name} {n}" for name, n in sorted(counts.items())))
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
