"""Calibrated reconstruction on real data and on the synthetic walk-around: the figures of docs/perspective.md.

Usage::

    python benchmarks/real_data_perspective.py                  # Oxford house and Merton I, ours vs pycolmap
    python benchmarks/real_data_perspective.py --synthetic 20   # + NEES over 20 seeded walk-arounds (2 layouts)
    python benchmarks/real_data_perspective.py --no-colmap

Oxford VGG data (``../shared/data/oxford_model_house``, ``oxford_merton1``): the tracks and the
intrinsics read off the datasets' cameras (RQ, positive diagonal) are the only input; the datasets'
points and camera centres are the reference. Errors are 3-D distances after the least-squares
similarity alignment of all reconstructed points onto the reference (a reflection allowed: the house
lives in a mirrored frame), in % of the reference's RMS radius. pycolmap's incremental mapper gets the
same tracks as matches (every pair sharing >= 15 tracks), the same intrinsics (PINHOLE, skew mapped
out of the observations, intrinsics not refined) and its default options otherwise.

Synthetic: :func:`kalmansfm.scenes.perspective.perspective_scene` (10 frames on a 40° arc, 400 points
on partial tracks, 0.7 px noise, 3 % gross outliers); NEES of the similarity-aligned points (3 dof)
and cameras (6 dof) with the reconstruction's free-network covariances, camera centre errors in % of
the viewing distance.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from kalmansfm.errors import NotEnoughDataError
from kalmansfm.io.oxford import read_oxford
from kalmansfm.scenes.perspective import perspective_scene
from kalmansfm.structure.geometry.alignment import align_similarity
from kalmansfm.structure.perspective.bundle import compare_in_gauge
from kalmansfm.structure.perspective.reconstruct import reconstruct_perspective
from kalmansfm.structure.geometry.pinhole import decompose_projection

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / ".." / "shared" / "data"


def load(name: str):
    data = read_oxford(DATA / name)
    pose = decompose_projection(data.cameras.matrices)
    return data, pose


def score(points: np.ndarray, centres: np.ndarray | None, reference: np.ndarray, ref_centres: np.ndarray) -> dict:
    ok = np.isfinite(points).all(axis=1)
    al = align_similarity(points[ok], reference[ok], allow_reflection=True)
    radius = np.sqrt(np.mean(np.sum((reference - reference.mean(axis=0)) ** 2, axis=1)))
    err = np.linalg.norm(al.aligned - reference[ok], axis=1) / radius * 100
    out = dict(points=f"{ok.sum()}/{len(ok)}", median=np.median(err), p95=np.percentile(err, 95),
               rms=np.sqrt(np.mean(err**2)))
    if centres is not None:
        seen = np.isfinite(centres).all(axis=1)
        moved = al.scale * centres[seen] @ al.rotation.T + al.translation
        out["centres"] = np.linalg.norm(moved - ref_centres[seen], axis=1).max() / radius * 100
    return out


def colmap_incremental(observations: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """pycolmap's incremental mapper on the tracks as matches; (points per track, camera centres)."""
    import pycolmap

    F, P = observations.shape[:2]
    work = Path(tempfile.mkdtemp(prefix="colmap_"))
    try:
        db = pycolmap.Database.open(str(work / "db.db"))
        keypoint = -np.ones((F, P), np.int64)
        for f in range(F):  # one image per frame
            K0 = K[f].copy()
            K0[0, 1] = 0.0
            seen = np.flatnonzero(np.isfinite(observations[f, :, 0]))
            h = np.c_[observations[f, seen], np.ones(len(seen))] @ (K0 @ np.linalg.inv(K[f])).T
            camera = pycolmap.Camera(model="PINHOLE", width=size[0], height=size[1],
                                     params=[K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]])
            image_id = db.write_image(pycolmap.Image(name=f"{f}.png", camera_id=db.write_camera(camera)))
            assert image_id == f + 1
            db.write_keypoints(image_id, (h[:, :2] / h[:, 2:]).astype(np.float32))
            keypoint[f, seen] = np.arange(len(seen))
        with open(work / "pairs.txt", "w") as pairs:
            for a in range(F):
                for b in range(a + 1, F):
                    both = np.flatnonzero((keypoint[a] >= 0) & (keypoint[b] >= 0))
                    if len(both) >= 15:
                        db.write_matches(a + 1, b + 1, np.stack([keypoint[a, both], keypoint[b, both]], 1)
                                         .astype(np.uint32))
                        pairs.write(f"{a}.png {b}.png\n")
        db.close()
        pycolmap.verify_matches(str(work / "db.db"), str(work / "pairs.txt"))
        options = pycolmap.IncrementalPipelineOptions()
        options.ba_refine_focal_length = options.ba_refine_principal_point = options.ba_refine_extra_params = False
        (work / "images").mkdir()
        models = pycolmap.incremental_mapping(str(work / "db.db"), str(work / "images"), str(work / "sparse"), options)
        model = max(models.values(), key=lambda r: r.num_points3D())
        track_of = {(f + 1, int(k)): p for f in range(F) for p, k in enumerate(keypoint[f]) if k >= 0}
        X = np.full((P, 3), np.nan)
        for point in model.points3D.values():
            for element in point.track.elements:
                X[track_of[(element.image_id, element.point2D_idx)]] = point.xyz
        centres = np.full((F, 3), np.nan)
        for image_id in model.reg_image_ids():
            pose = model.image(image_id).cam_from_world()
            centres[image_id - 1] = -pose.rotation.matrix().T @ pose.translation
        return X, centres
    finally:
        shutil.rmtree(work, ignore_errors=True)


