"""What a recursive fusion pass leaves (the compiled kernel's and the NumPy pass's common record)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RecursiveStates"]


@dataclass(frozen=True)
class RecursiveStates:
    """What a recursive pass leaves: unit-σ inverse-depth states and the bookkeeping."""

    theta: np.ndarray  # (n, 3), NaN where not started
    cov: np.ndarray  # (n, 3, 3)
    anchor: np.ndarray  # (n,) -1 where not started
    started: np.ndarray  # (n,) bool
    stalled: np.ndarray  # (n,) bool: a pair without parallax was met
    used: np.ndarray  # (V, n) bool
    rejected: np.ndarray  # (V, n) bool
    residuals: np.ndarray  # (V, n, 2) observed - projected at the final state, every observation; NaN elsewhere
    in_front: np.ndarray  # (n,) bool: positive oriented depth in every used view (started points)
    history: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None
