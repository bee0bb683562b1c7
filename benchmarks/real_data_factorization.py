"""Factorization on the real data sets in ../shared/data; prints the numbers quoted in docs/factorization.md.

Usage::

    python benchmarks/real_data_factorization.py [--figures docs/figures] [--images docs/images]

The first part factorizes the tracks and labels shipped with the data sets; the second
(``== sequences tracked by our tracker``) runs ``kalmansfm.track`` on the image sequences and
videos and factorizes the result with ``kalmansfm.pipeline.factorize_tracks``; ``--images``
writes its shape pictures (small PNGs) there. ``--skip-shipped`` runs only the second part.
"""

from __future__ import annotations

import argparse
from types import SimpleNamespace
from pathlib import Path

import numpy as np
import scipy.io

from kalmansfm import NotEnoughDataError, track
from kalmansfm.io.frames import read_frames
from kalmansfm.pipeline import factorize_tracks
from kalmansfm.experiments import report_tracks
from kalmansfm.report.figures import shape_views_figure
from kalmansfm.structure import align_affine, align_similarity, factorize

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
np.set_printoptions(precision=4, suppress=True, linewidth=140)


def rms_radius(points: np.ndarray) -> float:
    ok = np.isfinite(points).all(axis=1)
    centred = points[ok] - points[ok].mean(axis=0)
    return float(np.sqrt(np.mean(np.sum(centred**2, axis=1))))


def rows_quality(motion: np.ndarray) -> str:
    ok = np.isfinite(motion).all(axis=(1, 2))
    lengths = np.linalg.norm(motion[ok], axis=2)
    cosine = np.sum(motion[ok, 0] * motion[ok, 1], axis=1) / lengths.prod(axis=1)
    return f"row lengths {lengths.min():.4f}–{lengths.max():.4f}, max |cos(i, j)| {np.abs(cosine).max():.4f}"


def show(name: str, rec, figures: Path | None, ids=None) -> None:
    print(f"{name}: method {rec.method} ({rec.details.iterations} it.), singular values {rec.details.singular_values[:5]}, "
          f"residual {rec.reprojection_rms:.4f} px; {rows_quality(rec.motion)}")
    for w in rec.warnings:
        print(f"    warning: {w}")
    if figures is not None:
        ids = np.arange(len(rec.points)) if ids is None else ids
        finite = np.isfinite(rec.points).all(axis=1)
        (figures / f"structure_{name}.png").write_bytes(shape_views_figure(rec.points[finite], list(np.asarray(ids)[finite])))


def house_labels() -> np.ndarray:
    folder = DATA / "cmu_house" / "labels"
    return np.stack([np.loadtxt(folder / f"house{f + 1}") for f in range(111)]) - 1.0


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--figures", type=Path, default=None)
    parser.add_argument("--images", type=Path, default=None, help="folder for the tracked-sequence shape pictures")
    parser.add_argument("--skip-shipped", action="store_true", help="only the sequences tracked by our tracker")
    args = parser.parse_args()
    if args.figures:
        args.figures.mkdir(parents=True, exist_ok=True)
    if not args.skip_shipped:
        shipped(args)
    tracked_sequences(args.images)


