"""How every CSV writer of ``io`` spells numbers and joins rows, and how every CSV reader splits a file."""

from __future__ import annotations

import csv
import os
import re
from collections.abc import Iterable
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


def read_rows(path: str | os.PathLike[str], expected: str, *, allow_no_rows: bool = False) -> CsvRows:
    """Read the header and the rows of a CSV file with the rules every reader of ``io`` shares.

    The rules (``docs/formats.md``):

    * UTF-8 text, with or without a byte-order mark; a file with NUL bytes is not text;
    * a line whose first non-blank character is ``#`` is a comment;
    * a blank line, or one with nothing but separators and spaces, is skipped;
    * the first other line is the header, its names stripped of surrounding spaces;
    * every row has as many fields as the header.

    Parameters
    ----------
    path : the file.
    expected : the header the caller expects, for the message of an empty file
        (``"FILE: empty file; expected a header " + expected``).
    allow_no_rows : a file with a header and no rows is valid (else it is refused).

    Raises
    ------
    InvalidInputError
        Naming the file, and the 1-based line where there is one (:func:`where`): ``FILE: no such file``,
        ``FILE: not a readable text CSV (…)``, ``FILE: empty file; expected a header …``,
        ``FILE: line N: no rows after the header`` (N the header's line), ``FILE: line N: K fields,
        the header has M``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "t.csv"
    >>> _ = f.write_bytes("\\ufeff# made by hand\\n a , b\\n\\n1,2\\n,\\n3,4\\n".encode())
    >>> read_rows(f, "a,b")
    CsvRows(header=['a', 'b'], header_line=2, rows=[(4, ['1', '2']), (6, ['3', '4'])])
    """
    file = Path(path)
    try:
        data = file.read_bytes()
    except FileNotFoundError:
        raise InvalidInputError(f"{where(file)}: no such file") from None
    except OSError as exc:
        raise InvalidInputError(f"{where(file)}: not a readable text CSV ({exc.strerror or exc})") from None
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
        raise InvalidInputError(f"{where(file)}: empty file; expected a header {expected}")
    header_line, header = records[0]
    header = [name.strip() for name in header]
    rows = records[1:]
    for n, fields in rows:
        if len(fields) != len(header):
            raise InvalidInputError(f"{where(file, n)}: {len(fields)} fields, the header has {len(header)}")
    if not rows and not allow_no_rows:
        raise InvalidInputError(f"{where(file, header_line)}: no rows after the header")
    return CsvRows(header, header_line, rows)
