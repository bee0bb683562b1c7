"""``kalmansfm consistency``: is the reported uncertainty honest?  Monte Carlo NEES test."""

from __future__ import annotations

import argparse
import sys

from tqdm import tqdm

from ..errors import InvalidInputError
from ..experiments.consistency import SPACES, run_consistency
from ..experiments.task7 import DEFAULT_FOCAL, DEFAULT_PIXEL_NOISE_STD
from ..report.consistency import consistency_csv, consistency_text
from ..structure.fusion.landmark import TASK7_DEFAULT_METHOD
from ..structure.fusion import FUSION_METHODS
from ._options import add_hidden_alias, as_typed


class _StoreMethod(argparse.Action):
    """Store ``--method`` and note that it was given (its default is Task 7's, shown by ``--help``)."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object,
                 option_string: str | None = None) -> None:
        setattr(namespace, self.dest, values)
        namespace.method_given = True


def add_parser(subparsers: argparse._SubParsersAction, parents: list[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "consistency",
        parents=parents,
        help="Monte Carlo check of the fused uncertainty (NEES, 1σ/3σ fractions)",
        description="Simulate an experiment N times with known truth and check whether each estimator's "
        "covariance matches its actual errors: per axis the fraction of errors within 1σ and 3σ, and the mean "
        "NEES with its 95 % chi-square interval.  PASS means the final iteration's mean NEES is inside it.",
    )
    p.add_argument("--task", type=int, choices=[2, 7], required=True, help="Task 2 (1D fusion) or Task 7 (landmark)")
    p.add_argument("--method", choices=FUSION_METHODS, default=TASK7_DEFAULT_METHOD, action=_StoreMethod,
                   help="Task 7 estimator")
    p.add_argument("--runs", type=int, default=300, help="number of Monte Carlo runs N (>= 2)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated noise")
    p.add_argument("--focal", type=float, default=DEFAULT_FOCAL, help="Task 7 focal length, pixels")
    p.add_argument(
        "--pixel-std", type=float, default=DEFAULT_PIXEL_NOISE_STD, metavar="PX", help="Task 7 image noise std, pixels"
    )
    add_hidden_alias(p, "--pixel-noise", "pixel_std", float)  # the earlier spelling
    p.add_argument(
        "--space", choices=[x.replace("_", "-") for x in SPACES], default="point",
        help="Task 7: judge the point (x, y, z) in the current camera frame, or (--method recursive) the "
        "filter's own state, the inverse depth in the first camera frame",
    )
    p.add_argument("--format", choices=["text", "csv"], default="text", help="summary text or per-iteration CSV")
    p.set_defaults(run=run, method_given=False)


def run(args: argparse.Namespace) -> int:
    if args.task == 2 and args.method_given:
        raise InvalidInputError("--method applies to --task 7 only (task 2 is plain Kalman fusion)")
    if args.task == 2 and args.space != "point":
        raise InvalidInputError("--space applies to --task 7 only")
    bars: list[tqdm] = []

    def progress(n: int = 1) -> None:
        # the bar appears with the first finished run, after run_consistency has checked the options
        if not bars:
            bars.append(tqdm(total=args.runs, desc=f"task {args.task} runs", unit="run", disable=args.quiet,
                             file=sys.stderr))
        bars[0].update(n)

    try:
        with as_typed({"runs": "--runs", "seed": "--seed", "focal": "--focal", "pixel_noise_std": "--pixel-std"}):
            result = run_consistency(
                args.task, args.method if args.task == 7 else None, args.runs, args.seed, args.focal, args.pixel_std, progress=progress,
                space=args.space.replace("-", "_"),
            )
    finally:
        for bar in bars:
            bar.close()
    sys.stdout.write(consistency_text(result) if args.format == "text" else consistency_csv(result))
    return 0
