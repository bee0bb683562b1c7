"""``kalmansfm export RUN --colmap DIR``: a run's reconstruction as a COLMAP sparse model."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..pipeline.export import EXPORT_IMAGES, ExportRequest, run_export
from ._options import as_typed, print_warnings


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    """Declare ``kalmansfm export``."""
    p = subparsers.add_parser(
        "export",
        parents=parents,
        help="write a run's reconstruction as a COLMAP sparse model (Gaussian splatting, nerfstudio, OpenMVS)",
        description="Write the reconstruction of a finished run (reconstruct --camera perspective, fuse, or demo "
        "--camera perspective) as a COLMAP sparse model in DIR/sparse/0: cameras (PINHOLE), images (pose and "
        "2-D points) and points3D (colour, reprojection RMS as ERROR, track), plus points3D_covariance.txt "
        "with each point's covariance and its gauge. --images copy|link puts the source images in DIR/images, "
        "the layout 3D Gaussian Splatting and nerfstudio read. An affine (factorization) run has no pinhole "
        "cameras and is refused.",
    )
    p.add_argument("run_dir", metavar="RUN", type=Path, help="the run folder (contains summary.json)")
    p.add_argument("--colmap", metavar="DIR", type=Path, required=True, help="the export folder")
    p.add_argument("--binary", action="store_true", help="COLMAP's binary files (.bin) instead of text (.txt)")
    p.add_argument("--images", choices=EXPORT_IMAGES, default="none",
                   help="copy or link the source images into DIR/images (a demo of a folder of images knows them)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Export; print what was written."""
    with as_typed({"images": "--images"}):
        result = run_export(ExportRequest(args.run_dir, args.colmap, binary=args.binary, images=args.images))
    print(f"images: {result.images}  points: {result.points}  format: {'binary' if args.binary else 'text'}")
    print_warnings(result.summary)
    print(f"wrote {result.out_dir}")
    return 0
