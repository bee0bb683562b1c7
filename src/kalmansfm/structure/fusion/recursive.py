"""The recursive method: a gated iterated Kalman update per view in inverse depth.

Large chunks run the compiled kernel (:mod:`._recursive_kernel`), small ones the NumPy pass of the same
transitions (:mod:`.recursive_numpy`, also the reference the tests compare the kernel with).
"""

from __future__ import annotations

import numpy as np

from ..points import PointStatus
from .chunks import Chunk, ChunkResult, finish
from .inverse_depth import IEKF_ITERATIONS, IEKF_TOLERANCE, MAX_CONDITION, START_ITERATIONS
from .recursive_numpy import recursive_states_numpy
from .states import RecursiveStates

__all__ = ["COMPILED_MIN_POINTS", "RecursiveStates", "recursive_states", "run_recursive"]


def recursive_states(job: Chunk) -> RecursiveStates:
    """The numba kernel (:mod:`._recursive_kernel`), point by point; same results as the reference."""
    from ._recursive_kernel import recursive_pass

    g = job.geometry
    V, n, _ = job.observations.shape
    # point-major copies: a point's views sit together in memory while the kernel walks through them
    obs = np.ascontiguousarray(job.observations.transpose(1, 0, 2))
    theta = np.full((n, 3), np.nan)
    cov = np.full((n, 3, 3), np.nan)
    anchor = np.full(n, -1, dtype=np.int64)
    started = np.zeros(n, dtype=bool)
    stalled = np.zeros(n, dtype=bool)
    used = np.zeros((n, V), dtype=bool)
    rejected = np.zeros((n, V), dtype=bool)
    residuals = np.full((n, V, 2), np.nan)
    in_front = np.zeros(n, dtype=bool)
    shape = (n, V) if job.history else (0, 0)
    hist_theta, hist_cov = np.zeros(shape + (3,)), np.zeros(shape + (3, 3))
    hist_mask = np.zeros(shape, dtype=bool)
    weighted = job.scales is not None
    scale = np.ascontiguousarray(job.scales.T) if weighted else np.ones((0, 0))
    recursive_pass(np.ascontiguousarray(g.Q), np.ascontiguousarray(g.K_inv), g.depth_sign * float(g.orientation),
                   obs, scale, weighted, float(job.sigma), float(job.gate2), float(job.gate1), START_ITERATIONS, IEKF_ITERATIONS,
                   IEKF_TOLERANCE, MAX_CONDITION, bool(job.history), theta, cov, anchor, started, stalled, used,
                   rejected, residuals, in_front, hist_theta, hist_cov, hist_mask)
    history = None
    if job.history:
        views, pts = np.nonzero(hist_mask.T)
        history = (views, pts, hist_theta[pts, views], hist_cov[pts, views])
    return RecursiveStates(theta, cov, anchor, started, stalled, used.T, rejected.T, residuals.transpose(1, 0, 2), in_front,
                   history)


#: Below this many points a chunk runs the NumPy pass (:mod:`.recursive_numpy`): a first fusion of a few
#: hundred points should not wait for the kernel to compile (seconds), and NumPy is fast enough there.
COMPILED_MIN_POINTS = 2048


def _states(job: Chunk) -> RecursiveStates:
    """The NumPy pass for small fusions, the compiled kernel for the others (by the chunk's size if not said)."""
    compiled = job.observations.shape[1] >= COMPILED_MIN_POINTS if job.compiled is None else job.compiled
    return recursive_states(job) if compiled else recursive_states_numpy(job)


#: The pass run_recursive uses (tests swap in either one to compare them).
_STATES = _states


def run_recursive(job: Chunk) -> ChunkResult:
    n = job.observations.shape[1]
    st = _STATES(job)
    theta, cov, started = st.theta, st.cov, st.started
    status = np.full(n, PointStatus.OK, dtype=np.int8)
    status[~started] = np.where(st.stalled[~started], PointStatus.DEGENERATE, PointStatus.TOO_FEW_VIEWS)
    # ρ <= 0: the estimate lies beyond infinity; clearly so (3σ) is a point behind the cameras,
    # otherwise the depth is not determined yet
    rho_std = np.sqrt(np.abs(cov[:, 2, 2]))
    no_depth = started & ~(theta[:, 2] > 0)
    status[no_depth] = np.where(theta[no_depth, 2] + 3 * rho_std[no_depth] < 0, PointStatus.BEHIND_CAMERA,
                                PointStatus.DEGENERATE)
    status[(status == PointStatus.OK) & ~st.in_front] = PointStatus.BEHIND_CAMERA
    # The state goes out in inverse depth: its (X, Y, Z) image depends on σ (second-order terms), known later.
    return finish(theta, cov, status, st.used, st.rejected, st.residuals, st.history, st.anchor)
