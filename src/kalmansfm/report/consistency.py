"""The report of a consistency study (NEES and per-axis coverage over many noise draws), as text or CSV."""

from __future__ import annotations

import numpy as np

from ..experiments.consistency import ConsistencyResult
from ..io._csv import csv_text, number

__all__ = ["consistency_csv", "consistency_text"]

_AXES = {1: ["distance"], 3: ["x", "y", "z"]}
_STATE_AXES = ["x/z", "y/z", "1/z"]


def _axes(r: ConsistencyResult) -> list[str]:
    if r.parameters.get("space") == "inverse_depth":
        return _STATE_AXES
    return _AXES.get(r.dimension, [str(i + 1) for i in range(r.dimension)])


def consistency_text(r: ConsistencyResult) -> str:
    """A short human-readable summary of a consistency study (what ``kalmansfm consistency`` prints).

    Examples
    --------
    >>> from kalmansfm.experiments.consistency import run_consistency
    >>> print(consistency_text(run_consistency(2, runs=20)).splitlines()[-1])
    PASS: consistent
    """
    axes = _axes(r)
    params = ", ".join(f"{k} = {v:g}" if isinstance(v, float) else f"{k} = {v}" for k, v in r.parameters.items())
    lines = [
        f"Task {r.task}, method {r.method}: {r.runs} runs, {r.iterations} iterations, d = {r.dimension} ({params})",
        "axis        within 1σ  within 3σ   (consistent: 0.683, 0.997)",
    ]
    for i, name in enumerate(axes):
        lines.append(f"{name:<10}  {r.pooled_within_1sigma[i]:9.3f}  {r.pooled_within_3sigma[i]:9.3f}")
    lines += [
        f"mean NEES, final iteration: {r.final_mean_nees:.3f}  95% interval [{r.nees_low[-1]:.3f}, "
        f"{r.nees_high[-1]:.3f}]  (expected {r.dimension})",
        f"mean NEES, all iterations:  {r.pooled_mean_nees:.3f}",
        f"iterations inside the interval: {int(r.inside.sum())}/{r.iterations}; consistent from iteration "
        f"{r.consistent_from if r.consistent_from is not None else '-'}",
        f"runs with an estimate: min {int(r.valid_runs.min())}/{r.runs} per iteration",
        f"{'PASS' if r.passed else 'FAIL'}: {r.verdict}",
    ]
    return "\n".join(lines) + "\n"


def consistency_csv(r: ConsistencyResult) -> str:
    """One row per iteration: NEES, its interval and the per-axis 1σ/3σ fractions.

    Numbers as every CSV of the package writes them (:func:`kalmansfm.io._csv.number`:
    full round-trip precision, an empty cell for NaN).

    Examples
    --------
    >>> from kalmansfm.experiments.consistency import run_consistency
    >>> consistency_csv(run_consistency(2, runs=20)).splitlines()[1]
    '1,20,0.7575437354078361,0.4795388696132433,1.7084803451419166,1,0.75,1.0'
    """
    axes = [a.replace("/", "_over_") for a in _axes(r)]
    header = ["iter", "valid_runs", "mean_nees", "nees_low", "nees_high", "inside"]
    header += [f"within1_{a}" for a in axes] + [f"within3_{a}" for a in axes]
    rows = (
        [k + 1, int(r.valid_runs[k]), *map(number, (r.mean_nees[k], r.nees_low[k], r.nees_high[k])), int(r.inside[k]),
         *map(number, np.concatenate([r.within_1sigma[k], r.within_3sigma[k]]))]
        for k in range(r.iterations)
    )
    return csv_text(header, rows)
