"""The ``kalmansfm`` command: a thin shell that parses arguments and calls the library.

Each subcommand lives in its own module in this package with two functions:
``add_parser(subparsers, parents)`` declares its options and ``run(args)``
calls one library function and returns the exit code.

Exit codes: 0 success, 2 bad input or usage (one line on stderr, no
traceback), 1 unexpected failure (rerun with ``--debug`` for the traceback),
130 interrupted (Ctrl-C), 143 terminated (SIGTERM); the line after an interrupt
says whether the new results were written.

What the command prints goes through a guard (:class:`_GuardedStdout`): when standard
output is a closed pipe (``| head -c1``), a full disk (``> /dev/full``) or closed
(``>&-``), the one line on stderr says whether the results were written (exit 0 if they
were, 2 if not), and text the terminal cannot encode (``σ`` on an ASCII terminal, a file
name that is not UTF-8) is written as its closest ASCII or its original bytes.  NumPy's
RuntimeWarnings ("overflow encountered") are held back while the command runs: dropped when
it ends in an error line (the absurd value the line names caused them), shown one line each
when it succeeds.

This module imports nothing heavy at load time (the parser is in :mod:`.parser`): the
console entry point (:func:`run`) sets up its signal handling first and only then loads
argparse, NumPy, OpenCV and the commands, so that a Ctrl-C in the first second is the
same one line.
"""

from __future__ import annotations

import codecs
import os
import signal
import sys
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

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


#: How a character the terminal cannot show is written: the nearest ASCII (an ASCII-only terminal).
_ASCII = {"σ": "sigma", "Σ": "Sigma", "χ": "chi", "λ": "lambda", "μ": "u", "±": "+/-", "×": "x", "…": "...",
          "≥": ">=", "≤": "<=", "≈": "~", "²": "^2", "³": "^3", "⁻": "^-", "¹": "1", "—": "--", "–": "-", "−": "-",
          "·": ".", "→": "->", "√": "sqrt", "°": " deg", "‖": "||", "θ": "theta", "π": "pi", "∞": "inf"}


def _terminal_fallback(exc: UnicodeError) -> tuple[str | bytes, int]:
    """Encoding error handler of the command's output: a file name's original bytes, else the nearest ASCII."""
    if not isinstance(exc, UnicodeEncodeError):
        raise exc
    text = exc.object[exc.start:exc.end]
    if all("\udc80" <= c <= "\udcff" for c in text):  # bytes of a file name that were not valid text
        return bytes(ord(c) - 0xDC00 for c in text), exc.end
    return "".join(_ASCII.get(c, f"\\u{ord(c):04x}") for c in text), exc.end


codecs.register_error("kalmansfm-terminal", _terminal_fallback)


class _OutputLost(Exception):
    """Standard output could not take what the command printed (a closed pipe, a full disk, closed)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class _GuardedStdout:
    """``sys.stdout`` while a command runs: a failed write is :class:`_OutputLost`; unencodable text is replaced."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def _reason(self, exc: BaseException) -> str:
        if isinstance(exc, OSError):
            return exc.strerror or str(exc)
        return "standard output is closed"

    def write(self, text: str) -> int:
        if self._stream is None:
            raise _OutputLost("standard output is closed")
        try:
            try:
                return self._stream.write(text)
            except UnicodeEncodeError:
                encoding = getattr(self._stream, "encoding", None) or "utf-8"
                data = text.encode(encoding, "kalmansfm-terminal")
                buffer = getattr(self._stream, "buffer", None)
                if buffer is None:
                    return self._stream.write(data.decode(encoding, "replace"))
                self._stream.flush()
                buffer.write(data)
                return len(text)
        except (OSError, ValueError) as exc:  # ValueError: "I/O operation on closed file"
            raise _OutputLost(self._reason(exc)) from None

    def flush(self) -> None:
        if self._stream is None:
            return
        try:
            self._stream.flush()
        except (OSError, ValueError) as exc:
            raise _OutputLost(self._reason(exc)) from None

    def isatty(self) -> bool:
        return self._stream is not None and self._stream.isatty()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def _discard_output(stream: Any) -> None:
    """After a failed write, point the process's standard output at the null device.

    Python flushes stdout again when it exits; on the same closed pipe that would print an
    "Exception ignored … BrokenPipeError" traceback after our line.
    """
    if stream is None or stream is not sys.__stdout__:
        return
    try:
        descriptor = stream.fileno()
        null = os.open(os.devnull, os.O_WRONLY)
    except (OSError, ValueError):
        return
    os.dup2(null, descriptor)
    os.close(null)