def real_data(colmap: bool) -> None:
    for name, size in (("oxford_model_house", (768, 576)), ("oxford_merton1", (1024, 768))):
        data, pose = load(name)
        K = pose.intrinsics
        print(f"\n== {name}: {data.observations.shape[0]} views, {data.observations.shape[1]} tracks, "
              f"{int(np.isfinite(data.observations[..., 0]).sum())} observations")
        print(f"  {'method':26s} {'points':>9s} {'median %':>9s} {'p95 %':>8s} {'RMS %':>8s} {'centres %':>10s} "
              f"{'reproj px':>10s} {'sigma px':>9s} {'time s':>7s}")
        for method in ("batch", "recursive"):
            start = time.perf_counter()
            rec = reconstruct_perspective(data.observations, K, method=method)
            elapsed = time.perf_counter() - start
            s = score(rec.points, rec.centres, data.points, pose.centers)
            print(f"  {'ours, ' + method:26s} {s['points']:>9s} {s['median']:9.4f} {s['p95']:8.4f} {s['rms']:8.4f} "
                  f"{s['centres']:10.3f} {rec.reprojection_rms:10.3f} {rec.noise.std:9.3f} {elapsed:7.2f}")
            for w in rec.warnings:
                print(f"      warning: {w}")
        if colmap:
            start = time.perf_counter()
            X, centres = colmap_incremental(data.observations, K, size)
            elapsed = time.perf_counter() - start
            s = score(X, centres, data.points, pose.centers)
            print(f"  {'pycolmap incremental':26s} {s['points']:>9s} {s['median']:9.4f} {s['p95']:8.4f} {s['rms']:8.4f} "
                  f"{s['centres']:10.3f} {'':>10s} {'':>9s} {elapsed:7.2f}")


def synthetic(runs: int, frames: int = 10, arc: float = 40.0) -> None:
    print(f"\n== synthetic walk-around, {runs} seeds ({frames} frames on a {arc:g}° arc, 400 points, 0.7 px, "
          f"3 % outliers)")
    for method in ("batch", "recursive"):
        nees, cam_nees, centre, reconstructed, median, refused = [], [], [], [], [], 0
        for seed in range(runs):
            s = perspective_scene(frames=frames, points=400, pixel_std=0.7, outlier_fraction=0.03, arc_degrees=arc,
                                  seed=seed)
            try:
                rec = reconstruct_perspective(s.observations, s.intrinsics, method=method)
            except NotEnoughDataError:
                refused += 1
                continue
            ok, reg = rec.reconstructed, rec.registered
            # the recursive method's camera covariances are in the gauge of its first camera: centres only
            out = compare_in_gauge(rec.points[ok], rec.point_covariances[ok], s.points[ok],
                                   centres=rec.centres[reg], reference_centres=s.centres[reg],
                                   **({} if method != "batch" else dict(
                                       rotations=rec.rotations[reg], camera_covariances=rec.pose_covariances[reg],
                                       reference_rotations=s.rotations[reg])))
            nees.append(out.point_nees)
            centre.append(np.linalg.norm(out.centre_errors, axis=1).max() / s.viewing_distance * 100)
            reconstructed.append(ok.mean())
            median.append(np.median(np.linalg.norm(out.point_errors, axis=1)))
            if method == "batch":
                cam_nees.append(out.camera_nees)
        n = np.concatenate(nees)
        line = (f"  {method:9s}: point NEES mean {n.mean():.2f} (median {np.median(n):.2f}, χ²₃ median 2.37), "
                f"within the 99 % bound {100 * np.mean(n < chi2.ppf(0.99, 3)):.1f} %; median point error "
                f"{np.median(median):.4f} (object radius 1.7); worst camera centre {max(centre):.3f} % of the "
                f"viewing distance; points reconstructed {100 * min(reconstructed):.1f}-{100 * max(reconstructed):.1f} %"
                f"; refused (no parallax) {refused} of {runs}")
        if cam_nees:
            line += f"; camera NEES (6 dof) mean {np.concatenate(cam_nees).mean():.2f}"
        print(line)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--synthetic", type=int, default=0, metavar="SEEDS")
    parser.add_argument("--no-colmap", action="store_true")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}")
    real_data(colmap=not args.no_colmap)
    if args.synthetic:
        synthetic(args.synthetic)
        synthetic(args.synthetic, frames=6, arc=60.0)  # 12° between frames: the recursive method's own ground


if __name__ == "__main__":
    main()
