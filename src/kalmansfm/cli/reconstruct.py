"""``kalmansfm reconstruct TRACKS --out DIR``: shape and motion from tracks (factorization, or calibrated
reconstruction with ``--camera perspective``)."""

from __future__ import annotations

import argparse

import numpy as np
from pathlib import Path


from ..errors import InvalidInputError
from ..features import DETECTORS, FeatureSettings
from ..mapping import MappingSettings
from ..mapping.settings import FEATURE_OUTLIER_THRESHOLD_PX
from ..pipeline import Affine, Auto, Perspective, ReconstructRequest, run_reconstruct
from ..pipeline.cluster import check_cluster
from ..pipeline.images import ImagesRequest, is_image_input, run_reconstruct_images
from ..pipeline.perspective import CAMERA_MODELS
from ..pipeline.requests import Camera
from ..structure.affine.factorization import DEFAULT_MAX_ITERATIONS
from ..structure.perspective import PERSPECTIVE_METHODS, PerspectiveSettings
from ._options import as_typed, print_warnings


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "reconstruct",
        parents=parents,
        help="3D shape and camera motion from point tracks (factorization, or calibrated perspective reconstruction)",
        description="Recover the 3D shape and the camera motion from point tracks. TRACKS is the tracker's "
        "tracks.csv or tracks.npz, or a CSV with columns frame,track_id,x,y. --camera affine (default): "
        "orthographic factorization with a metric upgrade; writes structure.csv, structure.ply, motion.csv, "
        "structure.png and summary.json. --camera perspective: calibrated reconstruction (needs --intrinsics "
        "K.csv with frame,fx,fy,cx,cy,skew, or --focal F): initial pair, PnP growth, bundle adjustment, "
        "per-point covariances in the free-network gauge; writes structure.csv (with covariances and status), "
        "cameras.csv, structure.ply, reconstruction.png and summary.json. --camera auto runs both and keeps "
        "the perspective model when its reprojection RMS is at most the affine model's.",
    )
    p.add_argument("tracks", metavar="INPUT", type=Path,
                   help="tracks.csv, tracks.npz, a frame,track_id,x,y CSV or the folder of a track run; or, with "
                   "--camera perspective, images (a folder, a glob or a video: frame k is the k-th image in natural "
                   "order) reconstructed by the feature front end")
    p.add_argument("--out", metavar="DIR", type=Path, required=True, help="output folder")
    defaults = PerspectiveSettings()
    p.add_argument("--camera", choices=CAMERA_MODELS, default="affine", help="camera model")
    p.add_argument("--intrinsics", metavar="K.csv", type=Path, default=None,
                   help="perspective/auto: the intrinsics, frame,fx,fy,cx,cy,skew (one row for all frames or one per frame)")
    p.add_argument("--focal", metavar="F", type=float, default=None,
                   help="perspective/auto: focal length in pixels instead of --intrinsics (principal point at the "
                   "image centre)")
    p.add_argument("--image-size", metavar=("W", "H"), type=int, nargs=2, default=None,
                   help="image width and height for --focal when the tracks file does not record them")
    p.add_argument("--method", choices=PERSPECTIVE_METHODS, default=defaults.method,
                   help="perspective: bundle adjustment (batch) or the report's relative orientations and recursive "
                   "fusion (recursive)")
    p.add_argument("--outlier-threshold", metavar="PX", type=float, default=None,
                   help="perspective: an observation farther than this from where its other views put the point is "
                   "an outlier (unless the estimated noise makes the chi-square bound wider); default "
                   f"{defaults.outlier_threshold_px:g} px for tracks, {FEATURE_OUTLIER_THRESHOLD_PX:g} px for the "
                   "feature tracks of images")
    p.add_argument(
        "--no-weights",
        action="store_true",
        help="ignore the tracker's standard deviations and weight every observation equally",
    )
    p.add_argument(
        "--smooth",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="factorize RTS-smoothed positions (needs the tracker's tracks.npz). Default: smooth a tracks.npz "
        "that is not smoothed yet, read a CSV as it is",
    )
    p.add_argument("--max-iterations", type=int, default=DEFAULT_MAX_ITERATIONS, help="cap on the missing-data refinement iterations")
    p.add_argument("--workers", type=int, default=None,
                   help="images: match the image pairs on a local Dask cluster of this many processes (default: on "
                   "threads in this process)")
    p.add_argument("--scheduler", default=None,
                   help="images: match the image pairs on an existing Dask scheduler, e.g. tcp://host:8786")
    features = FeatureSettings()
    p.add_argument("--detector", choices=DETECTORS, default=None,
                   help=f"images: the feature detector and descriptor (default: {features.detector}; RootSIFT)")
    p.add_argument("--max-features", metavar="N", type=int, default=None,
                   help=f"images: keep each image's N strongest features (default: {features.max_features}; 0 = all)")
    p.add_argument("--sift-upsampling", metavar="U", type=float, default=None,
                   help=f"images: how much SIFT's first octave enlarges the image (default: {features.sift_upsampling:g}; "
                   "2 = OpenCV's own detection, more accurate and slower; see docs/front-end.md)")
    p.add_argument("--no-plot", action="store_true", help="do not draw structure.png")
    p.set_defaults(run=run)


