"""The ``kalmansfm`` command: a thin shell that parses arguments and calls the library.

Each subcommand lives in its own module in this package with two functions:
``add_parser(subparsers, parents)`` declares its options and ``run(args)``
calls one library function and returns the exit code.

Exit codes: 0 success, 2 bad input or usage (one line on stderr, no
traceback), 1 unexpected failure (rerun with ``--debug`` for the traceback),
130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from .._version import __version__
from ..errors import KalmanSfmError, ReportInterrupted

# Order shown in --help.
SUBCOMMANDS = ["demo", "track", "reconstruct", "fuse", "report", "batch", "tables", "consistency", "scene"]

log = logging.getLogger("kalmansfm")


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are a single line."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


class _CurrentStderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever ``sys.stderr`` is when a record is emitted.

    A plain ``StreamHandler(sys.stderr)`` keeps the stream of the first call of
    :func:`main`; when ``main`` runs again in the same process after sys.stderr was
    replaced (pytest's capture, a notebook) it wrote to a closed file and printed a
    "--- Logging error ---" traceback.
    """

    @property  # type: ignore[override]
    def stream(self):  # type: ignore[no-untyped-def]
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # type: ignore[no-untyped-def]
        pass


def _common_options() -> argparse.ArgumentParser:
    common = _Parser(add_help=False)
    common.add_argument("--quiet", "-q", action="store_true", help="no progress bars or log lines")
    common.add_argument("--debug", action="store_true", help="show the traceback of an unexpected error")
    return common


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every subcommand."""
    parser = _Parser(
        prog="kalmansfm",
        description="Track points through video with Kalman filters, recover 3D shape and camera motion "
        "by factorization, and fuse noisy 3D structure with honest uncertainty.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"kalmansfm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    common = _common_options()
    for name in SUBCOMMANDS:
        module = importlib.import_module(f"{__package__}.{name.replace('-', '_')}")
        module.add_parser(sub, [common])
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``) and return the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    # Configure our own logger only: libraries we call (Dask, Matplotlib) keep their defaults.
    if not log.handlers:
        handler = _CurrentStderrHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(handler)
        log.propagate = False
    log.setLevel(logging.WARNING if getattr(args, "quiet", False) else logging.INFO)
    prog = f"kalmansfm {args.command}"
    try:
        return int(args.run(args) or 0)
    except KalmanSfmError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        print(f"{prog}: error:{where}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        what = str(exc) if isinstance(exc, ReportInterrupted) else "earlier results were left as they were"
        print(f"{prog}: interrupted; {what}", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug, not a user mistake
        if args.debug:
            raise
        print(
            f"{prog}: unexpected error: {type(exc).__name__}: {exc} (rerun with --debug for the traceback)",
            file=sys.stderr,
        )
        return 1


def run() -> None:
    """Console-script entry point."""
    sys.exit(main())
