"""The argument parser of the ``kalmansfm`` command and its log output (loaded by :mod:`.main` when a command starts)."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from .._version import __version__
from ._options import HelpFormatter

__all__ = ["make_parser", "show_log"]

log = logging.getLogger("kalmansfm")


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are a single line."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


class _CurrentStderrHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever ``sys.stderr`` is when a record is emitted.

    A plain ``StreamHandler(sys.stderr)`` keeps the stream of the first call of
    :func:`~kalmansfm.cli.main.main`; when ``main`` runs again in the same process after
    sys.stderr was replaced (pytest's capture, a notebook) it wrote to a closed file and
    printed a "--- Logging error ---" traceback.
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


def make_parser(subcommands: Sequence[str]) -> argparse.ArgumentParser:
    """The full argument parser with the ``subcommands`` (modules of this package), in that order."""
    parser = _Parser(
        prog="kalmansfm",
        description="Track points through video with Kalman filters, recover 3D shape and camera motion "
        "by factorization, and fuse noisy 3D structure with honest uncertainty.",
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"kalmansfm {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    common = _common_options()
    for name in subcommands:
        module = importlib.import_module(f"{__package__}.{name.replace('-', '_')}")
        module.add_parser(sub, [common])
    for subparser in sub.choices.values():
        subparser.formatter_class = HelpFormatter  # one way of showing defaults in every --help
    return parser


def show_log(quiet: bool) -> None:
    """Send our own logger's lines to stderr (libraries we call, Dask and Matplotlib, keep their defaults)."""
    if not log.handlers:
        handler = _CurrentStderrHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(handler)
        log.propagate = False
    log.setLevel(logging.WARNING if quiet else logging.INFO)
