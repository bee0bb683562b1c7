"""From calibrated images to cameras: our feature front end + back end (``reconstruct_images``) vs pycolmap.

Usage::

    python benchmarks/bench_frontend.py                 # templeRing (47), its arc 13-31, dinoRing (48)
    python benchmarks/bench_frontend.py --quick         # templeRing 13-22 and dinoRing 1-12
    python benchmarks/bench_frontend.py --sets dino --no-colmap --profile
    python benchmarks/bench_frontend.py --no-colmap --sift-upsampling 2 --sift-sigma 1.6   # OpenCV's own SIFT

Data: ``../shared/data/middlebury_templering`` and ``middlebury_dinoring`` (their READMEs), images in
file order, the dataset's K for every view; the dataset's R, t are only the reference (dinoRing's R
are re-orthonormalised: they are off by up to 1.6e-6).  Both methods start from the image files:
ours reads them with ``kalmansfm.io.frames.read_frames`` and runs ``kalmansfm.mapping.reconstruct_images``;
pycolmap runs ``extract_features`` (SIFT, PINHOLE camera with the dataset's K, one camera for all),
``match_exhaustive`` and ``incremental_mapping`` with the intrinsics fixed (its largest model is scored),
on all cores, as ours.  Both are timed end to end in the same process, in interleaved rounds (``--repeat``,
best of each): wall time, and CPU time of the process (all threads; steadier when other work shares the
cores).

Scores, on the registered views: camera centres after the least-squares similarity alignment onto
the true centres, RMS in % of the ring radius (the circle through the true centres); rotation error
(the angle of R_true (R Qᵀ)ᵀ, Q the alignment's rotation), median in degrees; the same with Q taken from
the orientations alone (the rotation nearest Σ R_trueᵀ R: on an arc, centres fix the frame's turn about
the arc's chord poorly, and that error is in the first figure for every view); and the share of our
observations within 3 px of their reprojection under the TRUE cameras (each track triangulated with
the true cameras by ``kalmansfm.structure.fuse(..., method="batch")``), over all observations of the
final tracks and over the reconstruction's inliers.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kalmansfm.features import FeatureSettings
from kalmansfm.io.frames import FrameSource, list_image_files
from kalmansfm.io.middlebury import read_middlebury_cameras
from kalmansfm.mapping import MappingSettings, reconstruct_images
from kalmansfm.structure import CameraSet, align_similarity, fuse
from kalmansfm.structure.geometry.orthographic import rotation_angle_deg
from kalmansfm.structure.geometry.pinhole import camera_centres

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / ".." / "shared" / "data"
SETS = {
    "temple": ("middlebury_templering", "templeR", None),
    "temple-arc": ("middlebury_templering", "templeR", range(12, 31)),  # views 13-31 (file numbers)
    "dino": ("middlebury_dinoring", "dinoR", None),
    "temple-quick": ("middlebury_templering", "templeR", range(12, 22)),
    "dino-quick": ("middlebury_dinoring", "dinoR", range(0, 12)),
}


@dataclass
class Dataset:
    name: str
    folder: Path
    files: list[Path]
    K: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray

    @property
    def centres(self) -> np.ndarray:
        return camera_centres(self.rotations, self.translations)


def load(name: str, data: Path = DATA) -> Dataset:
    folder_name, prefix, subset = SETS[name]
    folder = data / folder_name
    cams = read_middlebury_cameras(folder / f"{prefix}_par.txt")
    index = {image: k for k, image in enumerate(cams.names)}
    files = list_image_files(folder / "images")
    if subset is not None:
        files = [files[k] for k in subset]
    rows = [index[f.name] for f in files]
    u, _, vt = np.linalg.svd(cams.rotations[rows])  # dinoRing's R are orthonormal to 1.6e-6 only
    return Dataset(name, folder, files, cams.intrinsics[rows], u @ vt, cams.translations[rows])


def ring_radius(centres: np.ndarray) -> float:
    """Radius of the circle through the centres (plane by SVD, circle by linear least squares)."""
    c = centres - centres.mean(axis=0)
    _, _, vt = np.linalg.svd(c)
    uv = c @ vt[:2].T
    a = np.c_[2 * uv, np.ones(len(uv))]
    x = np.linalg.lstsq(a, (uv**2).sum(axis=1), rcond=None)[0]
    return float(np.sqrt(x[2] + x[0] ** 2 + x[1] ** 2))


def camera_scores(data: Dataset, registered: np.ndarray, rotations: np.ndarray, centres: np.ndarray) -> dict:
    true_c = data.centres
    if registered.sum() < 3:
        return dict(registered=int(registered.sum()), centres=np.nan, rotation=np.nan, rotation_own_frame=np.nan)
    fit = align_similarity(centres[registered], true_c[registered])
    moved = fit.scale * centres[registered] @ fit.rotation.T + fit.translation
    rms = np.sqrt(np.mean(np.sum((moved - true_c[registered]) ** 2, axis=1))) / ring_radius(true_c) * 100
    true_r, ours_r = data.rotations[registered], rotations[registered]
    # the frame from the orientations alone: Q = argmin Σ |R_true Q - R|, the polar factor of Σ R_trueᵀ R
    u, _, vt = np.linalg.svd(np.einsum("fji,fjk->ik", true_r, ours_r))
    own = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return dict(registered=int(registered.sum()), centres=float(rms),
                rotation=float(np.median(rotation_angle_deg(ours_r @ fit.rotation.T, true_r))),
                rotation_own_frame=float(np.median(rotation_angle_deg(ours_r @ own.T, true_r))))


def within_3px(data: Dataset, observations: np.ndarray, mask: np.ndarray | None = None) -> tuple[float, int]:
    """Share of the observations within 3 px of their reprojection under the true cameras, and their count."""
    cams = CameraSet.from_pose(data.K, data.rotations, data.translations)
    fused = fuse(observations, cams, method="batch")
    P = data.K @ np.concatenate([data.rotations, data.translations[..., None]], axis=2)
    h = np.einsum("fij,pj->fpi", P, np.c_[fused.points, np.ones(len(fused.points))])
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.linalg.norm(h[..., :2] / h[..., 2:] - observations, axis=2)
    seen = np.isfinite(observations[..., 0]) if mask is None else mask
    return float(np.sum(seen & (r < 3.0)) / max(seen.sum(), 1)), int(seen.sum())


def run_ours(data: Dataset, settings: MappingSettings, executor=None) -> dict:
    start, cpu = time.perf_counter(), time.process_time()
    # the files are decoded as the features of the first are detected (as ``kalmansfm reconstruct IMAGES`` does)
    images = FrameSource(description=data.name, files=tuple(data.files), count=len(data.files))
    result = reconstruct_images(images, data.K, settings, executor=executor)
    elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
    rec = result.reconstruction
    out = camera_scores(data, result.registered, rec.rotations, rec.centres)
    obs = result.tracks.observations
    out["share_all"], out["observations"] = within_3px(data, obs)
    out["share_inliers"], out["inliers"] = within_3px(data, obs, rec.observations.used_mask())
    out.update(time=elapsed, cpu=cpu, timings=result.timings, result=result)
    return out


def run_pycolmap(data: Dataset) -> dict:
    import pycolmap

    work = Path(tempfile.mkdtemp(prefix="colmap_"))
    try:
        start, cpu = time.perf_counter(), time.process_time()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        K = data.K[0]
        reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"
        names = [f.name for f in data.files]
        pycolmap.extract_features(work / "db.db", data.files[0].parent, image_names=names,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader)
        extracted = time.perf_counter()
        pycolmap.match_exhaustive(work / "db.db")
        matched = time.perf_counter()
        options = pycolmap.IncrementalPipelineOptions()
        options.ba_refine_focal_length = options.ba_refine_principal_point = options.ba_refine_extra_params = False
        models = pycolmap.incremental_mapping(work / "db.db", data.files[0].parent, work / "sparse", options)
        elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
        F = len(data.files)
        registered = np.zeros(F, bool)
        rotations = np.full((F, 3, 3), np.nan)
        centres = np.full((F, 3), np.nan)
        if models:
            model = max(models.values(), key=lambda r: r.num_reg_images())
            index = {name: k for k, name in enumerate(names)}
            for image_id in model.reg_image_ids():
                image = model.image(image_id)
                k = index[image.name]
                pose = image.cam_from_world()
                registered[k] = True
                rotations[k] = pose.rotation.matrix()
                centres[k] = -rotations[k].T @ pose.translation
        out = camera_scores(data, registered, rotations, centres)
        stages = {"extract_features": extracted - start, "match_exhaustive": matched - extracted,
                  "incremental_mapping": elapsed - (matched - start)}
        out.update(time=elapsed, cpu=cpu, timings=stages, models=len(models))
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)


def best_of(first: dict | None, run: dict, deterministic: bool) -> dict:
    """The first round's scores with the smallest wall and CPU times of the rounds.

    Ours must give the same cameras every round; pycolmap's multi-threaded mapper need not (its first
    round is scored).
    """
    if first is None:
        return run
    if deterministic and (first["registered"], first["centres"]) != (run["registered"], run["centres"]):
        raise RuntimeError("two rounds of reconstruct_images gave different cameras")
    return {**first, "time": min(first["time"], run["time"]), "cpu": min(first["cpu"], run["cpu"])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sets", default="temple,temple-arc,dino",
                        help=f"comma-separated, from {', '.join(SETS)}")
    parser.add_argument("--quick", action="store_true", help="templeRing 13-22 and dinoRing 1-12 only")
    parser.add_argument("--no-colmap", action="store_true", help="ours only")
    parser.add_argument("--profile", action="store_true", help="print our time per stage")
    parser.add_argument("--data", type=Path, default=DATA, help="the folder holding the data sets")
    parser.add_argument("--repeat", type=int, default=2,
                        help="interleaved rounds (ours, pycolmap, ours, ...); the best time of each is reported")
    defaults = FeatureSettings()
    parser.add_argument("--sift-upsampling", type=float, default=defaults.sift_upsampling,
                        help="ours: FeatureSettings.sift_upsampling (2 = OpenCV's own SIFT)")
    parser.add_argument("--sift-sigma", type=float, default=defaults.sift_sigma,
                        help="ours: FeatureSettings.sift_sigma (1.6 = OpenCV's default)")
    parser.add_argument("--workers", type=int, default=None,
                        help="ours: match the image pairs on a local Dask cluster of this many processes (started once, "
                        "before the timed runs; its CPU time is not in ours)")
    args = parser.parse_args()
    names = ["temple-quick", "dino-quick"] if args.quick else args.sets.split(",")
    with ExitStack() as stack:
        executor = None
        if args.workers is not None:
            from kalmansfm.pipeline.cluster import ScatteringExecutor, dask_client

            executor = ScatteringExecutor(stack.enter_context(dask_client(n_workers=args.workers)))
        compare(names, args, executor)


def compare(names: list[str], args: argparse.Namespace, executor) -> None:
    settings = MappingSettings(features=FeatureSettings(sift_upsampling=args.sift_upsampling,
                                                        sift_sigma=args.sift_sigma))
    print(f"SIFT upsampling {args.sift_upsampling}, sigma {args.sift_sigma}; load average {os.getloadavg()[0]:.2f} "
          f"{os.getloadavg()[1]:.2f}, {os.cpu_count()} cores")
    rows = []
    for name in names:
        data = load(name, args.data)
        ours = colmap = None
        for _ in range(args.repeat):  # interleaved; the scores do not change between rounds, the times do
            ours = best_of(ours, run_ours(data, settings, executor), deterministic=True)
            if not args.no_colmap:
                colmap = best_of(colmap, run_pycolmap(data), deterministic=False)
        rows.append((name, len(data.files), ours, colmap, os.getloadavg()[0]))
        if args.profile:
            print(f"{name}: ours " + ", ".join(f"{k} {v:.2f} s" for k, v in ours["timings"].items()))
            if colmap:
                print(f"{name}: pycolmap " + ", ".join(f"{k} {v:.2f} s" for k, v in colmap["timings"].items()))
            r = ours["result"]
            print(f"{name}: {int(r.match_graph.verified.sum())} verified pairs of {len(r.match_graph.candidates)}, "
                  f"{r.tracks.observations.shape[1]} tracks, guided matching {r.guided}; unregistered: "
                  f"{'; '.join(r.unregistered_lines()) or 'none'}")
    print()
    print("| set | method | registered | centres RMS (% ring radius) | rotation median (°) | rotation median, frame from "
          "the rotations (°) | observations within 3 px (all / inliers) | wall time (s) | ours / pycolmap | CPU time (s) "
          "| ours / pycolmap | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, count, ours, colmap, load_average in rows:
        ratio = f"{ours['time'] / colmap['time']:.2f}" if colmap else ""
        cpu_ratio = f"{ours['cpu'] / colmap['cpu']:.2f}" if colmap else ""
        share = (f"{100 * ours['share_all']:.1f} % of {ours['observations']} / {100 * ours['share_inliers']:.1f} % of "
                 f"{ours['inliers']}")
        print(f"| {name} ({count}) | ours | {ours['registered']}/{count} | {ours['centres']:.3f} | "
              f"{ours['rotation']:.3f} | {ours['rotation_own_frame']:.3f} | {share} | {ours['time']:.1f} | {ratio} | "
              f"{ours['cpu']:.1f} | {cpu_ratio} | "
              f"{load_average:.1f} |")
        if colmap:
            print(f"| | pycolmap | {colmap['registered']}/{count} | {colmap['centres']:.3f} | "
                  f"{colmap['rotation']:.3f} | {colmap['rotation_own_frame']:.3f} | | {colmap['time']:.1f} | | "
                  f"{colmap['cpu']:.1f} | | |")


if __name__ == "__main__":
    main()
