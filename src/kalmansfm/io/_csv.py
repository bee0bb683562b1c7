"""How every CSV writer of ``io`` spells numbers and joins rows."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np


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
