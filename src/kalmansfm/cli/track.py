"""``kalmansfm track INPUT --out DIR``: Kalman-gated template tracking of points through frames."""

from __future__ import annotations

import argparse
import logging
import sys

from ..features import FeatureSettings
from ..pipeline import TrackRequest, run_track
from ..tracking import TrackerSettings
from ..tracking.settings import MATCHERS
from ._options import as_typed

log = logging.getLogger("kalmansfm")

#: The tracker's defaults, shown in --help: defined once, in TrackerSettings.
DEFAULTS = TrackerSettings()


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "track",
        parents=parents,
        help="track points through a folder of images, a glob or a video",
        description="Track points with one Kalman filter per point (constant velocity): predict, measure, update. "
        "The default matcher follows each point by Lucas-Kanade started from its prediction, checked by the gate, "
        "a forward-backward flow and its anchor's appearance, with a measurement noise from the refinement itself; "
        "--matcher search is the report's exhaustive SSD/NCC template search inside the gate ellipse. Writes tracks.csv, tracks.npz, "
        "covariance_trace.png, tracks.png, tracks.gif and summary.json to DIR. With --smooth the files hold "
        "Rauch-Tung-Striebel smoothed estimates (each given the whole sequence) instead of the online ones.",
    )
    p.add_argument("input", metavar="INPUT", help="folder of images (natural order), glob pattern or video file")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--points", metavar="FILE", help="CSV with header x,y[,track_id]: points in frame 0 (default: detect corners)")
    p.add_argument("--max-features", type=int, default=None, metavar="N",
                   help=f"corners to detect when --points is not given (default: {DEFAULTS.max_features}; with "
                   f"--matcher features the strongest {FeatureSettings().max_features} features of each frame)")
    gate = p.add_mutually_exclusive_group()
    gate.add_argument("--gate", type=float, default=DEFAULTS.gate_probability, metavar="P",
                      help="gate confidence level: c² is the chi-square 2-dof quantile of P")
    gate.add_argument("--gate-radius", type=float, default=None, metavar="C", help="gate radius c directly")
    p.add_argument("--matcher", choices=(*MATCHERS, "features"), default=DEFAULTS.matcher,
                   help="differential: Lucas-Kanade from the Kalman prediction; search: the report's gated template "
                   "search; features: no filter, SIFT features matched between neighbouring and similar frames "
                   "anywhere in the clip (wide baselines, points that leave and come back), verified by the epipolar "
                   "geometry (docs/front-end.md)")
    p.add_argument("--score", choices=["ssd", "ncc"], default=DEFAULTS.score, help="template score (--matcher search)")
    p.add_argument("--window", type=int, default=DEFAULTS.window, metavar="N", help="template side in pixels (odd)")
    p.add_argument("--max-misses", type=int, default=DEFAULTS.max_misses, metavar="N",
                   help="frames a track may coast before it is lost (default: 3 with --matcher search, 5 with differential)")
    p.add_argument("--redetect", action="store_true", help="add new corners in empty regions as tracks are lost")
    p.add_argument("--reattach", type=int, default=DEFAULTS.reattach_frames, metavar="N",
                   help="with --redetect: a track lost at most N frames ago takes a redetected corner in its predicted "
                   "gate whose descriptor and patch match it, and keeps its id (occlusions); 0: off")
    p.add_argument("--smooth", action="store_true",
                   help="write RTS-smoothed positions and covariances (fixed interval: each frame uses all frames)")
    p.add_argument("--smooth-lag", type=int, default=None, metavar="L",
                   help="fixed-lag smoothing instead: frame t uses the frames up to t + L (implies --smooth)")
    p.set_defaults(run=run)


def settings_from_args(args: argparse.Namespace) -> TrackerSettings:
    """The tracker settings the options ask for (the others keep their defaults)."""
    with as_typed({"window": "--window", "gate_probability": "--gate", "gate_radius": "--gate-radius",
                   "max_misses": "--max-misses", "max_features": "--max-features", "reattach_frames": "--reattach", "redetect": "--redetect"}):
        return TrackerSettings(
            matcher=args.matcher,
            window=args.window,
            score=args.score,
            gate_probability=args.gate,
            gate_radius=args.gate_radius,
            max_misses=args.max_misses,
            max_features=DEFAULTS.max_features if args.max_features is None else args.max_features,
            redetect=args.redetect,
            reattach_frames=args.reattach,
        )


def run(args: argparse.Namespace) -> int:
    smooth: bool | int = args.smooth_lag if args.smooth_lag is not None else bool(args.smooth)
    features = None
    if args.matcher == "features":
        features = FeatureSettings() if args.max_features is None else FeatureSettings(max_features=args.max_features)
        args.matcher = DEFAULTS.matcher  # the tracker's own settings are not used
    settings = settings_from_args(args)
    smooth_flag = "--smooth-lag" if args.smooth_lag is not None else "--smooth"
    with as_typed({"smooth": smooth_flag, "points": "--points", "max_features": "--max-features"}):
        result = run_track(TrackRequest(args.input, args.out, points=args.points, settings=settings, smooth=smooth,
                                        progress=not args.quiet, features=features))
    m = result.summary.tracking
    print(
        f"tracked {m.tracks} points through {m.frames} frames; {m.alive_in_last_frame} alive at the end, "
        f"{m.survival_of_first_frame_tracks:.0%} of the first frame's; "
        + ("smoothed; " if result.tracks.smoothed is not False else "")
        + f"results in {args.out}",
        file=sys.stdout,
    )
    return 0
