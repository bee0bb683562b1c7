"""How every CSV writer of ``io`` spells numbers and joins rows, and how every CSV reader splits a file."""

from __future__ import annotations

import csv
import os
import re
import stat
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import InvalidInputError


def number(value: float) -> str:
    """The shortest text that reads back as the same float; an empty cell for NaN or ±inf (no value).

    Examples
    --------
    >>> number(0.1), number(2.0), number(float("nan"))
    ('0.1', '2.0', '')
    """
    return "" if not np.isfinite(value) else repr(float(value))


def csv_text(header: Iterable[str], rows: Iterable[Iterable[object]]) -> str:
    """A header line and one line per row, values joined by commas (already formatted or ``str``-able).

    Examples
    --------
    >>> csv_text(["a", "b"], [[1, "x"]])
    'a,b\\n1,x\\n'
    """
    lines = [",".join(header)]
    lines.extend(",".join(str(v) for v in row) for row in rows)
    return "\n".join(lines) + "\n"


#: A field that ``%r`` or ``%f`` formatting wrote for a number that is not finite; writers blank it (no value).
NOT_FINITE_FIELD = re.compile(r"(?<=,)-?(?:nan|inf)(?=[,\n])")

#: Rows a large table's writer formats into one piece of text at a time (``history.csv``).
CSV_CHUNK_ROWS = 65_536


# --- reading ------------------------------------------------------------------------------------


def where(path: str | os.PathLike[str], *lines: int) -> str:
    """Where a problem in an input file is, the prefix of every message that names one.

    ``FILE`` for the whole file, ``FILE: line N`` for one line (the file's own 1-based line, as
    :func:`read_rows` gives it, the header included), ``FILE: lines N and M`` for two. The message
    follows after ``": "``.

    Examples
    --------
    >>> where("a/points.csv"), where("points.csv", 4), where("K.csv", 2, 5)
    ('a/points.csv', 'points.csv: line 4', 'K.csv: lines 2 and 5')
    """
    text = os.fspath(path)
    if not lines:
        return text
    if len(lines) == 1:
        return f"{text}: line {int(lines[0])}"
    return f"{text}: lines {', '.join(str(int(n)) for n in lines[:-1])} and {int(lines[-1])}"


_NEWLINE = re.compile(r"\r\n|\r|\n")


class CsvRows(NamedTuple):
    """What :func:`read_rows` gives: the header (names stripped), its line and the data rows.

    ``rows`` holds ``(line, fields)`` pairs, ``line`` the 1-based line of the file where the row
    starts and ``fields`` its cells as written (not stripped), as many as the header has.
    """

    header: list[str]
    header_line: int
    rows: list[tuple[int, list[str]]]


#: The most bytes a CSV reader reads: a larger file is refused before it is read (it would not fit in memory
#: as rows of text; a tracks CSV of 10⁶ observations is about 60 MB).
MAX_CSV_BYTES = 1 << 30


def read_file_bytes(path: str | os.PathLike[str], kind: str, max_bytes: int) -> bytes:
    """The bytes of a regular file, refusing what is not one before reading it, and reading at most ``max_bytes``.

    A folder, a FIFO (which would block until a writer comes), a device such as ``/dev/zero`` (which
    never ends) or a socket is refused without reading; so is a file larger than ``max_bytes`` (also one
    that grows while it is read).  The file is opened without blocking and checked on the open handle,
    so that nothing can be swapped in between the check and the read.

    Parameters
    ----------
    path : the file.
    kind : what the file should be, for the messages (``"text CSV"``, ``"COLMAP binary file"``).
    max_bytes : the largest size accepted.

    Raises
    ------
    InvalidInputError
        ``FILE: no such file``, ``FILE: is a folder, not a KIND``, ``FILE: is a FIFO, not a KIND``
        (device, socket), ``FILE: is larger than the N bytes a KIND may have here``,
        ``FILE: not a readable KIND (reason)``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (folder / "a.csv").write_text("x\\n1\\n")
    >>> read_file_bytes(folder / "a.csv", "text CSV", 100)
    b'x\\n1\\n'
    >>> read_file_bytes(folder, "text CSV", 100)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: ...: is a folder, not a text CSV
    """
    file = Path(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0)
    try:
        if file.is_dir():  # Windows cannot open a folder to ask
            raise InvalidInputError(f"{where(file)}: is a folder, not a {kind}")
        fd = os.open(file, flags)
    except FileNotFoundError:
        raise InvalidInputError(f"{where(file)}: no such file") from None
    except OSError as exc:
        raise InvalidInputError(f"{where(file)}: not a readable {kind} ({exc.strerror or exc})") from None
    with os.fdopen(fd, "rb") as handle:
        mode = os.fstat(handle.fileno()).st_mode
        if not stat.S_ISREG(mode):
            what = ("a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else
                    "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else
                    "a socket" if stat.S_ISSOCK(mode) else "not a regular file")
            raise InvalidInputError(f"{where(file)}: is {what}, not a {kind}")
        try:
            data = handle.read(max_bytes + 1)
        except OSError as exc:
            raise InvalidInputError(f"{where(file)}: not a readable {kind} ({exc.strerror or exc})") from None
    if len(data) > max_bytes:
        raise InvalidInputError(f"{where(file)}: is larger than the {max_bytes} bytes a {kind} may have here")
    return data


