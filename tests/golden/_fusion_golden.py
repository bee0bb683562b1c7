"""Helpers of the fusion-table golden tests: printed strings, their precision, and input-rounding margins."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from kalmansfm import fuse_recursive
from kalmansfm.experiments.fusion_tasks import load_task

GOLDEN = Path(__file__).parent / "data"


def half_unit(printed: str) -> float:
    """Half a unit of the last printed digit: '100.06' -> 0.005, '0.7071' -> 0.00005, '40' -> 0.5."""
    decimals = len(printed.split(".")[1]) if "." in printed else 0
    return 0.5 * 10.0**-decimals


def read_rows(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(line for line in text.splitlines() if line and not line.startswith("#")))


def columns(rows: list[dict[str, str]], name: str, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Values (K, d) and half units (K, d) of column ``name`` (``name_x``... for d = 3)."""
    keys = [name] if d == 1 else [f"{name}_{a}" for a in "xyz"]
    strings = [[row[k] for k in keys] for row in rows]
    values = np.array([[float(s) for s in r] for r in strings])
    halves = np.array([[half_unit(s) for s in r] for r in strings])
    return values, halves


@dataclass(frozen=True)
class Printed:
    """The report's printed columns of one task, with the precision of every entry."""

    meas: np.ndarray
    meas_half: np.ndarray
    meas_std: np.ndarray
    meas_std_half: np.ndarray
    truth: np.ndarray
    truth_half: np.ndarray
    kalman: np.ndarray
    kalman_half: np.ndarray
    kalman_std: np.ndarray
    kalman_std_half: np.ndarray
    meas_err: np.ndarray
    meas_err_half: np.ndarray
    kalman_err: np.ndarray
    kalman_err_half: np.ndarray


def printed(number: int) -> Printed:
    d = 1 if number <= 3 else 3
    data = read_rows(
        resources.files("kalmansfm").joinpath("data", "fusion_tasks", f"task{number}.csv").read_text("utf-8")
    )
    report = read_rows((GOLDEN / f"task{number}_report.csv").read_text("utf-8"))
    assert [r["iter"] for r in data] == [r["iter"] for r in report]
    cols = {}
    for name, rows in [("meas", data), ("meas_std", data), ("truth", data), ("kalman", report),
                       ("kalman_std", report), ("meas_err", report), ("kalman_err", report)]:
        cols[name], cols[f"{name}_half"] = columns(rows, name, d)
    return Printed(**cols)


def rounding_margins(number: int) -> tuple[np.ndarray, np.ndarray]:
    """How far rounding of the printed inputs can move the fused estimate and its std, (K, d) each.

    Every printed measurement p and standard deviation σ may differ from the value the
    report computed with by up to half a unit of its last digit, δ.  The estimate is
    linear in the p's and smooth in the σ's, so the first-order bound
    Σ_j |∂y/∂u_j| δ_j is the largest move of an output y; ∂y/∂u_j δ_j is evaluated as
    the central difference (y(u_j + δ_j) - y(u_j - δ_j)) / 2, which is exact for the
    p's and neglects only O(δ²) ≈ 1e-8 relative terms for the σ's.
    All perturbations run at once as independent "landmarks" of one fuse_recursive call.
    """
    task = load_task(number)
    pr = printed(number)
    K, d = task.measurements.shape
    n = K * d
    # Perturbation j (of 2n): input j of (measurements, std) moved by +δ_j; 2n more by -δ_j.
    p = np.repeat(task.measurements[:, None, :], 4 * n, axis=1)
    s = np.repeat(task.measurement_std[:, None, :], 4 * n, axis=1)
    idx = np.arange(n)
    k, a = np.divmod(idx, d)
    for sign, offset in ((1.0, 0), (-1.0, 2 * n)):
        p[k, offset + idx, a] += sign * pr.meas_half[k, a]
        s[k, offset + n + idx, a] += sign * pr.meas_std_half[k, a]
    R = np.zeros((K, 4 * n, d, d))
    R[..., np.arange(d), np.arange(d)] = s**2
    fused = fuse_recursive(p, R, task.rotations, task.translations)
    x, sd = fused.estimates, fused.standard_deviations  # (K, 4n, d)
    half_diff_x = np.abs(x[:, : 2 * n] - x[:, 2 * n :]) / 2  # (K, 2n, d)
    half_diff_s = np.abs(sd[:, : 2 * n] - sd[:, 2 * n :]) / 2
    return half_diff_x.sum(axis=1), half_diff_s.sum(axis=1)
