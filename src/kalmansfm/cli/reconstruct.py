"""``kalmansfm reconstruct TRACKS --out DIR``: shape and motion from tracks by factorization."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import InvalidInputError
from ..io.atomic import check_output_directory, output_directory
from ..pipeline import read_tracks_for_factorization, save_structure
from ..structure.factorization import factorize

log = logging.getLogger("kalmansfm")


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
    check_output_directory(args.out)
    tracks = read_tracks_for_factorization(args.tracks, smooth=args.smooth)
    weights = None if args.no_weights else tracks.weights
    log.info("read %d frames x %d tracks from %s", *tracks.positions.shape[:2], args.tracks)
    result = factorize(tracks.positions, weights=weights, max_iterations=args.max_iterations)
    summary = {
        "command": "reconstruct",
        "version": __version__,
        "tracks": str(args.tracks),
        "weighted": weights is not None,
        "smoothed": tracks.smoothed,
        "frames": int(tracks.positions.shape[0]),
        "points": int(tracks.positions.shape[1]),
        "method": result.method,
        "iterations": result.iterations,
        "singular_values": [float(s) for s in result.singular_values[:10]],
        "residual_rms_px": result.residual_rms,
        "reconstructed_points": int(np.isfinite(result.points).all(axis=1).sum()),
        "reconstructed_frames": int(np.isfinite(result.motion).all(axis=(1, 2)).sum()),
        "warnings": list(result.warnings),
    }
    with output_directory(args.out) as out:
        save_structure(
            out, result, tracks.track_ids, frames=tracks.frames, title=f"Recovered shape: {args.tracks.name}",
            comment=f"kalmansfm {__version__} from {args.tracks.name}", plot=not args.no_plot,
        )
        out.write_text("summary.json", json.dumps(summary, indent=2) + "\n")
    shown = np.array2string(result.singular_values[:6], precision=4, separator=", ")
    print(f"frames: {summary['frames']}  tracks: {summary['points']}  method: {result.method}"
          + (f" ({result.iterations} iterations)" if result.method == "als" else "")
          + ("  weighted by tracker std" if weights is not None else "")
          + ("  smoothed" if tracks.smoothed is not False else ""))
    print(f"singular values: {shown}")
    print(f"rank-3 residual: {result.residual_rms:.4f} px RMS")
    for note in result.warnings:
        print(f"warning: {note}")
    print(f"wrote {args.out}")
    return 0