def missing_columns(header: list[str], required: Sequence[str] | Mapping[str, Sequence[str]]) -> str | None:
    """The one message for a header that lacks required columns, or None when it has them.

    ``required`` is one list of columns, or alternative layouts (a description → columns mapping)
    of which one suffices.  The message names the missing columns (of the layout the header comes
    closest to), every accepted layout and the header that came::

        missing column(s) y; expected frame,track_id,x,y; got frame,track_id,x

    Examples
    --------
    >>> missing_columns(["x", "z"], ["x", "y"])
    'missing column(s) y; expected x,y; got x,z'
    >>> print(missing_columns(["fx"], {"K": ["fx", "fy"], "P": ["p11"]}))
    missing column(s) fy of the K layout; expected the K layout fx,fy or the P layout p11; got fx
    >>> missing_columns(["p11"], {"K": ["fx", "fy"], "P": ["p11"]}) is None
    True
    """
    layouts = _layouts(required)
    have = set(header)
    lacking = {name: [c for c in columns if c not in have] for name, columns in layouts.items()}
    if any(not m for m in lacking.values()):
        return None
    # the layout with the most columns present is the one the file was meant to be
    closest = max(layouts, key=lambda name: (len(layouts[name]) - len(lacking[name]), -len(lacking[name])))
    of = f" of the {closest} layout" if closest else ""
    return f"missing column(s) {', '.join(lacking[closest])}{of}; expected {_expected(layouts)}; got {','.join(header)}"


def _layouts(required: Sequence[str] | Mapping[str, Sequence[str]]) -> dict[str, list[str]]:
    """Alternative layouts by description; one unnamed layout for a plain list of columns."""
    if isinstance(required, Mapping):
        return {name: list(columns) for name, columns in required.items()}
    return {"": list(required)}


def _expected(layouts: dict[str, list[str]]) -> str:
    """``a,b`` or ``the X layout a,b or the Y layout c,d``."""
    return " or ".join(f"the {name} layout {','.join(columns)}" if name else ",".join(columns)
                       for name, columns in layouts.items())


