"""What every subcommand shares about its options: how ``--help`` shows them, and errors in their names.

:class:`HelpFormatter` adds ``(default: …)`` only where it tells the user something: not to
a required option, an option without a default, a plain on/off flag, or a help text that
already names its default; a pair of numbers prints as ``WxH``.

:func:`as_typed` lets a subcommand call the library and still name, in any error, the
option the user typed (``--frames``) instead of the library's argument (``n_frames``).
"""

from __future__ import annotations

import argparse
import math
import os
import re
from collections.abc import Iterator, Mapping
from contextlib import contextmanager

from ..errors import InvalidInputError, KalmanSfmError
from ..io.paths import path_problem
from ..io.summary import RunSummary

__all__ = [
    "HelpFormatter",
    "add_hidden_alias",
    "as_typed",
    "check_path_arguments",
    "command_parser",
    "print_warnings",
    "suspect_arguments",
]

#: A number given as an option beyond these magnitudes is suspect when a computation overflows or runs out of memory.
_LARGEST_FLOAT, _SMALLEST_FLOAT, _LARGEST_COUNT = 1e12, 1e-12, 10**6


class HelpFormatter(argparse.HelpFormatter):
    """``--help`` with each useful default once.

    Examples
    --------
    >>> parser = argparse.ArgumentParser(prog="x", formatter_class=HelpFormatter)
    >>> _ = parser.add_argument("--out", required=True, help="output folder")
    >>> _ = parser.add_argument("--size", type=str, default=(320, 240), help="image size")
    >>> _ = parser.add_argument("--workers", type=int, default=None, help="workers (default: CPU cores)")
    >>> _ = parser.add_argument("--open", action="store_true", help="open it")
    >>> text = parser.format_help()
    >>> "output folder\\n" in text, "(default: 320x240)" in text, text.count("default:"), "%" in text
    (True, True, 2, False)
    """

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        silent = (
            action.required
            or default is None
            or default is argparse.SUPPRESS
            or isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction))
            or "default" in text.lower()
            or not action.option_strings
        )
        if silent:
            return text
        if isinstance(default, tuple) and len(default) == 2:
            shown = "x".join(str(v) for v in default)
        else:
            shown = str(default)
        # argparse %-formats a help text: a literal % in the default must be doubled
        return f"{text} (default: {shown.replace('%', '%%')})"


def add_hidden_alias(parser: argparse.ArgumentParser | argparse._ArgumentGroup, alias: str, dest: str,
                     type: object = None) -> None:
    """Accept ``alias`` as an old spelling of the option stored in ``dest``, not shown in ``--help``.

    Examples
    --------
    >>> parser = argparse.ArgumentParser(prog="x")
    >>> _ = parser.add_argument("--pixel-std", type=float, default=1.0, help="noise")
    >>> add_hidden_alias(parser, "--pixel-noise", "pixel_std", float)
    >>> parser.parse_args(["--pixel-noise", "2"]).pixel_std, parser.parse_args([]).pixel_std
    (2.0, 1.0)
    >>> "--pixel-noise" in parser.format_help()
    False
    """
    parser.add_argument(alias, dest=dest, type=type, default=argparse.SUPPRESS, help=argparse.SUPPRESS)


@contextmanager
def as_typed(names: Mapping[str, str]) -> Iterator[None]:
    """Re-raise a library error that starts with an argument's name with the option's name instead.

    ``names`` maps the library's argument names to the options the user typed, e.g.
    ``{"n_frames": "--frames"}``; the error keeps its class and the rest of its message.

    Examples
    --------
    >>> from kalmansfm.errors import InvalidInputError
    >>> try:
    ...     with as_typed({"n_frames": "--frames"}):
    ...         raise InvalidInputError("n_frames must be an integer >= 3; got 0")
    ... except InvalidInputError as exc:
    ...     print(exc)
    --frames must be an integer >= 3; got 0
    >>> try:
    ...     with as_typed({"focal": "--focal", "intrinsics": "--intrinsics"}):
    ...         raise InvalidInputError("give intrinsics or focal", fields=("intrinsics", "focal"))
    ... except InvalidInputError as exc:
    ...     print(exc)
    give --intrinsics or --focal
    """
    try:
        yield
    except KalmanSfmError as exc:
        message = str(exc)
        named = [name for name in exc.fields if name in names]
        if named:
            # the library said which words of its message are field names: put the options there
            for name in named:
                message = re.sub(rf"(?<![\w-]){re.escape(name)}(?![\w-])", names[name], message)
            raise type(exc)(message) from None
        for name, option in sorted(names.items(), key=lambda item: -len(item[0])):
            if message.startswith(name) and message[len(name):len(name) + 1] in (" ", ":", ";", ","):
                raise type(exc)(option + message[len(name):]) from None
        raise


