"""``kalmansfm batch``: track and reconstruct many sequences as independent Dask tasks."""

from __future__ import annotations

import argparse

from ..pipeline.batch import check_sequence, run_batch
from ..errors import InvalidInputError


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    """Declare ``kalmansfm batch``."""
    p = subparsers.add_parser(
        "batch",
        parents=parents,
        help="run the pipeline on many sequences in parallel (Dask)",
        description="Track and reconstruct each SEQUENCE (an image folder, a glob, a video, or scene:SEED for "
        "the built-in scene) as an independent task on dask.distributed: a local cluster by default, or an "
        "existing one with --scheduler. One run folder per sequence in --out and a batch_summary.csv; a failing "
        "sequence does not stop the others, and sequences whose folder already has a summary.json are skipped.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("sequences", nargs="+", metavar="SEQUENCE", help="image folder, glob, video or scene:SEED")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--workers", type=int, default=None, help="workers of the local cluster (default: CPU cores)")
    p.add_argument("--report", action="store_true", help="also build each sequence's report.html")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the batch; print the summary table; exit 1 if any sequence failed."""
    # Mistakes visible before any work (a misspelt path, a bad scene:SEED) stop the run at once;
    # the library's run_batch would instead report them as failed rows after the others ran.
    for spec in args.sequences:
        check_sequence(spec)
    if args.workers is not None and args.workers < 1:
        raise InvalidInputError(f"--workers must be >= 1; got {args.workers}")
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
