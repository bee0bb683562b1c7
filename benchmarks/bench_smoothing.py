"""Filtered vs RTS-smoothed tracks on the built-in scene: tracking error and factorization shape error.

Run from the repository root:

    python benchmarks/bench_smoothing.py [--seeds 10] [--frames 30]

For each seed the scene is rendered three times: plain; with the default occluder card
(``Occluder()``: it hides track 0 in frames 10–12, track 1 in 20–23 — one frame more than
the tracker coasts, so that track is lost — and track 6 in 24–26); and with a small card
(``Occluder(track_id=2, height_px=12)``) that hides track 2 alone in frames 10–12.
the frame-0 visible corners are tracked as ``run_demo`` does, and the tracks are
scored as filtered, fixed-interval smoothed and fixed-lag smoothed (lag 3):

* measured: frames where the tracker measured a visible corner (``compare_with_truth``);
* coasting: frames where a track coasted (status "predicted"), against the true position;
* shape error: the weighted factorization of the measured positions (``factorize_tracks``,
  as ``kalmansfm demo``), RMS after similarity alignment in % of the object's radius;
  "unweighted" factorizes the same positions with equal weights.

The table pools the (frame, track) errors of all seeds; the last columns count the seeds
where the smoothed shape error is lower than the filtered one.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402

import numpy as np  # noqa: E402

from kalmansfm.errors import NotEnoughDataError  # noqa: E402
from kalmansfm.pipeline import compare_with_truth, factorize_tracks  # noqa: E402
from kalmansfm.scenes import Occluder, render_scene  # noqa: E402
from kalmansfm.tracking import track  # noqa: E402
from kalmansfm.tracking.smoothing import smooth_tracks  # noqa: E402
from kalmansfm.tracking.tracks import MEASURED, PREDICTED  # noqa: E402

VARIANTS = ("filtered", "smoothed", "fixed lag 3")


def shape_error(tracks, scene, weighted: bool) -> float:
    try:
        reconstruction = factorize_tracks(tracks, weighted=weighted)
    except NotEnoughDataError:
        return float("nan")
    value = compare_with_truth(tracks, reconstruction, scene.ground_truth()).shape_error_pct
    return float("nan") if value is None else float(value)


def errors(tracks, scene):
    """Position errors (px) on measured-and-visible frames and on coasting frames."""
    column = {int(t): p for p, t in enumerate(scene.track_ids)}
    cols = np.array([column[int(t)] for t in tracks.track_ids])
    truth, visible = scene.positions[:, cols], scene.visible[:, cols]
    error = np.linalg.norm(tracks.positions - truth, axis=-1)
    return error[(tracks.status == MEASURED) & visible], error[tracks.status == PREDICTED]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="seeds 0 … N-1")
    parser.add_argument("--frames", type=int, default=30)
    args = parser.parse_args()

    rows = {}
    scenes = (("plain", None), ("default card", Occluder()), ("small card", Occluder(track_id=2, height_px=12.0)))
    for label, occluder in scenes:
        pooled = {v: {"measured": [], "coasting": [], "weighted": [], "unweighted": []} for v in VARIANTS}
        for seed in range(args.seeds):
            scene = render_scene(n_frames=args.frames, seed=seed, occluder=occluder)
            first = scene.visible[0]
            filtered = track(list(scene.frames), scene.positions[0, first], track_ids=scene.track_ids[first])
            results = {"filtered": filtered, "smoothed": smooth_tracks(filtered),
                       "fixed lag 3": smooth_tracks(filtered, lag=3)}
            for variant, tracks in results.items():
                measured, coasting = errors(tracks, scene)
                pooled[variant]["measured"].append(measured)
                pooled[variant]["coasting"].append(coasting)
                pooled[variant]["weighted"].append(shape_error(tracks, scene, weighted=True))
                pooled[variant]["unweighted"].append(shape_error(tracks, scene, weighted=False))
        rows[label] = pooled

    header = ("| scene (seeds 0–{}, {} frames) | tracks | measured RMS px | measured ≤ 2 px | coasting RMS px "
              "| coasting ≤ 2 px | coasting frames | shape error % (weighted) | shape error % (unweighted) "
              "| seeds better (w / u) |").format(args.seeds - 1, args.frames)
    print(header)
    print("|---" * 10 + "|")
    for label, pooled in rows.items():
        base_w = np.array(pooled["filtered"]["weighted"])
        base_u = np.array(pooled["filtered"]["unweighted"])
        for variant in VARIANTS:
            p = pooled[variant]
            measured = np.concatenate(p["measured"])
            coasting = np.concatenate(p["coasting"])
            w, u = np.array(p["weighted"]), np.array(p["unweighted"])
            better = "" if variant == "filtered" else f"{int(np.sum(w < base_w))} / {int(np.sum(u < base_u))}"
            coast_rms = f"{np.sqrt(np.mean(coasting**2)):.3f}" if coasting.size else "–"
            coast_within = f"{np.mean(coasting <= 2.0):.1%}" if coasting.size else "–"
            print(f"| {label} | {variant} | {np.sqrt(np.mean(measured**2)):.3f} | {np.mean(measured <= 2.0):.1%} "
                  f"| {coast_rms} | {coast_within} | {coasting.size} | {np.nanmean(w):.3f} (median {np.nanmedian(w):.3f}) "
                  f"| {np.nanmean(u):.3f} (median {np.nanmedian(u):.3f}) | {better} |")


if __name__ == "__main__":
    main()
