"""``kalmansfm tables``: print one of the report's fusion tables with the Kalman columns computed here."""

from __future__ import annotations

import argparse

from ..experiments import available_tasks, fusion_table
from ..experiments.tables import SIMULATED_TASK
from ..experiments.task7 import DEFAULT_FOCAL, DEFAULT_PIXEL_NOISE_STD
from ..report.tables import format_csv, format_text
from ..structure.fusion.landmark import TASK7_DEFAULT_METHOD
from ..structure.fusion import FUSION_METHODS
from ._options import add_hidden_alias, as_typed


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    """Declare ``kalmansfm tables``."""
    tasks = available_tasks()
    p = subparsers.add_parser(
        "tables",
        parents=parents,
        help="print the structure-fusion table of one task, Kalman columns computed by kalmansfm",
        description="Print the table of Task N of Thomas & Oliensis, 'Fusing Structure by Kalman Filtering': "
        "ground truth, measurements and their standard deviations as published, and the fused (Kalman) "
        f"estimate and its standard deviation computed by kalmansfm. Tasks {tasks[0]}-{tasks[-1]} are the report's "
        f"published tables; task {SIMULATED_TASK} simulates its structure-from-motion experiment along the same path "
        "(single-pair triangulation as the measurement, the chosen method's estimate as the Kalman columns).",
    )
    p.add_argument("--task", type=int, required=True, metavar="N", help="task number")
    p.add_argument(
        "--format",
        default="text",
        choices=["text", "csv"],
        help="text: aligned table with error columns; csv: machine-readable, one row per iteration",
    )
    add_task7_options(p)
    p.set_defaults(run=run)


def add_task7_options(parser: argparse.ArgumentParser) -> None:
    """Add the Task 7 simulation options to ``parser``."""
    group = parser.add_argument_group("task 7 (simulated structure from a moving camera)")
    group.add_argument(
        "--method",
        choices=FUSION_METHODS,
        default=TASK7_DEFAULT_METHOD,
        help="pairs: the report's Kalman fusion of consecutive-pair triangulations (over-confident); "
        "recursive: Kalman fusion of the images, inverse depth, iterated EKF (consistent); "
        "batch: Gauss-Newton maximum likelihood on all images so far",
    )
    group.add_argument("--seed", type=int, default=0, help="seed of the simulated image noise")
    group.add_argument("--focal", type=float, default=DEFAULT_FOCAL, help="focal length, pixels")
    group.add_argument(
        "--pixel-std", type=float, default=DEFAULT_PIXEL_NOISE_STD, metavar="PX", help="image noise standard deviation, pixels"
    )
    add_hidden_alias(group, "--pixel-noise", "pixel_std", float)  # the earlier spelling


def run(args: argparse.Namespace) -> int:
    """Compute the table and print it to stdout."""
    with as_typed({"seed": "--seed", "focal": "--focal", "pixel_noise_std": "--pixel-std"}):
        table = fusion_table(args.task, method=args.method, seed=args.seed, focal=args.focal,
                             pixel_noise_std=args.pixel_std)
    text = format_csv(table) if args.format == "csv" else format_text(table)
    print(text, end="" if text.endswith("\n") else "\n")
    return 0
