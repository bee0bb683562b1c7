"""Tracker failure modes on the built-in scene: identity kept, track ended, or silent swap — rates over seeds.

Three cases, each on the scene rendered with several seeds (textures and noise
change with the seed, the geometry does not):

* ``exit``      — ``scenario="exit"``: the object accelerates out through the left
  border; every marker that leaves is a subject.
* ``occlusion`` — ``Occluder(track_id=2, first_frame=10, n_frames=6)``: a card hides
  marker 2 for 6 frames, longer than ``max_misses`` (3) + 1.
* ``crossing``  — the same card with its own marker (``marker=True``), which passes
  over the hidden marker 2: two markers cross.

Every tracker frame with status *measured* is scored against the ground truth of
the track's own corner.  A subject track is

Subjects are the tracks whose marker disappears (leaves the image or goes under the
card); the tracks whose marker stays visible are counted separately.

* **kept** if every measured position is within ``--tolerance`` px of its own corner;
* **ended** if it was lost (status 3, then 0) with no wrong measurement before;
* **swapped** if any measured position is farther than the tolerance from its own
  corner (the tracker silently reports another point under this identity).

Run::

    python benchmarks/bench_failure_modes.py --seeds 20
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from kalmansfm.scenes import Occluder, render_scene
from kalmansfm.tracking.tracker import track

LOST = 3
MEASURED = 1
CASES = ("exit", "occlusion", "crossing")


@dataclass(frozen=True)
class Outcome:
    """One subject track of one run."""

    case: str
    seed: int
    track_id: int
    verdict: str  # kept / ended / swapped
    subject: bool  # its marker disappears at some frame
    worst_error_px: float
    lost_at: int | None


def render(case: str, seed: int):
    if case == "exit":
        return render_scene(seed=seed, scenario="exit")
    marker = case == "crossing"
    return render_scene(seed=seed, occluder=Occluder(track_id=2, first_frame=10, n_frames=6, marker=marker))


def subjects(scene) -> np.ndarray:
    """Track ids whose marker disappears at some frame after being tracked from frame 0.

    exit: the markers that leave the image; occlusion/crossing: marker 2 and every other
    marker the card passes over (the default scene has no self-occlusion in these frames).
    """
    return scene.track_ids[scene.visible[0] & ~scene.visible.all(axis=0)]


def classify(scene, tracks, track_id: int, tolerance_px: float) -> tuple[str, float, int | None]:
    column = int(np.flatnonzero(tracks.track_ids == track_id)[0])
    truth = scene.positions[:, int(np.flatnonzero(scene.track_ids == track_id)[0])]
    status = tracks.status[:, column]
    measured = status == MEASURED
    errors = np.linalg.norm(tracks.positions[:, column] - truth, axis=1)
    worst = float(errors[measured].max()) if measured.any() else 0.0
    lost = np.flatnonzero(status == LOST)
    lost_at = int(lost[0]) if lost.size else None
    if worst > tolerance_px:
        return "swapped", worst, lost_at
    if lost_at is not None:
        # a lost track must end: nothing after the frame of the loss
        assert not (status[lost_at + 1 :] != 0).any(), "a lost track came back"
        return "ended", worst, lost_at
    return "kept", worst, lost_at


def run_case(case: str, seed: int, tolerance_px: float = 3.0, **options) -> list[Outcome]:
    scene = render(case, seed)
    start = scene.visible[0]
    tracks = track(scene.frames, scene.positions[0, start], track_ids=scene.track_ids[start], **options)
    hidden = set(subjects(scene).tolist())
    outcomes = []
    for track_id in tracks.track_ids.tolist():
        verdict, worst, lost_at = classify(scene, tracks, track_id, tolerance_px)
        outcomes.append(Outcome(case, seed, track_id, verdict, track_id in hidden, worst, lost_at))
    return outcomes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=20, help="seeds 0 … N-1")
    parser.add_argument("--tolerance", type=float, default=3.0, help="px from the own corner that still counts as it")
    parser.add_argument("--max-misses", type=int, default=3)
    args = parser.parse_args()
    started = time.perf_counter()
    rows = [o for case in CASES for seed in range(args.seeds)
            for o in run_case(case, seed, args.tolerance, max_misses=args.max_misses)]
    print(f"{args.seeds} seeds, tolerance {args.tolerance} px, max_misses {args.max_misses}")
    print(f"{'case':<10} {'tracks':<16} {'n':>4} {'kept':>7} {'ended':>7} {'swapped':>8}  worst error kept/ended px")
    for case in CASES:
        for label, subject in (("marker disappears", True), ("always visible", False)):
            mine = [o for o in rows if o.case == case and o.subject == subject]
            if not mine:
                continue
            count = {v: sum(o.verdict == v for o in mine) for v in ("kept", "ended", "swapped")}
            honest = [o.worst_error_px for o in mine if o.verdict != "swapped"]
            print(f"{case:<10} {label:<16} {len(mine):>4} "
                  + " ".join(f"{count[v] / len(mine):>7.1%}" for v in ("kept", "ended"))
                  + f" {count['swapped'] / len(mine):>8.1%}  {max(honest) if honest else float('nan'):.2f}")
    for o in rows:
        if o.verdict == "swapped":
            kind = "hidden" if o.subject else "visible"
            print(f"  swap: {o.case} seed {o.seed} track {o.track_id} ({kind}): {o.worst_error_px:.1f} px off")
    print(f"time {time.perf_counter() - started:.1f} s")


if __name__ == "__main__":
    main()