def read_rows(path: str | os.PathLike[str], expected: str | None = None, *,
              required: Sequence[str] | Mapping[str, Sequence[str]] = (), allow_no_rows: bool = False,
              max_bytes: int = MAX_CSV_BYTES) -> CsvRows:
    """Read the header and the rows of a CSV file with the rules every reader of ``io`` shares.

    The rules (``docs/formats.md``):

    * a regular file of at most ``max_bytes`` (a folder, FIFO or device is refused unread);
    * UTF-8 text, with or without a byte-order mark; a file with NUL bytes is not text;
    * a line whose first non-blank character is ``#`` is a comment;
    * a blank line, or one with nothing but separators and spaces, is skipped;
    * the first other line is the header, its names stripped of surrounding spaces, holding the
      ``required`` columns;
    * every row has as many fields as the header.

    Parameters
    ----------
    path : the file.
    expected : the header the caller expects, for the message of an empty file
        (``"FILE: empty file; expected a header " + expected``); by default the ``required`` columns.
    required : the columns the header must hold, or alternative layouts (description → columns) of
        which one suffices; the one message for a header without them is :func:`missing_columns`'.
    allow_no_rows : a file with a header and no rows is valid (else it is refused).
    max_bytes : the largest file read.

    Raises
    ------
    InvalidInputError
        Naming the file, and the 1-based line where there is one (:func:`where`): ``FILE: no such file``,
        ``FILE: is a folder, not a text CSV`` (FIFO, device), ``FILE: not a readable text CSV (…)``,
        ``FILE: empty file; expected a header …``, ``FILE: line N: missing column(s) …`` (N the header's
        line), ``FILE: line N: no rows after the header``, ``FILE: line N: K fields, the header has M``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "t.csv"
    >>> _ = f.write_bytes("\\ufeff# made by hand\\n a , b\\n\\n1,2\\n,\\n3,4\\n".encode())
    >>> read_rows(f, "a,b")
    CsvRows(header=['a', 'b'], header_line=2, rows=[(4, ['1', '2']), (6, ['3', '4'])])
    >>> read_rows(f, required=["a", "c"])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: ...t.csv: line 2: missing column(s) c; expected a,c; got a,b
    """
    file = Path(path)
    data = read_file_bytes(file, "text CSV", max_bytes)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InvalidInputError(f"{where(file)}: not a readable text CSV (not UTF-8: byte 0x{data[exc.start]:02x} "
                                f"at offset {exc.start})") from None
    if "\x00" in text:
        raise InvalidInputError(f"{where(file)}: not a readable text CSV (holds NUL bytes)")
    kept = [(n, line) for n, line in enumerate(_NEWLINE.split(text), start=1)
            if line.strip() and not line.lstrip().startswith("#")]
    records: list[tuple[int, list[str]]] = []
    reader = csv.reader(line + "\n" for _, line in kept)
    start = 0
    try:
        for fields in reader:
            if any(cell.strip() for cell in fields):
                records.append((kept[start][0], fields))
            start = reader.line_num
    except csv.Error as exc:
        raise InvalidInputError(f"{where(file, kept[start][0])}: not a readable CSV row ({exc})") from None
    if not records:
        if expected is None:
            expected = _expected(_layouts(required))
        raise InvalidInputError(f"{where(file)}: empty file; expected a header {expected}")
    header_line, header = records[0]
    header = [name.strip() for name in header]
    missing = missing_columns(header, required) if required else None
    if missing:
        raise InvalidInputError(f"{where(file, header_line)}: {missing}")
    rows = records[1:]
    for n, fields in rows:
        if len(fields) != len(header):
            raise InvalidInputError(f"{where(file, n)}: {len(fields)} fields, the header has {len(header)}")
    if not rows and not allow_no_rows:
        raise InvalidInputError(f"{where(file, header_line)}: no rows after the header")
    return CsvRows(header, header_line, rows)


# --- columns of numbers ---------------------------------------------------------------------------

#: Frame numbers and track ids index dense arrays: larger numbers are refused (they would need absurd memory).
MAX_INDEX = 10_000_000
#: Image coordinates beyond ± this many pixels are refused: no camera has such images, and their
#: squares (1e300² overflows) would break the factorization's arithmetic.
MAX_COORDINATE_PX = 1e7


def index_column(file: Path, values: np.ndarray, lines: np.ndarray, name: str) -> np.ndarray:
    """Integers in 0 … MAX_INDEX of one column (its cells as written, ``lines`` their file lines), or one line naming the cell."""
    out = np.empty(len(values), dtype=np.int64)
    for i, text in enumerate(values):
        try:
            number = float(text)
        except ValueError:
            raise InvalidInputError(f"{where(file, lines[i])}: {name} must be an integer; got {text!r}") from None
        if not np.isfinite(number) or number != int(number):
            raise InvalidInputError(f"{where(file, lines[i])}: {name} must be an integer; got {text!r}")
        if not 0 <= number <= MAX_INDEX:
            raise InvalidInputError(f"{where(file, lines[i])}: {name} must be in 0 … {MAX_INDEX}; got {text.strip()}")
        out[i] = int(number)
    return out


def number_column(file: Path, values: np.ndarray, lines: np.ndarray, name: str, *, finite: bool = True) -> np.ndarray:
    """Numbers of one column; empty cells are NaN, refused when ``finite`` (so are magnitudes beyond MAX_COORDINATE_PX)."""
    out = np.empty(len(values))
    for i, text in enumerate(values):
        try:
            out[i] = float(text) if (text.strip() or finite) else np.nan
        except ValueError:
            raise InvalidInputError(f"{where(file, lines[i])}: {name} must be a number; got {text!r}") from None
        if finite and not np.isfinite(out[i]):
            raise InvalidInputError(f"{where(file, lines[i])}: {name} must be finite; got {text.strip()!r}")
        if finite and abs(out[i]) > MAX_COORDINATE_PX:
            raise InvalidInputError(
                f"{where(file, lines[i])}: {name} must be within ±{MAX_COORDINATE_PX:g} px; got {text.strip()!r}"
            )
        if not finite and np.isinf(out[i]):
            raise InvalidInputError(f"{where(file, lines[i])}: {name} must not be infinite; got {text.strip()!r}")
    return out
