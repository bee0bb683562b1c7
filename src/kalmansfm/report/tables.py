"""Tables of a fusion experiment: truth, measurements and the fused (Kalman) estimate per iteration.

:func:`format_csv` and :func:`format_text` print a
:class:`~kalmansfm.experiments.fusion_tasks.FusionTable` (the columns of one of the
report's tables, Tasks 1-7 of ``004_cd423c68da9c9743.txt``).
"""

from __future__ import annotations

import numpy as np

from ..experiments.fusion_tasks import FusionTable
from ..io._csv import csv_text, number

__all__ = ["format_csv", "format_text"]


def _axis_names(d: int) -> list[str]:
    return ["x", "y", "z"] if d == 3 else [str(i + 1) for i in range(d)]


def _column_groups(table: FusionTable) -> list[tuple[str, np.ndarray]]:
    return [
        ("truth", table.truth),
        ("meas", table.measured),
        ("meas_std", table.measured_std),
        ("kalman", table.estimate),
        ("kalman_std", table.estimate_std),
    ]


def format_csv(table: FusionTable) -> str:
    """The table as CSV with a header line; numbers as every CSV of the package writes them
    (:func:`kalmansfm.io._csv.number`: full round-trip precision, an empty cell for NaN).

    Columns: ``iter,truth,meas,meas_std,kalman,kalman_std`` for d = 1, and
    ``iter,truth_x,truth_y,truth_z,meas_x,...,kalman_std_z`` for d = 3.

    Examples
    --------
    >>> t = FusionTable(1, "", [[10.0], [10.0]], [[10.2], [9.9]], [[1.0], [1.0]],
    ...                 [[10.2], [10.05]], [[1.0], [0.5]])
    >>> print(format_csv(t), end="")
    iter,truth,meas,meas_std,kalman,kalman_std
    1,10.0,10.2,1.0,10.2,1.0
    2,10.0,9.9,1.0,10.05,0.5
    """
    groups = _column_groups(table)
    d = table.dimension
    if d == 1:
        header = ["iter"] + [name for name, _ in groups]
    else:
        header = ["iter"] + [f"{name}_{axis}" for name, _ in groups for axis in _axis_names(d)]
    values = np.concatenate([array for _, array in groups], axis=1)
    return csv_text(header, ([k + 1, *map(number, row)] for k, row in enumerate(values)))


def _aligned(groups: list[tuple[str, list[str], np.ndarray]], decimals: int) -> list[str]:
    """Right-aligned columns under group titles; ``groups`` = (title, column names, (K, c) values)."""
    K = groups[0][2].shape[0]
    blocks = [(" ", ["iter"], [[str(k + 1)] for k in range(K)])]
    for title, names, values in groups:
        blocks.append((title, names, [[f"{v:.{decimals}f}" for v in row] for row in values]))
    rendered: list[list[str]] = [[], [], *([] for _ in range(K))]
    for title, names, cells in blocks:
        widths = [max(len(n), *(len(row[j]) for row in cells)) for j, n in enumerate(names)]
        block_width = max(sum(widths) + 2 * (len(widths) - 1), len(title))
        widths[0] += block_width - (sum(widths) + 2 * (len(widths) - 1))
        rendered[0].append(title.center(block_width))
        rendered[1].append("  ".join(n.rjust(w) for n, w in zip(names, widths)))
        for k, row in enumerate(cells):
            rendered[2 + k].append("  ".join(c.rjust(w) for c, w in zip(row, widths)))
    return [" | ".join(parts).rstrip() for parts in rendered]


def format_text(table: FusionTable, *, decimals: int = 4) -> str:
    """The table aligned for reading, with the errors of the measurement and the estimate.

    For d = 1 one table: truth, measurement, its standard deviation and error
    (meas - truth), then the same for the Kalman estimate.  For d > 1 three
    blocks, as in the report: coordinates; standard deviations; errors per
    coordinate plus the distance error |value| - |truth| (the report's
    "distance error", the error in the range from the sensor) and the length of
    the error vector |value - truth|.

    Examples
    --------
    >>> t = FusionTable(1, "Two readings", [[10.0], [10.0]], [[10.2], [9.9]], [[1.0], [1.0]],
    ...                 [[10.2], [10.05]], [[1.0], [0.7071]])
    >>> print(format_text(t, decimals=2))
    Two readings
         |       |      measured      |       kalman
    iter | truth | value   std  error | value   std  error
       1 | 10.00 | 10.20  1.00   0.20 | 10.20  1.00   0.20
       2 | 10.00 |  9.90  1.00  -0.10 | 10.05  0.71   0.05
    """
    t = table
    lines = [t.title]
    if t.dimension == 1:
        lines += _aligned(
            [
                (" ", ["truth"], t.truth),
                ("measured", ["value", "std", "error"], np.hstack([t.measured, t.measured_std, t.measured - t.truth])),
                ("kalman", ["value", "std", "error"], np.hstack([t.estimate, t.estimate_std, t.estimate - t.truth])),
            ],
            decimals,
        )
        return "\n".join(lines)
    axes = _axis_names(t.dimension)
    truth_range = np.linalg.norm(t.truth, axis=1, keepdims=True)

    def errors(values: np.ndarray) -> np.ndarray:
        range_error = np.linalg.norm(values, axis=1, keepdims=True) - truth_range
        return np.hstack([values - t.truth, range_error, np.linalg.norm(values - t.truth, axis=1, keepdims=True)])

    lines += ["", "Coordinates"]
    lines += _aligned([("truth", axes, t.truth), ("measured", axes, t.measured), ("kalman", axes, t.estimate)], decimals)
    lines += ["", "Standard deviations"]
    lines += _aligned([("measured", axes, t.measured_std), ("kalman", axes, t.estimate_std)], decimals)
    lines += ["", "Errors (value - truth; range = |value| - |truth|; |err| = |value - truth|)"]
    names = axes + ["range", "|err|"]
    lines += _aligned([("measured", names, errors(t.measured)), ("kalman", names, errors(t.estimate))], decimals)
    return "\n".join(lines)