def shipped(args: argparse.Namespace) -> None:

    print("== report tracks (9 points, 30 frames)")
    tracks = report_tracks()
    rec = factorize(tracks.observations())
    show("report_polyhedron", rec, args.figures, tracks.track_ids)
    print("points:\n", rec.points)
    # The report's recipe without centring: the rank-3 truncation then has to spend one
    # component on the translation.
    f, p = tracks.positions.shape[:2]
    w = tracks.positions.transpose(0, 2, 1).reshape(2 * f, p)
    s_uncentred = np.linalg.svd(w, compute_uv=False)
    print("uncentred W singular values:", s_uncentred[:5])

    print("\n== cmu_house labels (30 points, 111 frames)")
    house = house_labels()
    complete = factorize(house)
    show("cmu_house", complete, args.figures)
    for seed in range(3):
        holes = house.copy()
        holes[np.random.default_rng(seed).random(holes.shape[:2]) < 0.3] = np.nan
        rec = factorize(holes)
        fit = align_similarity(rec.points, complete.points, allow_reflection=True)
        print(f"  30% missing (seed {seed}): {rec.details.iterations} ALS it., residual {rec.reprojection_rms:.4f} px, "
              f"shape vs complete {fit.rms / rms_radius(complete.points):.4%} of RMS radius, warnings {rec.warnings}")

    print("\n== cmu_hotel")
    cmum = scipy.io.loadmat(DATA / "cmu_hotel" / "tracks" / "cmum.mat", squeeze_me=True, struct_as_record=False)
    hotel = np.stack([np.asarray(cmum["CMUM"].hotel.XTs[k], dtype=float).T for k in range(51)]) - 1.0
    show("cmu_hotel_landmarks", factorize(hotel), args.figures)
    klt = scipy.io.loadmat(DATA / "cmu_hotel" / "tracks" / "tracked_points.mat")
    tracks_klt = np.stack([klt["Xs"], klt["Ys"]], axis=2) - 1.0
    show("cmu_hotel_klt_all", factorize(tracks_klt), None)
    jumps = np.linalg.norm(np.diff(tracks_klt, axis=0), axis=2).max(axis=0)
    keep = jumps <= 3.0
    rec = factorize(tracks_klt[:, keep])
    print(f"  KLT tracks with a frame-to-frame jump > 3 px dropped: {int((~keep).sum())} of {keep.size}")
    show("cmu_hotel_klt", rec, args.figures)

    print("\n== oxford_model_house (10 views, 672 points, most in few views)")
    folder = DATA / "oxford_model_house"
    table = np.genfromtxt(folder / "2D" / "house.nview-corners", dtype=float, missing_values="*", filling_values=-1)
    corners = [np.loadtxt(folder / "2D" / f"house.00{v}.corners") for v in range(10)]
    positions = np.full((10, len(table), 2), np.nan)
    for v in range(10):
        seen = table[:, v] >= 0
        positions[v, seen] = corners[v][table[seen, v].astype(int)]
    truth = np.loadtxt(folder / "3D" / "house.p3d")
    print(f"  observed entries: {np.isfinite(positions[..., 0]).mean():.1%}; views per point "
          f"{np.bincount(np.isfinite(positions[..., 0]).sum(axis=0))}")
    rec = factorize(positions)
    show("oxford_model_house", rec, args.figures)
    radius = rms_radius(truth)
    ok = np.isfinite(rec.points).all(axis=1)
    affine = align_affine(rec.points, truth)
    similar = align_similarity(rec.points, truth, allow_reflection=True)
    print(f"  {ok.sum()} points reconstructed; 3D RMS radius {radius:.3f}; aligned error: "
          f"affine {affine.rms:.4f} ({affine.rms / radius:.2%}), similarity {similar.rms:.4f} ({similar.rms / radius:.2%})")
    residual_by_views = {}
    counts = np.isfinite(positions[..., 0]).sum(axis=0)
    err = np.linalg.norm(similar.aligned - truth, axis=1)
    for c in np.unique(counts):
        sel = (counts == c) & ok
        if sel.any():
            residual_by_views[int(c)] = f"{np.sqrt(np.mean(err[sel] ** 2)) / radius:.2%} (n={sel.sum()})"
    print(f"  similarity-aligned error by number of views: {residual_by_views}")
    seven = counts == 10
    rec7 = factorize(positions[:, seven])
    fit7 = align_similarity(rec7.points, truth[seven], allow_reflection=True)
    print(f"  the {seven.sum()} points seen in all 10 views alone: residual {rec7.reprojection_rms:.3f} px, "
          f"similarity error {fit7.rms / rms_radius(truth[seven]):.2%} of their RMS radius")

    print("\n== movi_house_cs231a set1 (2 views, 37 points + 3D)")
    folder = DATA / "movi_house_cs231a" / "set1"
    views = np.stack([np.loadtxt(folder / f"pt_2D_{k}.txt", skiprows=1) for k in (1, 2)])
    truth = np.loadtxt(folder / "pt_3D.txt", skiprows=1)
    try:
        factorize(views)
    except NotEnoughDataError as exc:
        print(f"  factorize: NotEnoughDataError: {exc}")
    w = views.transpose(0, 2, 1).reshape(4, -1)
    w = w - w.mean(axis=1, keepdims=True)
    u, s, vt = np.linalg.svd(w, full_matrices=False)
    affine_shape = (vt[:3].T * np.sqrt(s[:3]))
    residual = np.sqrt(s[3] ** 2 / views.shape[1])
    fit = align_affine(affine_shape, truth)
    print(f"  affine 2-view factorization: singular values {s}, rank-3 residual {residual:.3f} px RMS; "
          f"affine shape vs 3D points after best affine alignment {fit.rms:.4f} ({fit.rms / rms_radius(truth):.2%} of RMS radius)")