def _say(text: str) -> None:
    """One line on stderr; a stderr that is gone too can take nothing more."""
    try:
        print(text, file=sys.stderr)
    except (OSError, ValueError):
        pass


@contextmanager
def _runtime_warnings_held(held: list[str], debug: bool) -> Iterator[None]:
    """Collect NumPy's RuntimeWarnings (one line each, once) instead of printing them as they come."""
    if debug:
        yield
        return
    with warnings.catch_warnings():
        shown = warnings.showwarning

        def hold(message: Any, category: type[Warning], filename: str, lineno: int, file: Any = None,
                 line: str | None = None) -> None:
            if issubclass(category, RuntimeWarning):
                text = f"warning: {message} ({os.path.basename(filename)}:{lineno})"
                if text not in held:
                    held.append(text)
            else:
                shown(message, category, filename, lineno, file, line)

        warnings.showwarning = hold
        yield


def _out_of_range(prog: str, exc: BaseException, suspects: list[str]) -> str | None:
    """The line for an overflow or an exhausted memory that an option's absurd value explains, or None."""
    if isinstance(exc, MemoryError):
        blame = f"; {', '.join(suspects)} is probably too large" if suspects else "; an input file or an option is too large"
        return f"{prog}: error: not enough memory for this run{blame} for this machine"
    if isinstance(exc, (OverflowError, FloatingPointError)) and suspects:
        reason = exc.args[-1] if exc.args and isinstance(exc.args[-1], str) else str(exc) or type(exc).__name__
        return f"{prog}: error: {', '.join(suspects)}: too far from any sensible value to compute with ({reason})"
    return None


