"""``kalmansfm fuse TRACKS --cameras CAMERAS --out DIR``: 3-D points with covariances from known cameras."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..pipeline import FuseRequest, run_fuse
from ..pipeline.cluster import check_cluster
from ..estimation.noise_model import NOISE_MODELS
from ..structure.fusion import FUSION_METHODS, FusionSettings
from ._options import as_typed, print_warnings

_DEFAULTS = FusionSettings()


def _pixel_std(text: str) -> float | None:
    """``auto`` → None (estimate it), else a number > 0 (checked by FusionSettings)."""
    if text.strip().lower() == "auto":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be 'auto' or a number of pixels; got {text!r}") from None


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "fuse",
        parents=parents,
        help="3D points with honest covariances from tracks and known cameras (Kalman fusion, view by view)",
        description="Fuse every tracked point over the views of known cameras into a 3D position with a "
        "covariance, as Thomas & Oliensis fuse structure by Kalman filtering: each point starts from its first "
        "two views and is updated by every further view, and observations that fail the chi-square gate are "
        "rejected as outliers. TRACKS is the tracker's tracks.csv or tracks.npz, or a CSV frame,track_id,x,y "
        "(optional status); CAMERAS a CSV frame,p11..p34 (3x4 projection matrices, row-major) or "
        "frame,fx,fy,cx,cy,skew,r11..r33,t1,t2,t3 (x_cam = R X + t). Writes structure.csv, history.csv, "
        "rejected.csv, structure.ply, fusion.png and summary.json to DIR.",
    )
    p.add_argument("tracks", metavar="TRACKS", type=Path, help="tracks.csv, tracks.npz or a frame,track_id,x,y CSV")
    p.add_argument("--cameras", metavar="CAMERAS", type=Path, required=True, help="the cameras CSV")
    p.add_argument("--out", metavar="DIR", type=Path, required=True, help="output folder")
    p.add_argument("--method", choices=FUSION_METHODS, default=_DEFAULTS.method,
                   help="recursive: the paper's Kalman fusion, view by view; batch: per-point maximum likelihood "
                   "over all views (the reference); pairs: the report's fusion of consecutive two-view "
                   "triangulations (over-confident, no outlier test)")
    p.add_argument("--pixel-std", type=_pixel_std, default="auto", metavar="auto|PX",
                   help="image noise standard deviation in pixels, or auto: estimated from the residuals "
                   "(2 degrees of freedom per observation minus 3 per point, after outlier rejection)")
    p.add_argument("--outlier-prob", type=float, default=_DEFAULTS.outlier_probability, metavar="P",
                   help="an observation beyond the chi-square quantile of P is rejected (1 turns the test off)")
    p.add_argument("--noise-model", choices=NOISE_MODELS, default=_DEFAULTS.noise_model,
                   help="the image noise fitted to the residuals when --pixel-std is auto: gaussian (one sigma, the "
                   "report's), student-t, mixture (Gaussian + uniform outliers) or student-t+uniform; each observation "
                   "is weighted by it and the covariances follow from it (docs/fusion.md)")
    p.add_argument("--track-scales", action="store_true",
                   help="with a fitted noise model, give each track its own noise scale (pooled toward the common one)")
    p.add_argument("--chunk-points", type=int, default=_DEFAULTS.chunk_points,
                   help="points fused together (bounds the memory)")
    p.add_argument("--workers", type=int, default=None,
                   help="fuse the chunks on a local Dask cluster of this many processes (default: in this process)")
    p.add_argument("--scheduler", default=None, help="fuse the chunks on an existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--no-plot", action="store_true", help="do not draw fusion.png")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    check_cluster(args.scheduler, args.workers, scheduler_name="--scheduler", workers_name="--workers")
    with as_typed({"pixel_std": "--pixel-std", "outlier_probability": "--outlier-prob", "chunk_points": "--chunk-points"}):
        settings = FusionSettings(method=args.method, pixel_std=args.pixel_std, outlier_probability=args.outlier_prob,
                                  history=True, chunk_points=args.chunk_points, noise_model=args.noise_model,
                                  track_scales=args.track_scales)
    result = run_fuse(FuseRequest(args.tracks, args.cameras, args.out, settings, scheduler=args.scheduler,
                                  workers=args.workers, plot=not args.no_plot, progress=not args.quiet))
    f = result.summary.reconstruction
    assert f is not None  # run_fuse always records its reconstruction
    print(f"views: {f.frames}  tracks: {f.points}  method: {f.method}")
    print(f"fused: {f.reconstructed}  unreliable: {f.unreliable}  too few views: {f.too_few_views}  "
          f"degenerate: {f.degenerate}  behind camera: {f.behind_camera}")
    print(f"observations: {f.observations}  rejected as outliers: {f.rejected}")
    how = "estimated, " + f"{f.degrees_of_freedom} degrees of freedom" if f.noise_estimated else "given"
    shown = {"outlier_share": "outliers {:.2%}", "tail_dof": "tail dof {:.3g}"}
    model = "".join(", " + shown[k].format(v) for k, v in f.noise_parameters if k in shown)
    print(f"pixel noise: {f.noise_std:.4g} px ({f.noise_model}{model}; {how})")
    if f.reprojection_rms_px is not None:
        print(f"reprojection RMS: {f.reprojection_rms_px:.4g} px  median point uncertainty: {f.median_point_std:.4g}")
    print_warnings(result.summary)
    print(f"wrote {args.out}")
    return 0
