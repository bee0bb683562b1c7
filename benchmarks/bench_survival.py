"""Forward–backward verified track survival on real footage: both matchers vs OpenCV's pyramidal LK, same run.

Run from the repository root:

    python benchmarks/bench_survival.py [--points N] [--quick]

For each clip, every tracker starts from the same corners of the first frame
(Shi–Tomasi, N = 200 by default, quality 0.01, 10 px apart, 5 px from the border).  A
track *survives* only if

1. it is still measured in the last frame (LK: status 1 throughout), inside the image;
2. the same tracker, run on the reversed clip from that last position, still measures
   it in the first frame, within 1 px of where it started.

One table per clip: the share of the start points alive (measured) at the end, the
forward–backward verified survival, the median closure distance of the tracks that
came back, frames per second of the forward run (CPU time, one core:
cv2.setNumThreads(1), OMP/OPENBLAS/MKL threads 1), and survival ÷ LK's in the same
run.  LK runs with OpenCV's defaults (21×21 window, 3 pyramid levels), started at the
previous position; an LK track ends at its first status 0.  ``--quick`` skips the whole
of slow.flv (656 frames); ``--why`` adds, per clip, the rejection that began the last
miss of each differential track not measured in the last frame, and what became of the
tracks that LK verifies and the differential matcher does not: ended in the forward run
(by which rejection), left the image, ended in the backward run (by which rejection), or
came back more than 1 px from their start (closure 1–2 px or more than 2 px).
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
from kalmansfm.tracking import _differential_step as differential_step_module  # noqa: E402
from kalmansfm.tracking.detect import detect_corners  # noqa: E402
from kalmansfm.tracking.differential import REJECTION_NAMES  # noqa: E402
from kalmansfm.tracking.tracker import Tracker  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
CLOSURE_PX = 1.0


def run_lk(frames: list[np.ndarray], points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Plain pyramidal LK from ``points``: (positions (F, P, 2), measured in the last frame (P,), CPU seconds)."""
    current = np.asarray(points, np.float32).reshape(-1, 1, 2)
    alive = np.ones(len(points), bool)
    start = time.process_time()
    for k in range(1, len(frames)):
        current, status, _ = cv2.calcOpticalFlowPyrLK(frames[k - 1], frames[k], current, None)
        alive &= status[:, 0] == 1
    seconds = time.process_time() - start
    return np.where(alive[:, None], current[:, 0], np.nan).astype(np.float64), alive, seconds


def run_kalman(frames: list[np.ndarray], points: np.ndarray, matcher: str) -> tuple[np.ndarray, np.ndarray, float]:
    """The tracker with ``matcher``: (last positions (P, 2), measured in the last frame (P,), CPU seconds)."""
    tracker = Tracker(points, matcher=matcher)
    start = time.process_time()
    for frame in frames:
        estimate = tracker.feed(frame)
    seconds = time.process_time() - start
    # The last frame lists the tracks still present, by id (the ids are 0 … P-1, the rows of points).
    last = np.full((len(points), 2), np.nan)
    measured = np.zeros(len(points), bool)
    last[estimate.track_ids] = estimate.positions
    measured[estimate.track_ids] = estimate.status == 1
    return np.where(measured[:, None], last, np.nan), measured, seconds


