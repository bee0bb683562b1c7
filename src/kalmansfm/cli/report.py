"""``kalmansfm report DIR``: rebuild the HTML report of a finished run from its files."""

from __future__ import annotations

import argparse
import webbrowser
from pathlib import Path

from ..report.html import build_report
from ._options import as_typed


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    """Declare ``kalmansfm report``."""
    p = subparsers.add_parser(
        "report",
        parents=parents,
        help="rebuild report.html of a finished run folder",
        description="Rebuild the self-contained report.html of a finished run (for example the folder "
        "'kalmansfm demo' wrote) from the files in it, without recomputing anything. The folder needs "
        "summary.json; every other file (frames/, tracks.npz, structure.csv, motion.csv, ground truth, "
        "fusion_tables/) adds its section when present.",
    )
    p.add_argument("run_dir", metavar="DIR", type=Path, help="the run folder (contains summary.json)")
    p.add_argument("--name", default="report.html", help="file name of the report inside DIR")
    p.add_argument("--open", action="store_true", help="open the report in the default web browser")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Build the report, print its path, optionally open it."""
    with as_typed({"out_name": "--name"}):
        report = build_report(args.run_dir, out_name=args.name, progress=not args.quiet)
    print(report)
    if args.open:
        webbrowser.open(report.resolve().as_uri())
    return 0
