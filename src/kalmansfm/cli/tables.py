"""``kalmansfm tables``: print one of the report's fusion tables with the Kalman columns computed here."""

from __future__ import annotations

import argparse

from ..errors import InvalidInputError
from ..report.tables import format_csv, format_text
from ..scenes.fusion_tasks import available_tasks, run_task
from .task7 import add_task7_options, run_task7

SIMULATED_TASK = 7


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
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
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


def run(args: argparse.Namespace) -> int:
    """Compute the table and print it to stdout."""
    published = available_tasks()
    if args.task == SIMULATED_TASK:
        table = run_task7(args)
    elif args.task in published:
        table = run_task(args.task)
    else:
        raise InvalidInputError(
            f"unknown task {args.task}; tasks {published[0]}-{published[-1]} (published tables) "
            f"and {SIMULATED_TASK} (simulated moving camera) are available"
        )
    text = format_csv(table) if args.format == "csv" else format_text(table)
    print(text, end="" if text.endswith("\n") else "\n")
    return 0