def inside(positions: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    height, width = shape
    x, y = positions[:, 0], positions[:, 1]
    with np.errstate(invalid="ignore"):
        return (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)


def survival(frames: list[np.ndarray], points: np.ndarray, tracker: str) -> dict:
    """Alive at the end, forward–backward verified survival, median closure (px), forward frames/s and which tracks are verified (P,) of one tracker."""
    run = run_lk if tracker == "LK" else (lambda f, p: run_kalman(f, p, tracker))
    end, measured, seconds = run(frames, points)
    alive = measured & inside(end, frames[0].shape)
    came_back = np.zeros(len(points), bool)
    closure = np.full(len(points), np.nan)
    if alive.any():
        back, back_measured, _ = run(frames[::-1], end[alive])
        distance = np.linalg.norm(back - points[alive], axis=1)
        closure[alive] = np.where(back_measured, distance, np.nan)
        came_back[alive] = back_measured & (distance <= CLOSURE_PX)
    return {
        "alive": float(alive.mean()),
        "survival": float(came_back.mean()),
        "closure": float(np.nanmedian(closure)) if np.isfinite(closure).any() else float("nan"),
        "fps": len(frames) / max(seconds, 1e-9),
        "verified": came_back,
    }


def _last_miss_reasons(frames: list[np.ndarray], points: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The differential matcher from ``points``, instrumented: (last positions, measured in the last frame, and per
    track the rejection that began its last miss, "" where it is measured in the last frame).

    The tracker's steps are wrapped to read each frame's rejection codes; the tracking itself is unchanged.
    """
    codes: dict[int, list[int]] = {}
    matcher = differential_step_module.DifferentialMatcher
    step, measure = matcher.step, matcher._measure

    def recording_step(self, frame, kf, rows):
        self._recording_ids = rows.ids
        try:
            return step(self, frame, kf, rows)
        finally:
            self._recording_ids = None

    def recording_measure(self, *args, **kwargs):
        result = measure(self, *args, **kwargs)
        ids = getattr(self, "_recording_ids", None)
        if ids is not None:
            for track_id, code in zip(ids.tolist(), result.rejection.tolist()):
                codes.setdefault(track_id, []).append(code)
        return result

    matcher.step, matcher._measure = recording_step, recording_measure
    try:
        end, measured, _ = run_kalman(frames, points, "differential")
    finally:
        matcher.step, matcher._measure = step, measure
    reasons = []
    for track_id in range(len(points)):
        if measured[track_id]:
            reasons.append("")
            continue
        history = codes.get(track_id, [])
        accepted = [k for k, code in enumerate(history) if code == 0]
        misses = history[accepted[-1] + 1:] if accepted else history
        reasons.append(REJECTION_NAMES[misses[0]] if misses else "never measured")
    return end, measured, reasons


def _counted(names: list[str]) -> str:
    counts: dict[str, int] = {}
    for name in names:
        counts[name] = counts.get(name, 0) + 1
    return ", ".join(f"{name} {count}" for name, count in sorted(counts.items(), key=lambda item: (-item[1], item[0]))) or "none"


def why_ended(frames: list[np.ndarray], points: np.ndarray, lk_verified: np.ndarray | None = None) -> str:
    """Why the differential matcher's tracks are not measured in the last frame (the rejection that began their
    last miss), and, given LK's verified tracks, why it does not verify tracks that LK verifies.

    A track that LK verifies and the differential matcher does not is classed by what happened to it: ended in
    the forward run (by the rejection that began its last miss), measured at the end but outside the image,
    ended in the backward run (likewise), or back in the first frame but more than 1 px from its start
    (closure 1–2 px or > 2 px).
    """
    end, measured, reasons = _last_miss_reasons(frames, points)
    lines = [
        f"differential: {int((~measured).sum())} tracks not measured in the last frame; the rejection that began their "
        f"last miss: {_counted([r for r in reasons if r])}"
    ]
    if lk_verified is None:
        return lines[0]
    alive = measured & inside(end, frames[0].shape)
    outcome = ["" for _ in range(len(points))]
    for track_id in np.flatnonzero(measured & ~alive).tolist():
        outcome[track_id] = "left the image"
    for track_id in np.flatnonzero(~measured).tolist():
        outcome[track_id] = f"ended forward ({reasons[track_id]})"
    if alive.any():
        rows = np.flatnonzero(alive)
        back, back_measured, back_reasons = _last_miss_reasons(frames[::-1], end[alive])
        distance = np.linalg.norm(back - points[alive], axis=1)
        for j, track_id in enumerate(rows.tolist()):
            if not back_measured[j]:
                outcome[track_id] = f"ended backward ({back_reasons[j]})"
            elif not distance[j] <= CLOSURE_PX:
                outcome[track_id] = "closure 1-2 px" if distance[j] <= 2.0 else "closure > 2 px"
    lost = np.flatnonzero(lk_verified & np.array([bool(o) for o in outcome])).tolist()
    gained = int((~lk_verified & np.array([not o for o in outcome]) & alive).sum())
    lines.append(
        f"differential against LK: {len(lost)} tracks that LK verifies are not verified ({_counted([outcome[t] for t in lost])}); "
        f"{gained} verified that LK does not verify"
    )
    return "\n".join(lines)


def clip_table(label: str, frames: list[np.ndarray], n_points: int, why: bool = False) -> list[str]:
    points = detect_corners(frames[0], n_points, 0.01, 10.0, border_px=5)
    height, width = frames[0].shape
    results = {name: survival(frames, points, name) for name in ("differential", "search", "LK")}
    lk = results["LK"]["survival"]
    lines = [
        f"\n{label}: {width}×{height}, {len(frames)} frames, {len(points)} start corners",
        "",
        "| tracker | measured at the end | forward–backward verified survival | median closure px | frames/s CPU | survival ÷ LK |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        shown = "Kalman, differential (default)" if name == "differential" else ("Kalman, search (--matcher search)" if name == "search" else "OpenCV LK 21×21, 3 levels")
        ratio = r["survival"] / lk if lk > 0 else float("nan")
        lines.append(
            f"| {shown} | {100 * r['alive']:.1f} % | {100 * r['survival']:.1f} % | {r['closure']:.2f} | {r['fps']:.0f} | {ratio:.2f} |"
        )
    if why:
        lines += ["", why_ended(frames, points, results["LK"]["verified"])]
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=200, help="corners detected in the first frame")
    parser.add_argument("--quick", action="store_true", help="skip the whole of slow.flv")
    parser.add_argument("--why", action="store_true", help="per clip, why the differential matcher's tracks ended (rejection codes), and why it misses tracks that LK verifies")
    args = parser.parse_args()
    clips = [
        ("cmu_hotel", DATA / "cmu_hotel" / "images", None),
        ("tree.avi", DATA / "opencv_samples" / "tree.avi", None),
        ("slow.flv, first 100 frames", DATA / "opencv_samples" / "slow.flv", 100),
    ]
    if not args.quick:
        clips.append(("slow.flv, all frames", DATA / "opencv_samples" / "slow.flv", None))
    lines = [f"forward–backward verified survival (closure ≤ {CLOSURE_PX:g} px); load average {os.getloadavg()[0]:.1f}"]
    # Load the compiled kernels (numba's cache) before anything is timed.
    warm = [np.random.default_rng(0).integers(0, 255, (64, 64), dtype=np.uint8)] * 3
    run_kalman(warm, np.array([[32.0, 32.0]]), "differential")
    for label, path, limit in clips:
        if not path.exists():
            print(f"skipped {label}: {path} not found", file=sys.stderr)
            continue
        frames = list(read_frames(path))
        lines += clip_table(label, frames[:limit] if limit else frames, args.points, args.why)
    print("\n".join(lines))
    print(f"\none core (cv2.setNumThreads(1), OMP/OPENBLAS/MKL threads 1); load average {os.getloadavg()[0]:.1f} at the end", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