def _not_utf8(prog: str, exc: BaseException) -> str | None:
    """The line for a file name that could not be written as text into a result file, or None."""
    if not isinstance(exc, UnicodeEncodeError) or not any("\udc80" <= c <= "\udcff" for c in exc.object):
        return None
    start = exc.start
    while start > 0 and exc.object[start - 1] not in "\n\"'<>=/ ":
        start -= 1
    end = exc.end
    while end < len(exc.object) and exc.object[end] not in "\n\"'<>=/ ":
        end += 1
    shown = exc.object[start:end]
    if sys.getfilesystemencoding().lower() in ("ascii", "ansi_x3.4-1968"):
        why = ("Python reads file names as ASCII under the C locale; run with PYTHONUTF8=1 or LANG=C.UTF-8, or "
               "rename it")
    else:
        why = "it is not valid UTF-8; rename it"
    return f"{prog}: error: the name {shown} cannot be written into the results as text ({why})"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line with ``argv`` (default ``sys.argv[1:]``) and return the exit code."""
    prog, debug, commits_before = "kalmansfm", False, _commits()[0]
    _Stopping.reporting = False
    held: list[str] = []
    suspects: list[str] = []
    stdout = sys.stdout
    sys.stdout = _GuardedStdout(stdout)  # type: ignore[assignment]
    try:
        parser = build_parser()  # imports every command, NumPy and OpenCV
        args = parser.parse_args(argv)
        prog, debug = f"kalmansfm {args.command}", args.debug
        from ._options import check_path_arguments, command_parser, suspect_arguments
        from .parser import show_log

        show_log(quiet=getattr(args, "quiet", False))
        command = command_parser(parser, args.command)
        suspects = suspect_arguments(command, args)
        check_path_arguments(command, args)
        with _runtime_warnings_held(held, debug):
            code = int(args.run(args) or 0)
        for line in held:
            print(line, file=sys.stderr)
        sys.stdout.flush()
        return code
    except _OutputLost as lost:
        _close_progress_bars()
        _discard_output(stdout)
        count, written = _commits()
        if count > commits_before:
            _say(f"{prog}: wrote {written}; what it printed could not be written to standard output ({lost.reason})")
            return 0
        _say(f"{prog}: error: cannot write to standard output ({lost.reason}); no results were written")
        return 2
    except KalmanSfmError as exc:
        _close_progress_bars()
        _say(f"{prog}: error: {exc}")
        return 2
    except OSError as exc:  # the file system refused (a full disk, a permission): the user can act on it
        _close_progress_bars()
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        _say(f"{prog}: error: {where}{exc.strerror or exc}")
        return 2
    except KeyboardInterrupt as exc:
        _Stopping.reporting = True
        _close_progress_bars()
        number = exc.signal_number if isinstance(exc, Interrupted) else signal.SIGINT
        word = "terminated" if number == signal.SIGTERM else "interrupted"
        _say(f"{prog}: {word}; {_interrupt_message(exc, commits_before)}")
        return 128 + int(number)
    except Exception as exc:
        if _signals_received:
            # A Ctrl-C that lands while a compiled module initialises comes out of the import as
            # that module's own error (NumPy: "ImportError: initialization failed"): an interrupt.
            _Stopping.reporting = True
            _close_progress_bars()
            number = _signals_received[-1]
            word = "terminated" if number == signal.SIGTERM else "interrupted"
            _say(f"{prog}: {word}; {_interrupt_message(KeyboardInterrupt(), commits_before)}")
            return 128 + int(number)
        line = _out_of_range(prog, exc, suspects) or _not_utf8(prog, exc)
        if line is not None and not debug:
            _close_progress_bars()
            _say(line)
            return 2
        if debug:  # a bug, not a user mistake
            raise
        _close_progress_bars()
        _say(f"{prog}: unexpected error: {type(exc).__name__}: {exc} (rerun with --debug for the traceback)")
        return 1
    finally:
        sys.stdout = stdout


#: The signals (SIGINT, SIGTERM) the command line has received in this process.
_signals_received: list[int] = []


class _Stopping:
    """Whether :func:`main` is already saying how the command stopped: a further signal changes nothing then."""

    reporting = False


def _terminate(signum: int, frame: object) -> None:
    """SIGTERM handler: stop the way Ctrl-C does, so that staged files are removed on the way out."""
    _signals_received.append(signum)
    if not _Stopping.reporting:
        raise Interrupted(signal_number=signum)


def _interrupt(signum: int, frame: object) -> None:
    """SIGINT handler: Python's own (KeyboardInterrupt), remembering that the signal came."""
    _signals_received.append(signum)
    if not _Stopping.reporting:
        raise KeyboardInterrupt


def _interrupt_again(unraisable: Any) -> None:
    """``sys.unraisablehook``: an interrupt that a finalizer swallowed is sent again instead of printed.

    A signal handler raises wherever the interpreter happens to be; inside a weakref callback or
    a ``__del__`` the exception cannot propagate, so Python printed "Exception ignored in: …" with
    a traceback and the command ran on to exit 0 (issue 30's sweep).  The same signal is raised
    again from a timer thread a moment later, when the main thread is most likely back in
    ordinary code; it is delivered like the first.
    """
    exception = unraisable.exc_value
    if not isinstance(exception, KeyboardInterrupt):
        sys.__unraisablehook__(unraisable)
        return
    if _Stopping.reporting:
        return
    import threading

    number = exception.signal_number if isinstance(exception, Interrupted) else signal.SIGINT
    timer = threading.Timer(0.05, signal.raise_signal, (int(number),))
    timer.daemon = True
    timer.start()


def run() -> None:
    """Console-script entry point: signal handling first, then the command."""
    reconfigure = getattr(sys.stderr, "reconfigure", None)
    if reconfigure is not None:  # our lines name files as the user typed them, in any locale
        reconfigure(errors="kalmansfm-terminal")
    signal.signal(signal.SIGTERM, _terminate)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not when Ctrl-C is ignored
        signal.signal(signal.SIGINT, _interrupt)
    sys.unraisablehook = _interrupt_again
    code = main()
    # The command is over and has said what happened: a Ctrl-C or SIGTERM while Python shuts down
    # (a tenth of a second with NumPy, OpenCV and Matplotlib loaded) must not end the process by
    # the signal, with nothing said and the exit code lost.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    sys.exit(code)