def tracked_row(name: str, tracks, rec, seconds: float) -> str:
    measured = tracks.measured
    sv = ", ".join(f"{v:.4g}" for v in rec.details.singular_values[:5])
    notes = "; ".join(rec.warnings) if rec.warnings else "–"
    return (f"| {name} | {tracks.positions.shape[0]} × {tracks.positions.shape[1]} | {measured.mean():.0%} | {sv} | "
            f"{rec.details.singular_values[2] / rec.details.singular_values[3]:.3g} | {rec.reprojection_rms:.3f} | "
            f"{int(np.isfinite(rec.points).all(axis=1).sum())} | {seconds:.1f} s | {notes} |")


def tracked_sequences(images: Path | None) -> None:
    """Our tracker on the real sequences, then factorize_tracks; prints a markdown table."""
    import time

    print("\n== sequences tracked by our tracker (kalmansfm.track + pipeline.factorize_tracks, weighted)")
    rows, extra = [], []
    if images is not None:
        images.mkdir(parents=True, exist_ok=True)

    def run(name: str, frames, points=None, picture: str | None = None):
        start = time.perf_counter()
        tracks = track(frames, points)
        t_track = time.perf_counter() - start
        try:
            rec = factorize_tracks(tracks)
        except NotEnoughDataError as exc:
            rows.append(f"| {name} | {tracks.positions.shape[0]} × {tracks.positions.shape[1]} | – | – | – | – | – | "
                        f"{t_track:.1f} s | factorize: {exc} |")
            return tracks, None
        rows.append(tracked_row(name, tracks, rec, t_track))
        # The same tracks restricted to those measured in every frame: closed form, no completion.
        everywhere = tracks.measured.all(axis=0)
        block = None
        if everywhere.sum() >= 4:
            block = factorize(tracks.positions[:, everywhere])
            sub = SimpleNamespace(positions=tracks.positions[:, everywhere], measured=tracks.measured[:, everywhere])
            rows.append(tracked_row(f"  same, only the {int(everywhere.sum())} tracks measured in every frame", sub,
                                    block, t_track))
        if picture and images is not None and block is not None:
            (images / picture).write_bytes(shape_views_figure(block.points, tracks.track_ids[everywhere].tolist()))
        return tracks, rec

    house_frames = list(read_frames(DATA / "cmu_house" / "images"))
    run("cmu_house, detected corners", house_frames)
    labels = house_labels()
    tracks, rec = run("cmu_house, from the 30 labels of frame 0", house_frames, labels[0],
                      picture="factorization_cmu_house_from_labels.png")
    measured = tracks.measured
    drift = np.linalg.norm(tracks.positions - labels, axis=2)
    label_rec = factorize(labels)
    fit = align_similarity(rec.points, label_rec.points, allow_reflection=True)
    extra.append(f"cmu_house from the labels: tracked vs labelled 2D positions RMS {np.sqrt(np.mean(drift[measured] ** 2)):.2f} px "
                 f"(last frame {np.sqrt(np.nanmean(np.where(measured[-1], drift[-1], np.nan) ** 2)):.2f} px, "
                 f"{measured[-1].sum()} of 30 measured); shape vs the factorization of the labels themselves: "
                 f"{fit.rms / rms_radius(label_rec.points):.2%} of the RMS radius after similarity alignment "
                 f"(labels' own residual {label_rec.reprojection_rms:.3f} px)")
    run("cmu_hotel, detected corners", list(read_frames(DATA / "cmu_hotel" / "images")),
        picture="factorization_cmu_hotel_tracked.png")
    for video, limit in (("tree.avi", None), ("slow.flv", 120)):
        frames = list(read_frames(DATA / "opencv_samples" / video))
        frames = frames if limit is None else frames[:limit]
        tracks, rec = run(f"opencv_samples/{video}" + (f" (first {limit} frames)" if limit else ""), frames)
        measured = tracks.measured
        motion = np.linalg.norm(tracks.positions - tracks.positions[:1], axis=2)
        still = np.nanmedian(np.where(measured, motion, np.nan), axis=0)
        extra.append(f"{video}: median displacement from frame 0 per track: {np.nanmedian(still):.2f} px "
                     f"(90th percentile {np.nanpercentile(still, 90):.2f} px)")
    print()
    print("| sequence | frames × tracks | measured | σ₁…σ₅ | σ₃/σ₄ | residual (px RMS) | points | tracking time | warnings |")
    print("|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        print(row)
    print()
    for line in extra:
        print(line)


if __name__ == "__main__":
    main()
