"""The ``kalmansfm`` command: a thin shell that parses arguments and calls the library.

Each subcommand lives in its own module in this package with two functions:
``add_parser(subparsers, parents)`` declares its options and ``run(args)``
calls one library function and returns the exit code.

Exit codes: 0 success, 2 bad input or usage (one line on stderr, no
traceback), 1 unexpected failure (rerun with ``--debug`` for the traceback),
130 interrupted (Ctrl-C), 143 terminated (SIGTERM); the line after an interrupt
says whether the new results were written.

This module imports nothing heavy at load time (the parser is in :mod:`.parser`): the
console entry point (:func:`run`) sets up its signal handling first and only then loads
argparse, NumPy, OpenCV and the commands, so that a Ctrl-C in the first second is the
same one line.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

from ..errors import Interrupted, KalmanSfmError

if TYPE_CHECKING:
    import argparse

# Order shown in --help.
SUBCOMMANDS = ["demo", "track", "reconstruct", "fuse", "export", "report", "batch", "tables", "consistency", "scene"]


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every subcommand."""
    from .parser import make_parser

    return make_parser(SUBCOMMANDS)


def _commits() -> tuple[int, object]:
    """(run folders committed by this process, the last one), without importing anything.

    After Ctrl-C a module may be half imported; importing more would fail in odd ways.
    A process that has not loaded kalmansfm.io.atomic has committed nothing.
    """
    last_commit = getattr(sys.modules.get("kalmansfm.io.atomic"), "last_commit", None)
    return last_commit() if last_commit is not None else (0, None)


def _close_progress_bars() -> None:
    """Erase the progress bars an error or interrupt left open, so that our one line starts the line.

    A bar interrupted while it was being drawn does not always erase itself when closed;
    then the line is returned to (and on a terminal cleared) by hand.
    """
    bar_class = getattr(sys.modules.get("tqdm"), "tqdm", None)
    shown = [bar for bar in list(getattr(bar_class, "_instances", ())) if not getattr(bar, "disable", True)]
    for bar in shown:
        bar.close()
    if shown:
        sys.stderr.write("\r\033[K" if sys.stderr.isatty() else "\r")


def _interrupt_message(exc: KeyboardInterrupt, commits_before: int) -> str:
    """What is on disk after an interrupt, for the one line the command prints."""
    if str(exc):  # the command said it itself (batch: which sequences finished)
        return str(exc)
    count, folder = _commits()
    if count > commits_before:
        return f"the new results were written to {folder} before it stopped"
    return "earlier results were left as they were"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``) and return the exit code."""
    prog, debug, commits_before = "kalmansfm", False, _commits()[0]
    try:
        parser = build_parser()  # imports every command, NumPy and OpenCV
        args = parser.parse_args(argv)
        prog, debug = f"kalmansfm {args.command}", args.debug
        from .parser import show_log

        show_log(quiet=getattr(args, "quiet", False))
        return int(args.run(args) or 0)
    except KalmanSfmError as exc:
        _close_progress_bars()
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the file system refused (a full disk, a permission): the user can act on it
        _close_progress_bars()
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"{prog}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        _close_progress_bars()
        number = exc.signal_number if isinstance(exc, Interrupted) else signal.SIGINT
        word = "terminated" if number == signal.SIGTERM else "interrupted"
        print(f"{prog}: {word}; {_interrupt_message(exc, commits_before)}", file=sys.stderr)
        return 128 + int(number)
    except Exception as exc:
        if _signals_received:
            # A Ctrl-C that lands while a compiled module initialises comes out of the import as
            # that module's own error (NumPy: "ImportError: initialization failed"): an interrupt.
            _close_progress_bars()
            number = _signals_received[-1]
            word = "terminated" if number == signal.SIGTERM else "interrupted"
            print(f"{prog}: {word}; {_interrupt_message(KeyboardInterrupt(), commits_before)}", file=sys.stderr)
            return 128 + int(number)
        if debug:  # a bug, not a user mistake
            raise
        _close_progress_bars()
        print(
            f"{prog}: unexpected error: {type(exc).__name__}: {exc} (rerun with --debug for the traceback)",
            file=sys.stderr,
        )
        return 1


#: The signals (SIGINT, SIGTERM) the command line has received in this process.
_signals_received: list[int] = []


def _terminate(signum: int, frame: object) -> None:
    """SIGTERM handler: stop the way Ctrl-C does, so that staged files are removed on the way out."""
    _signals_received.append(signum)
    raise Interrupted(signal_number=signum)


def _interrupt(signum: int, frame: object) -> None:
    """SIGINT handler: Python's own (KeyboardInterrupt), remembering that the signal came."""
    _signals_received.append(signum)
    raise KeyboardInterrupt


def run() -> None:
    """Console-script entry point: signal handling first, then the command."""
    signal.signal(signal.SIGTERM, _terminate)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not when Ctrl-C is ignored
        signal.signal(signal.SIGINT, _interrupt)
    code = main()
    # The command is over and has said what happened: a Ctrl-C or SIGTERM while Python shuts down
    # (a tenth of a second with NumPy, OpenCV and Matplotlib loaded) must not end the process by
    # the signal, with nothing said and the exit code lost.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    sys.exit(code)
