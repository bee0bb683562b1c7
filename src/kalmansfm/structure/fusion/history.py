"""Each point's fused estimate after every view that observed it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import InvalidInputError

__all__ = ["FusionHistory"]


@dataclass(frozen=True)
class FusionHistory:
    """Each point's estimate after every view that observed it, from its second view on.

    Entries are sorted by view, then point.

    Attributes
    ----------
    views : (H,) int64 — view index (into the cameras) after which the estimate holds.
    points : (H,) int64 — point index.
    estimates : (H, 3) — NaN where the estimate has no finite (X, Y, Z) yet (depth undetermined).
    covariances : (H, 3, 3).
    states, state_covariances : (H, 3), (H, 3, 3) or None — for ``recursive``, the filter's own
        state: the inverse depth (α, β, ρ) in the anchor view (X = C_a + o R_aᵀ (α, β, 1) / ρ).
    anchors : (H,) int or None — the anchor view of each state.
    """

    views: np.ndarray
    points: np.ndarray
    estimates: np.ndarray
    covariances: np.ndarray
    states: np.ndarray | None = None
    state_covariances: np.ndarray | None = None
    anchors: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.views.shape[0])

    def dense(self, n_views: int, n_points: int, *, states: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(V, N, 3) estimates and (V, N, 3, 3) covariances (the filter states with ``states``), NaN where none."""
        values, covariances = (self.states, self.state_covariances) if states else (self.estimates, self.covariances)
        if values is None:
            raise InvalidInputError("this history has no filter states (only method='recursive' keeps them)")
        X = np.full((n_views, n_points, 3), np.nan)
        C = np.full((n_views, n_points, 3, 3), np.nan)
        X[self.views, self.points] = values
        C[self.views, self.points] = covariances
        return X, C

    def first(self) -> FusionHistory:
        """The first entry of every point (its two-view estimate for ``recursive``)."""
        order = np.lexsort((self.views, self.points))
        pts = self.points[order]
        keep = order[np.r_[True, pts[1:] != pts[:-1]]] if pts.size else order
        return self._take(keep)

    def _take(self, index: np.ndarray) -> FusionHistory:
        return FusionHistory(*(None if a is None else a[index] for a in (
            self.views, self.points, self.estimates, self.covariances, self.states, self.state_covariances,
            self.anchors)))
