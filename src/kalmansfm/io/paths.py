"""What a path given as input really is, in words: the checks every reader and the command line share.

A named pipe, a device, a socket or a symbolic link loop given where a file is expected
would make a reader hang (a FIFO nobody writes to), allocate without end (``/dev/zero``)
or fail with a Python error; :func:`path_problem` says what it is instead, so that the
message can be "… is a named pipe (FIFO), not a file" rather than "no such file".

:func:`resolved` is :meth:`pathlib.Path.resolve` that reports a link loop as bad input, and
:func:`native_path` is the text to hand to a native library (OpenCV) for a path whose name
may not be valid UTF-8 (OpenCV crashes on such text).
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from ..errors import InvalidInputError

__all__ = ["native_path", "path_problem", "resolved"]

_SPECIAL = (
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def path_problem(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` can be neither a regular file nor a folder, in words; None when it is one, or does not exist.

    Examples
    --------
    >>> path_problem("/dev/null")
    'a character device, not a file'
    >>> path_problem(".") is None, path_problem("no/such/file") is None
    (True, True)
    """
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "a broken symbolic link" if os.path.islink(path) else None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "a symbolic link loop"
        if exc.errno == errno.ENOTDIR:
            return None
        return f"not readable ({exc.strerror or exc})"
    except ValueError:  # an embedded NUL
        return "not a valid path"
    for test, words in _SPECIAL:
        if test(mode):
            return f"{words}, not a file"
    return None


def resolved(path: str | os.PathLike[str]) -> Path:
    """``Path(path).resolve()``; a symbolic link loop is :class:`InvalidInputError` naming the path.

    Examples
    --------
    >>> resolved("/") == Path("/")
    True
    """
    try:
        return Path(path).resolve()
    except (RuntimeError, OSError) as exc:  # a loop: RuntimeError up to Python 3.12, OSError (ELOOP) after
        raise InvalidInputError(f"{os.fspath(path)} is a symbolic link loop ({exc})") from None


def native_path(path: str | os.PathLike[str]) -> str | None:
    """The path as UTF-8 text for OpenCV, which crashes on names that are not valid UTF-8; None for such a name.

    A name read under the C locale holds its UTF-8 bytes as escapes (``'d\\udcc3\\udca9'`` for
    ``dé``); its UTF-8 text names the same file.  A name whose bytes are not UTF-8 has no such
    text (None): open the file from Python and decode the bytes instead.

    Examples
    --------
    >>> native_path("frames/f0.png"), native_path(os.fsdecode(b"bad\\xff.avi")) is None
    ('frames/f0.png', True)
    """
    try:
        return os.fsencode(path).decode("utf-8")
    except UnicodeDecodeError:
        return None