def print_warnings(summary: RunSummary) -> None:
    """Print a run's warnings to stdout, one ``warning: …`` line each, as every command shows them.

    Parameters
    ----------
    summary : RunSummary
        The finished run's summary; :meth:`~kalmansfm.io.summary.RunSummary.warning_lines` makes the lines.
    """
    for line in summary.warning_lines():
        print(line)


def command_parser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    """The parser of the subcommand ``command`` of the full parser.

    Examples
    --------
    >>> parser = argparse.ArgumentParser(prog="x")
    >>> sub = parser.add_subparsers(dest="command")
    >>> _ = sub.add_parser("go")
    >>> command_parser(parser, "go").prog
    'x go'
    """
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return subparsers.choices[command]


def _label(action: argparse.Action) -> str:
    return action.option_strings[-1] if action.option_strings else str(action.metavar or action.dest)


def _path_actions(parser: argparse.ArgumentParser) -> Iterator[argparse.Action]:
    """The arguments that may name a file or folder: text without a fixed set of choices."""
    for action in parser._actions:
        if action.choices is not None or action.nargs == 0 or action.type in (int, float):
            continue
        if action.dest in ("help", "version") or action.default is argparse.SUPPRESS and action.help is argparse.SUPPRESS:
            continue
        yield action


def check_path_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse, before any work, an argument that names a named pipe, a device, a socket or a link loop.

    Such a path given where kalmansfm reads or writes a file would make it wait for ever (a
    FIFO nobody writes to) or read without end (``/dev/zero``); the one line says what it is.

    Raises
    ------
    InvalidInputError
        ``/dev/zero is a character device, not a file (given as --cameras)``.

    Examples
    --------
    >>> parser = argparse.ArgumentParser(prog="x")
    >>> _ = parser.add_argument("--cameras")
    >>> check_path_arguments(parser, parser.parse_args(["--cameras", "cams.csv"]))
    >>> check_path_arguments(parser, parser.parse_args(["--cameras", "/dev/zero"]))
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: /dev/zero is a character device, not a file (given as --cameras)
    """
    for action in _path_actions(parser):
        value = getattr(args, action.dest, None)
        for item in value if isinstance(value, list) else [value]:
            if isinstance(item, (str, os.PathLike)) and os.fspath(item):
                problem = path_problem(item)
                if problem is not None:
                    raise InvalidInputError(f"{os.fspath(item)} is {problem} (given as {_label(action)})")


def suspect_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[str]:
    """The options given a value so large (or, for a real number, so small) that they may explain an overflow.

    Examples
    --------
    >>> parser = argparse.ArgumentParser(prog="x")
    >>> _ = parser.add_argument("--pixel-std", type=float, default=1.0)
    >>> _ = parser.add_argument("--frames", type=int, default=30)
    >>> _ = parser.add_argument("--seed", type=int, default=0)
    >>> suspect_arguments(parser, parser.parse_args(["--pixel-std", "1e300", "--frames", "100000000", "--seed", "9999999"]))
    ['--pixel-std 1e+300', '--frames 100000000']
    """
    found = []
    for action in parser._actions:
        value = getattr(args, action.dest, None)
        hidden = action.help is argparse.SUPPRESS  # an old spelling of an option that is listed itself
        if hidden or isinstance(value, bool) or not action.option_strings or "seed" in action.dest:
            continue
        if isinstance(value, float) and math.isfinite(value) and value != 0.0:
            suspect = not _SMALLEST_FLOAT <= abs(value) <= _LARGEST_FLOAT
        elif isinstance(value, int):
            suspect = abs(value) > _LARGEST_COUNT
        else:
            continue
        if suspect:
            found.append(f"{_label(action)} {value:g}" if isinstance(value, float) else f"{_label(action)} {value}")
    return found
