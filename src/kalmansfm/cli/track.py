"""``kalmansfm track INPUT --out DIR``: Kalman-gated template tracking of points through frames."""

from __future__ import annotations

import argparse
import json
import logging
import platform
import sys

import numpy as np

from .. import __version__
from ..errors import InvalidInputError
from ..io.atomic import check_output_directory, output_directory
from ..io.frames import read_frames
from ..io.tracks import check_points_inside, read_points_csv
from ..pipeline import save_tracking
from ..tracking.smoothing import smooth_tracks
from ..tracking.tracker import track

log = logging.getLogger("kalmansfm")


def _probability(text: str) -> float:
    value = float(text)
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1); got {text}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0; got {text}")
    return value


def _odd_window(text: str) -> int:
    value = int(text)
    if value < 3 or value % 2 == 0:
        raise argparse.ArgumentTypeError(f"must be an odd integer >= 3; got {text}")
    return value


def _count(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0; got {text}")
    return value


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "track",
        parents=parents,
        help="track points through a folder of images, a glob or a video",
        description="Track points with one Kalman filter per point (constant velocity): predict, search the "
        "template inside the gate ellipse of the predicted covariance, update. Writes tracks.csv, tracks.npz, "
        "covariance_trace.png, tracks.png, tracks.gif and summary.json to DIR. With --smooth the files hold "
        "Rauch-Tung-Striebel smoothed estimates (each given the whole sequence) instead of the online ones.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("input", metavar="INPUT", help="folder of images (natural order), glob pattern or video file")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--points", metavar="FILE", help="CSV with header x,y[,track_id]: points in frame 0 (default: detect corners)")
    p.add_argument("--max-features", type=int, default=200, metavar="N", help="corners to detect when --points is not given")
    gate = p.add_mutually_exclusive_group()
    gate.add_argument("--gate", type=_probability, default=0.95, metavar="P",
                      help="gate confidence level: c² is the chi-square 2-dof quantile of P")
    gate.add_argument("--gate-radius", type=_positive_float, default=None, metavar="C", help="gate radius c directly")
    p.add_argument("--score", choices=["ssd", "ncc"], default="ssd", help="template score")
    p.add_argument("--window", type=_odd_window, default=11, metavar="N", help="template side in pixels (odd)")
    p.add_argument("--max-misses", type=_count, default=3, metavar="N", help="frames a track may coast before it is lost")
    p.add_argument("--redetect", action="store_true", help="add new corners in empty regions as tracks are lost")
    p.add_argument("--smooth", action="store_true",
                   help="write RTS-smoothed positions and covariances (fixed interval: each frame uses all frames)")
    p.add_argument("--smooth-lag", type=_count, default=None, metavar="L",
                   help="fixed-lag smoothing instead: frame t uses the frames up to t + L (implies --smooth)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    check_output_directory(args.out)
    frames = read_frames(args.input)
    points = track_ids = None
    if args.points:
        points, track_ids = read_points_csv(args.points)
        first = next(iter(frames))
        check_points_inside(points, first.shape[1], first.shape[0], args.points)
    if args.max_features < 1:
        raise InvalidInputError(f"--max-features must be >= 1; got {args.max_features}")
    options = dict(
        window=args.window,
        score=args.score,
        gate_probability=args.gate,
        gate_radius=args.gate_radius,
        max_misses=args.max_misses,
        max_features=args.max_features,
        redetect=args.redetect,
    )
    tracks = track(frames, points, track_ids=track_ids, progress=not args.quiet, **options)
    if args.smooth or args.smooth_lag is not None:
        tracks = smooth_tracks(tracks, lag=args.smooth_lag)
    last_frame = None
    for last_frame in frames:  # the last frame for the picture (frames are decoded lazily)
        pass
    summary = {
        "command": "track",
        "input": str(args.input),
        "points": args.points,
        "parameters": tracks.parameters,
        "smoothed": tracks.parameters.get("smoothed", False),
        "versions": {"kalmansfm": __version__, "python": platform.python_version(), "numpy": np.__version__},
        "metrics": {
            "frames": tracks.n_frames,
            "tracks": tracks.n_tracks,
            "alive_in_last_frame": int(tracks.alive[-1].sum()),
            "survival_of_first_frame_tracks": float(tracks.survival()[-1]),
            "measured_fraction": float(tracks.measured.sum() / max(tracks.alive.sum(), 1)),
            "lost": int((tracks.status == 3).sum()),
        },
        "status_codes": {"0": "no track", "1": "measured", "2": "predicted", "3": "lost"},
    }
    with output_directory(args.out) as out:
        save_tracking(out, tracks, frames, last_frame=last_frame)
        out.write_text("summary.json", json.dumps(summary, indent=2) + "\n")
    m = summary["metrics"]
    print(
        f"tracked {m['tracks']} points through {m['frames']} frames; {m['alive_in_last_frame']} alive at the end, "
        f"{m['survival_of_first_frame_tracks']:.0%} of the first frame's; "
        + ("smoothed; " if summary["smoothed"] is not False else "")
        + f"results in {args.out}",
        file=sys.stdout,
    )
    return 0
