"""Kalman-gated template tracker vs OpenCV pyramidal Lucas–Kanade, side by side, on one core.

Run from the repository root:

    PYTHONPATH=src /work/venv/bin/python benchmarks/bench_tracker.py [--quick]

Prints one table: accuracy against ground truth where there is some (the built-in
scene, cmu_house's hand labels), track survival, and frames per second of the
tracking loop alone (frames already decoded).  LK starts from the same points,
with OpenCV's defaults (21×21 window, 3 pyramid levels); an LK track ends at its
first status 0.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

from kalmansfm.io.frames import read_frames  # noqa: E402
from kalmansfm.scenes import Occluder, render_scene  # noqa: E402
from kalmansfm.tracking.detect import detect_corners  # noqa: E402
from kalmansfm.tracking.tracker import Tracker  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def run_kalman(frames, points, **options):
    tracker = Tracker(points, **options)
    start = time.perf_counter()
    for frame in frames:
        tracker.feed(frame)
    seconds = time.perf_counter() - start
    tracks = tracker.result()
    return tracks.positions, tracks.alive, len(frames) / seconds


def run_lk(frames, points):
    points = np.asarray(points, np.float32).reshape(-1, 1, 2)
    positions = np.full((len(frames), len(points), 2), np.nan)
    alive = np.zeros((len(frames), len(points)), bool)
    positions[0], alive[0] = points[:, 0], True
    start = time.perf_counter()
    current = points
    for k in range(1, len(frames)):
        current, status, _ = cv2.calcOpticalFlowPyrLK(frames[k - 1], frames[k], current, None)
        alive[k] = alive[k - 1] & (status[:, 0] == 1)
        positions[k] = np.where(alive[k][:, None], current[:, 0], np.nan)
    seconds = time.perf_counter() - start
    return positions, alive, len(frames) / seconds


def accuracy(positions, truth, valid, within):
    error = np.linalg.norm(positions - truth, axis=2)[valid]
    error = np.where(np.isnan(error), np.inf, error)
    finite = error[np.isfinite(error)]
    rms = float(np.sqrt(np.mean(finite**2))) if finite.size else float("nan")
    return rms, float(np.median(error)), float(np.mean(error <= within))


def row(name, tracker, rms, median, within, within_px, survival, fps):
    cells = [name, tracker, f"{rms:.2f}" if rms == rms else "-", f"{median:.2f}" if median == median else "-",
             f"{100 * within:.1f} % ≤ {within_px:g} px" if within == within else "-", f"{100 * survival:.0f} %", f"{fps:.0f}"]
    return "| " + " | ".join(cells) + " |"


def textured_sequence(width, height, n_frames, seed=0):
    rng = np.random.default_rng(seed)
    world = cv2.GaussianBlur(rng.uniform(0, 255, (height + 120, width + 240)).astype(np.float32), (0, 0), 2.0)
    world = cv2.normalize(world, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return [world[60 : 60 + height, 200 - 2 * k : 200 - 2 * k + width].copy() for k in range(n_frames)]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="skip the long real videos")
    args = parser.parse_args()
    lines = ["| sequence | tracker | RMS px | median px | within | survival | frames/s |", "|---|---|---|---|---|---|---|"]

    scene = render_scene()
    start = scene.visible[0]
    truth, visible = scene.positions[:, start], scene.visible[:, start]
    frames = list(scene.frames)
    for name, result in [("Kalman (ssd)", run_kalman(frames, truth[0])), ("Kalman (ncc)", run_kalman(frames, truth[0], score="ncc")), ("LK", run_lk(frames, truth[0]))]:
        pos, alive, fps = result
        rms, med, within = accuracy(pos, truth, visible, 2.0)
        lines.append(row("scene 320×240, 30 fr", name, rms, med, within, 2, alive[-1][visible[-1]].mean(), fps))

    occluded = render_scene(occluder=Occluder())
    start = occluded.visible[0]
    truth, visible = occluded.positions[:, start], occluded.visible[:, start]
    hidden_col = int(np.flatnonzero(np.flatnonzero(start) == Occluder().track_id)[0])
    for name, result in [("Kalman (ssd)", run_kalman(list(occluded.frames), truth[0])), ("LK", run_lk(list(occluded.frames), truth[0]))]:
        pos, alive, fps = result
        rms, med, within = accuracy(pos, truth, visible, 2.0)
        end_error = np.linalg.norm(pos[-1, hidden_col] - truth[-1, hidden_col])
        lines.append(row(f"scene + occluder (hidden marker ends {end_error:.1f} px off)", name, rms, med, within, 2, alive[-1][visible[-1]].mean(), fps))

    house = DATA / "cmu_house"
    if house.exists():
        frames = list(read_frames(house / "images"))
        labels = np.stack([np.loadtxt(house / "labels" / f"house{k + 1}") for k in range(len(frames))]) - 1.0
        everything = np.ones(labels.shape[:2], bool)
        for name, result in [("Kalman (ssd)", run_kalman(frames, labels[0])), ("Kalman (ncc)", run_kalman(frames, labels[0], score="ncc")), ("LK", run_lk(frames, labels[0]))]:
            pos, alive, fps = result
            rms, med, within = accuracy(pos, labels, everything, 3.0)
            lines.append(row("cmu_house 576×384, 111 fr, 30 labels", name, rms, med, within, 3, alive[-1].mean(), fps))

    for width, height, n in [(320, 240, 100), (640, 480, 500), (640, 480, 1000)]:
        frames = textured_sequence(width, height, 40)
        points = detect_corners(frames[0], n, 0.001, 5.0, border_px=40)
        for name, result in [("Kalman (ssd)", run_kalman(frames, points)), ("LK", run_lk(frames, points))]:
            pos, alive, fps = result
            lines.append(row(f"speed {width}×{height}, {len(points)} features", name, float("nan"), float("nan"), float("nan"), 0, alive[-1].mean(), fps))

    real = [("cmu_hotel", DATA / "cmu_hotel" / "images"), ("tree.avi", DATA / "opencv_samples" / "tree.avi")]
    if not args.quick:
        real.append(("slow.flv", DATA / "opencv_samples" / "slow.flv"))
    for label, path in real:
        if not path.exists():
            continue
        frames = list(read_frames(path))
        points = detect_corners(frames[0], 200, 0.01, 10.0, border_px=5)
        h, w = frames[0].shape
        for name, result in [("Kalman (ssd)", run_kalman(frames, points)), ("Kalman (ncc)", run_kalman(frames, points, score="ncc")), ("LK", run_lk(frames, points))]:
            pos, alive, fps = result
            lines.append(row(f"{label} {w}×{h}, {len(frames)} fr, {len(points)} corners", name, float("nan"), float("nan"), float("nan"), 0, alive[-1].mean(), fps))

    print("\n".join(lines))
    print(f"\none core (cv2.setNumThreads(1), OMP/OPENBLAS threads 1); {os.cpu_count()} CPUs on the machine, shared", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
