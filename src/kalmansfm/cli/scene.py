"""``kalmansfm scene``: render the built-in synthetic sequence and its ground truth into a folder."""

from __future__ import annotations

import argparse
import logging

from ..errors import InvalidInputError
from ..pipeline import run_scene
from ..scenes import (
    DEFAULT_SCENE_FRAMES,
    DEFAULT_SCENE_NOISE,
    DEFAULT_SCENE_SEED,
    DEFAULT_SCENE_SIZE,
    SCENARIOS,
    Occluder,
)
from ._options import as_typed

log = logging.getLogger("kalmansfm")


def _size(text: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 320x240; got {text!r}") from None
    return width, height


def _occluder(text: str) -> tuple[int, int, int]:
    try:
        track_id, first_frame, n_frames = (int(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected TRACK,FIRST_FRAME,N_FRAMES such as 2,10,3; got {text!r}") from None
    return track_id, first_frame, n_frames


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "scene",
        parents=parents,
        help="write the built-in synthetic sequence (PNG frames + ground-truth CSVs)",
        description="Render the built-in synthetic scene — a textured house-shaped polyhedron with dark markers "
        "on its corners, turning slowly while it moves across a textured background — and write its frames "
        "(frame_000.png …) with the exact ground truth: ground_truth_tracks.csv, ground_truth_points.csv, "
        "ground_truth_motion.csv and points.csv (frame-0 markers, the input of 'kalmansfm track --points').",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    p.add_argument("--frames", type=int, default=DEFAULT_SCENE_FRAMES, metavar="N", help="number of frames (>= 3)")
    p.add_argument("--size", type=_size, default=DEFAULT_SCENE_SIZE, metavar="WxH", help="image size in pixels")
    p.add_argument("--seed", type=int, default=DEFAULT_SCENE_SEED, metavar="S", help="seed of the textures and the noise")
    p.add_argument("--noise", type=float, default=DEFAULT_SCENE_NOISE, metavar="SIGMA", help="pixel noise std in grey levels")
    p.add_argument(
        "--occluder",
        nargs="?",
        const="2,10,3",
        default=None,
        type=_occluder,
        metavar="TRACK,FIRST,N",
        help="a card passes in front and hides the marker of TRACK in frames FIRST … FIRST+N-1 "
        "(flag alone: 2,10,3)",
    )
    p.add_argument(
        "--occluder-marker",
        action="store_true",
        help="put a marker on the occluder card, so that it crosses the hidden marker",
    )
    p.add_argument(
        "--scenario",
        choices=SCENARIOS,
        default=SCENARIOS[0],
        help="default: the built-in path; 'exit': the object accelerates out through the left border",
    )
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    width, height = args.size
    occluder = None
    if args.occluder is not None:
        track_id, first_frame, n_frames = args.occluder
        occluder = Occluder(track_id=track_id, first_frame=first_frame, n_frames=n_frames, marker=args.occluder_marker)
    elif args.occluder_marker:
        raise InvalidInputError("--occluder-marker needs --occluder")
    typed = {"n_frames": "--frames", "seed": "--seed", "pixel_noise_std": "--noise", "image_size": "--size",
             "occluder.track_id": "--occluder TRACK", "occluder": "--occluder TRACK,FIRST,N"}
    with as_typed(typed):
        scene, files = run_scene(args.out, n_frames=args.frames, image_size=(width, height), seed=args.seed,
                                 pixel_noise_std=args.noise, occluder=occluder, scenario=args.scenario)
    log.info("wrote %d frames and the ground truth to %s", scene.n_frames, args.out)
    print(f"{args.out}: {len(files)} files ({scene.n_frames} frames {width}x{height}, {len(scene.track_ids)} corners)")
    return 0
