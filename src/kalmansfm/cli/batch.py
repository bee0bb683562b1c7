"""``kalmansfm batch``: track and reconstruct many sequences as independent Dask tasks."""

from __future__ import annotations

import argparse

from ..pipeline.batch import run_batch
from ..pipeline.cluster import check_cluster


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    """Declare ``kalmansfm batch``."""
    p = subparsers.add_parser(
        "batch",
        parents=parents,
        help="run the pipeline on many sequences in parallel (Dask)",
        description="Track and reconstruct each SEQUENCE (an image folder, a glob, a video, or scene:SEED for "
        "the built-in scene) as an independent task on dask.distributed: a local cluster by default, or an "
        "existing one with --scheduler. One run folder per sequence in --out (named after the input, the same "
        "in every batch) and a batch_summary.csv. Every sequence is checked first: one that cannot run is a "
        "failed row and the others run; a sequence whose folder holds a finished run of the same input files "
        "and options is skipped. Exit code 0 when every sequence is ok or skipped, 1 when any failed, 2 when "
        "none can run.",
    )
    p.add_argument("sequences", nargs="+", metavar="SEQUENCE", help="image folder, glob, video or scene:SEED")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--workers", type=int, default=None, help="workers of the local cluster (default: CPU cores)")
    p.add_argument("--report", action="store_true", help="also build each sequence's report.html")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the batch; print the summary table; exit 1 if any sequence failed."""
    check_cluster(args.scheduler, args.workers, scheduler_name="--scheduler", workers_name="--workers")
    result = run_batch(
        args.sequences,
        args.out,
        scheduler=args.scheduler,
        n_workers=args.workers,
        html=args.report,
        progress=not args.quiet,
    )
    print(result.table())
    print(f"summary: {result.summary_path}")
    return 1 if result.failed else 0
