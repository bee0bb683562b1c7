"""``kalmansfm demo``: the whole pipeline on the built-in scene (or on your own sequence)."""

from __future__ import annotations

import argparse
import sys
import webbrowser
from pathlib import Path

from ..errors import InvalidInputError
from ..pipeline import Affine, DemoRequest, Perspective, describe, run_demo
from ..scenes import DEFAULT_SCENE_FRAMES, DEFAULT_SCENE_SEED
from ..tracking import TrackerSettings
from ..tracking.settings import MATCHERS
from ._options import as_typed


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    """Declare ``kalmansfm demo``."""
    p = subparsers.add_parser(
        "demo",
        parents=parents,
        help="run the whole pipeline on the built-in scene and write an HTML report",
        description="Render the built-in polyhedron scene (or read --input), track its corners with the "
        "Kalman-gated tracker, recover shape and motion by factorization, compare with the ground truth, "
        "and write the results and a self-contained report.html into --out.",
    )
    p.add_argument("--out", default="kalmansfm-demo", help="output folder")
    p.add_argument(
        "--input",
        default=None,
        help="your own sequence (folder of images, glob or video) instead of the built-in scene; "
        "corners are detected automatically and there is no ground-truth section",
    )
    p.add_argument("--seed", type=int, default=DEFAULT_SCENE_SEED, help="seed of the built-in scene")
    p.add_argument("--frames", type=int, default=DEFAULT_SCENE_FRAMES, help="number of frames of the built-in scene")
    p.add_argument(
        "--smooth",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="RTS-smooth the tracks (each estimate given the whole sequence) before writing and factorizing them",
    )
    p.add_argument("--matcher", choices=MATCHERS, default=TrackerSettings().matcher,
                   help="differential: Lucas-Kanade from the Kalman prediction, anchored and checked; search: the "
                   "report's exhaustive template search inside the gate (see 'kalmansfm track --help')")
    defaults = TrackerSettings()
    p.add_argument("--max-features", type=int, default=defaults.max_features,
                   help="--input: at most this many corners are detected and tracked")
    p.add_argument("--redetect", action="store_true",
                   help="--input: detect new corners where tracks were lost (see 'kalmansfm track --help')")
    p.add_argument("--reattach", type=int, default=defaults.reattach_frames, metavar="N",
                   help="--input with --redetect: lost tracks found again within N frames keep their ids (see "
                   "'kalmansfm track --help')")
    p.add_argument("--camera", choices=("affine", "perspective"), default="affine",
                   help="affine: factorization; perspective: calibrated reconstruction of your --input with "
                   "--intrinsics or --focal (bundle adjustment, covariances in the free-network gauge)")
    p.add_argument("--intrinsics", metavar="K.csv", type=Path, default=None,
                   help="--camera perspective: the intrinsics, frame,fx,fy,cx,cy,skew (one row for all frames or one "
                   "per frame)")
    p.add_argument("--focal", metavar="F", type=float, default=None,
                   help="--camera perspective: focal length in pixels instead of --intrinsics (principal point at the "
                   "image centre)")
    p.add_argument("--open", action="store_true", help="open report.html in a browser when done")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the pipeline and print a short summary."""
    if args.camera == "affine" and (args.focal is not None or args.intrinsics is not None):
        raise InvalidInputError("--intrinsics and --focal describe a perspective camera: add --camera perspective")
    with as_typed({"n_frames": "--frames", "seed": "--seed", "focal": "--focal", "intrinsics": "--intrinsics",
                   "input": "--input", "max_features": "--max-features", "reattach_frames": "--reattach", "redetect": "--redetect"}):
        camera = Affine() if args.camera == "affine" else Perspective(intrinsics=args.intrinsics, focal=args.focal)
        tracker = TrackerSettings(matcher=args.matcher, max_features=args.max_features, redetect=args.redetect,
                                  reattach_frames=args.reattach)
        result = run_demo(DemoRequest(
            args.out, input=args.input, seed=args.seed, n_frames=args.frames, smooth=args.smooth,
            progress=not args.quiet, camera=camera, tracker=tracker))
    print(describe(result))
    if args.open and result.report is not None:
        webbrowser.open(result.report.resolve().as_uri())
    if result.reconstruction is None:
        # the run folder holds the tracks and says why; a script must still see that the job is not done
        print(f"kalmansfm demo: error: no {args.camera} reconstruction ({result.summary.structure_error}); the tracks "
              f"and the report were written to {result.out_dir}", file=sys.stderr)
        return 1
    return 0
