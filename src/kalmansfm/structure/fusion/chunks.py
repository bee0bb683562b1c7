"""A chunk of points: the job every fusion method runs and what it hands back."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..points import PointStatus
from .inverse_depth import ViewGeometry

__all__ = ["Chunk", "ChunkResult", "concat_history", "finish"]


@dataclass(frozen=True)
class Chunk:
    """One chunk's job (picklable, so an executor can run it elsewhere)."""

    method: str
    geometry: ViewGeometry
    observations: np.ndarray  # (V, n, 2)
    sigma: float  # pixel σ the gates use
    gate2: float
    gate1: float
    history: bool
    # (V, n) each observation's standard deviation relative to sigma (weighted passes), or None (all 1)
    scales: np.ndarray | None = None
    # run the compiled kernel (the fusion as a whole is large), or None: decide by the chunk's size
    compiled: bool | None = None


@dataclass(frozen=True)
class ChunkResult:
    points: np.ndarray  # (n, 3)
    covariances: np.ndarray  # (n, 3, 3), unit σ
    status: np.ndarray
    used: np.ndarray  # (V, n) bool accepted observations
    rejected: np.ndarray  # (V, n) bool
    residuals: np.ndarray  # (V, n) length of observed - projected, NaN where unseen or no estimate
    # views, local points, states and their unit-σ covariances (θ for recursive, else X)
    history: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None
    anchors: np.ndarray | None = None  # (n,) for states in inverse depth: points/covariances hold θ and its P


def finish(X, C, status, used, rejected, residuals, history, anchors=None) -> ChunkResult:
    ok = status == PointStatus.OK
    X = np.where(ok[:, None], X, np.nan)
    C = np.where(ok[:, None, None], C, np.nan)
    lengths = np.where(ok[None, :], np.linalg.norm(residuals, axis=2), np.nan)
    return ChunkResult(X, C, status, used & ok, rejected, lengths, history, anchors)


def concat_history(parts: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if not parts:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)))
    return (np.concatenate([np.full(p[1].size, p[0]) for p in parts]), np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts]))
