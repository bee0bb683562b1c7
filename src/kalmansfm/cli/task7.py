"""Task 7 options and handler for ``kalmansfm tables --task 7`` (wired in by the tables subcommand).

``add_task7_options(parser)`` declares ``--method``, ``--seed``, ``--focal`` and
``--pixel-noise``; ``run_task7(args)`` simulates the experiment with
:func:`kalmansfm.structure.task7.simulate_task7` and returns a
:class:`~kalmansfm.report.tables.FusionTable` (``meas_*`` the single-pair
triangulation, ``kalman_*`` the method's estimate).
"""

from __future__ import annotations

import argparse

from ..report.tables import FusionTable
from ..structure.landmark import METHODS
from ..structure.task7 import DEFAULT_FOCAL, DEFAULT_PIXEL_NOISE_STD, simulate_task7

__all__ = ["add_task7_options", "run_task7"]


def add_task7_options(parser: argparse.ArgumentParser) -> None:
    """Add the Task 7 simulation options to ``parser``."""
    group = parser.add_argument_group("task 7 (simulated structure from a moving camera)")
    group.add_argument(
        "--method",
        choices=METHODS,
        default="pairs",
        help="pairs: the report's Kalman fusion of consecutive-pair triangulations; "
        "batch: Gauss-Newton maximum likelihood on all images so far (consistent)",
    )
    group.add_argument("--seed", type=int, default=0, help="seed of the simulated image noise")
    group.add_argument("--focal", type=float, default=DEFAULT_FOCAL, help="focal length, pixels")
    group.add_argument(
        "--pixel-noise", type=float, default=DEFAULT_PIXEL_NOISE_STD, help="image noise standard deviation, pixels"
    )


def run_task7(args: argparse.Namespace) -> FusionTable:
    """Simulate Task 7 with the parsed options and return its table."""
    r = simulate_task7(method=args.method, seed=args.seed, focal=args.focal, pixel_noise_std=args.pixel_noise)
    return FusionTable(r.task, r.title, r.truth, r.measured, r.measured_std, r.estimate, r.estimate_std)
