"""What every subcommand shares about its options: how ``--help`` shows them, and errors in their names.

:class:`HelpFormatter` adds ``(default: …)`` only where it tells the user something: not to
a required option, an option without a default, a plain on/off flag, or a help text that
already names its default; a pair of numbers prints as ``WxH``.

:func:`as_typed` lets a subcommand call the library and still name, in any error, the
option the user typed (``--frames``) instead of the library's argument (``n_frames``).
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator, Mapping
from contextlib import contextmanager

from ..errors import KalmanSfmError
from ..io.summary import RunSummary

__all__ = ["HelpFormatter", "add_hidden_alias", "as_typed", "print_warnings"]


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
