"""Factorization on the real data sets in ../shared/data; prints the numbers quoted in docs/factorization.md.

Usage::

    PYTHONPATH=src python benchmarks/real_data_factorization.py [--figures docs/figures]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import scipy.io

from kalmansfm import NotEnoughDataError
from kalmansfm.report.plot_structure import plot_structure
from kalmansfm.scenes import report_tracks
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
    print(f"{name}: method {rec.method} ({rec.iterations} it.), singular values {rec.singular_values[:5]}, "
          f"residual {rec.residual_rms:.4f} px; {rows_quality(rec.motion)}")
    for w in rec.warnings:
        print(f"    warning: {w}")
    if figures is not None:
        ids = np.arange(len(rec.points)) if ids is None else ids
        plot_structure(rec.points, ids, figures / f"structure_{name}.png", title=name)


def house_labels() -> np.ndarray:
    folder = DATA / "cmu_house" / "labels"
    return np.stack([np.loadtxt(folder / f"house{f + 1}") for f in range(111)]) - 1.0


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--figures", type=Path, default=None)
    args = parser.parse_args()
    if args.figures:
        args.figures.mkdir(parents=True, exist_ok=True)

    print("== report tracks (9 points, 30 frames)")
    tracks = report_tracks()
    rec = factorize(tracks.positions)
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
        print(f"  30% missing (seed {seed}): {rec.iterations} ALS it., residual {rec.residual_rms:.4f} px, "
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
    print(f"  the {seven.sum()} points seen in all 10 views alone: residual {rec7.residual_rms:.3f} px, "
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


if __name__ == "__main__":
    main()