#: the front end's options, by the FeatureSettings field each sets.
_FEATURE_OPTIONS = {"detector": "--detector", "max_features": "--max-features", "sift_upsampling": "--sift-upsampling"}


def _feature_settings(args: argparse.Namespace, images_in: bool) -> FeatureSettings:
    given = {field: getattr(args, field) for field in _FEATURE_OPTIONS if getattr(args, field) is not None}
    if given and not images_in:
        names = ", ".join(_FEATURE_OPTIONS[field] for field in given)
        raise InvalidInputError(f"{names}: the feature front end's options apply to images; {args.tracks} holds tracks")
    with as_typed(_FEATURE_OPTIONS):
        return FeatureSettings(**given)


def run(args: argparse.Namespace) -> int:
    check_cluster(args.scheduler, args.workers, scheduler_name="--scheduler", workers_name="--workers")
    if args.camera == "affine" and (args.intrinsics is not None or args.focal is not None):
        raise InvalidInputError("--intrinsics and --focal describe a perspective camera: add --camera perspective "
                                "(or auto)")
    with as_typed({"outlier_threshold_px": "--outlier-threshold", "max_iterations": "--max-iterations",
                   "intrinsics": "--intrinsics", "focal": "--focal", "image_size": "--image-size"}):
        affine = Affine(weighted=not args.no_weights, max_iterations=args.max_iterations)
        camera: Camera = affine
        if args.camera != "affine":
            images_in = is_image_input(args.tracks)
            threshold = args.outlier_threshold
            if threshold is None:
                threshold = FEATURE_OUTLIER_THRESHOLD_PX if images_in else PerspectiveSettings().outlier_threshold_px
            settings = PerspectiveSettings(method=args.method, outlier_threshold_px=threshold)
            perspective = Perspective(intrinsics=args.intrinsics, focal=args.focal, settings=settings,
                                      image_size=None if args.image_size is None else tuple(args.image_size))
            camera = perspective if args.camera == "perspective" else Auto(perspective, affine)
        features = _feature_settings(args, is_image_input(args.tracks))
        if is_image_input(args.tracks):
            if args.camera != "perspective":
                raise InvalidInputError(f"{args.tracks} holds images: reconstruct them with --camera perspective and "
                                        "--intrinsics or --focal (or track them first)")
            images = run_reconstruct_images(ImagesRequest(args.tracks, args.out, camera, plot=not args.no_plot,
                                                          settings=MappingSettings(features=features,
                                                                                   reconstruction=settings),
                                                          scheduler=args.scheduler, workers=args.workers))
            _print_images(images)
            return 0
        if args.scheduler is not None or args.workers is not None:
            raise InvalidInputError(f"--workers and --scheduler spread the matching of image pairs; {args.tracks} holds "
                                    "tracks, which are reconstructed here")
        result = run_reconstruct(ReconstructRequest(args.tracks, args.out, camera, smooth=args.smooth,
                                                    plot=not args.no_plot, progress=not args.quiet))
    s = result.summary.reconstruction
    assert s is not None  # a reconstruct run records its reconstruction
    if s.kind == "perspective":
        _print_perspective(result)
        return 0
    shown = ", ".join(f"{v:.4g}" for v in s.singular_values[:5])  # as demo prints them
    print(f"frames: {s.frames}  tracks: {s.points}  method: {s.method}"
          + (f" ({s.iterations} iterations)" if s.method in ("als", "sequential") else "")
          + ("  weighted by tracker std" if s.weighted else "")
          + ("  smoothed" if s.smoothed is not False else ""))
    if shown:  # the frame-by-frame factorization of a long sequence forms no measurement matrix
        print(f"singular values: {shown}")
    print(f"rank-3 residual: {s.reprojection_rms_px:.4f} px RMS")
    print_warnings(result.summary)
    print(f"wrote {args.out}")
    return 0


def _print_images(run) -> None:
    r, p = run.result, run.summary.reconstruction
    counts = [len(f.keypoints) for f in r.features]
    graph = r.match_graph
    print(f"images: {len(r.features)} of {r.image_size[0]}x{r.image_size[1]}; median {int(np.median(counts))} features "
          f"per image; match graph: {int(graph.verified.sum())} of {len(graph.candidates)} pairs verified")
    print(f"tracks: {p.points}  observations: {p.observations}  guided matching added "
          f"{r.guided.added_observations}, merged {r.guided.merged_tracks} tracks")
    print(f"registered: {p.registered_frames}/{p.frames}  points: {p.reconstructed}  reprojection RMS "
          f"{p.reprojection_rms_px:.3g} px; pixel noise sigma {p.noise_std:.3g} px")
    print(f"intrinsics: {p.intrinsics}")
    print_warnings(run.summary)
    print(f"wrote {run.out_dir}")


def _print_perspective(result) -> None:
    p = result.summary.reconstruction
    print(f"frames: {p.frames}  registered: {p.registered_frames}  tracks: {p.points}  reconstructed: "
          f"{p.reconstructed}  method: {p.method}")
    if p.camera_choice:
        print(f"camera: {p.camera_choice}")
    print(f"intrinsics: {p.intrinsics}")
    print(f"inliers: {p.used} of {p.observations} observations; pixel noise sigma {p.noise_std:.3g} px; "
          f"reprojection RMS {p.reprojection_rms_px:.3g} px")
    print_warnings(result.summary)
    print(f"wrote {result.out_dir}")
