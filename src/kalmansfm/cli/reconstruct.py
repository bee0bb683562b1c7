"""``kalmansfm reconstruct TRACKS --out DIR``: shape and motion from tracks by factorization."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from ..pipeline import run_reconstruct


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "reconstruct",
        parents=parents,
        help="3D shape and camera motion from point tracks (Tomasi-Kanade factorization)",
        description="Recover the 3D shape and the camera motion from point tracks by orthographic "
        "factorization with a metric upgrade. TRACKS is the tracker's tracks.csv or tracks.npz, or a CSV "
        "with columns frame,track_id,x,y. Writes structure.csv, structure.ply, motion.csv, structure.png "
        "and summary.json to DIR and prints the singular values, the rank-3 residual and any warnings.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("tracks", metavar="TRACKS", type=Path, help="tracks.csv, tracks.npz or a frame,track_id,x,y CSV")
    p.add_argument("--out", metavar="DIR", type=Path, required=True, help="output folder")
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
    p.add_argument("--max-iterations", type=int, default=500, help="cap on the missing-data refinement iterations")
    p.add_argument("--no-plot", action="store_true", help="do not draw structure.png")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.max_iterations < 1:
        raise InvalidInputError(f"--max-iterations must be >= 1; got {args.max_iterations}")
    result = run_reconstruct(args.tracks, args.out, weighted=not args.no_weights, smooth=args.smooth,
                             max_iterations=args.max_iterations, plot=not args.no_plot)
    s, r = result.summary.structure, result.reconstruction
    assert s is not None  # run_reconstruct always records its structure
    shown = np.array2string(r.singular_values[:6], precision=4, separator=", ")
    print(f"frames: {s.frames}  tracks: {s.points}  method: {s.method}"
          + (f" ({s.iterations} iterations)" if s.method == "als" else "")
          + ("  weighted by tracker std" if s.weighted else "")
          + ("  smoothed" if s.smoothed is not False else ""))
    print(f"singular values: {shown}")
    print(f"rank-3 residual: {s.residual_rms_px:.4f} px RMS")
    for note in s.warnings:
        print(f"warning: {note}")
    print(f"wrote {args.out}")
    return 0
