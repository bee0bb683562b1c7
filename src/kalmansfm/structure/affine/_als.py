"""Weighted alternating least squares for the affine model over the observed entries only.

The model x_fp = M_f S_p + t_f (:mod:`~kalmansfm.structure.affine.factorization`) is fitted
to the observed entries of ``positions`` with the weights w (1 without weights), working
on the image rows of W: row 2f + c holds coordinate c of frame f, with the unknowns
m (the camera row, 3) and t (its translation). Each iteration alternates two batched
linear least-squares steps:

- points given frames: S_p = argmin Σ_rows w (x − m·S_p − t)², a 3 × 3 normal system
  Σ w m mᵀ · S_p = Σ w (x − t) m per point;
- frames given points: [m | t] = argmin Σ_p w (x − m·S_p − t)², a 4 × 4 normal system
  Σ w h hᵀ · [m | t] = Σ w x h per image row, h = (S_p, 1);

until the weighted cost Σ w (x − m·S − t)² decreases by less than ``tol`` (relative).

The normal systems and the cost come from one of two formulations of the same sums:

- *dense* (small problems): two (2F, P) arrays, the values (0 where unobserved) and the
  weights, and matrix products with thin blocks — BLAS does the work;
- *compiled* (2F·P ≥ ``_COMPILED_ENTRIES`` = 2·10⁶): numba kernels
  (:mod:`~kalmansfm.structure.affine._als_kernels`) that read ``positions``, the observed mask and
  the weights where they lie (no (2F, P) copy), one pass over them per step. The cost of an
  iterate is summed in the same pass that builds the next point step's systems, so an
  iteration is two reads of the data instead of three, and no (2F, P) array is made.

The dense formulation is the kernels' reference (the tests compare them); below the
threshold the compilation (about 2 s of CPU, once, cached on disk) would cost more than it
saves. Either way the iterates agree to rounding: the same sums in another order.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

# 2F·P from which the normal systems are built by the compiled kernels: large input, as for the
# streamed closed form. Below it the products (BLAS single-threaded inside factorize) take well under a
# second a hundred iterations, less than compiling the kernels once (about 2 s of CPU).
_COMPILED_ENTRIES = 2_000_000
# Relative ridge that keeps exactly singular systems solvable without biasing others.
_RIDGE = 1e-13


def weighted_als(
    x: np.ndarray,
    w: np.ndarray | None,
    observed: np.ndarray,
    max_iterations: int,
    tol: float,
    notes: list[str],
    progress: Callable[[int, int], object] | None = None,
    compiled: bool | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray, np.ndarray]:
    """Weighted ALS over the observed entries (``w`` None: unit weights).

    ``x`` (F, P, 2) float64 and ``w`` (F, P, 2) are only read where ``observed`` (F, P).
    Returns the affine motion (F, 2, 3), the shape (P, 3), the translation (F, 2), the
    iterations run and the masks of the frames and points reached. ``progress`` is called
    after each iteration with (iterations done, ``max_iterations``). ``compiled`` forces one
    formulation (default: by size).
    """
    frames, points = observed.shape
    if compiled is None:
        compiled = 2 * frames * points >= _COMPILED_ENTRIES
    problem: _DenseProblem | _CompiledProblem = (_CompiledProblem if compiled else _DenseProblem)(x, w, observed)
    motion, shape, translation, f_ok, p_ok = _initialise(problem, x, observed)
    problem.restrict(f_ok, p_ok)  # frames and points the initialisation did not reach take no part
    total = problem.total()
    previous, normal, rhs = problem.point_system(motion, translation, shape)
    iterations = 0
    converged = previous <= 1e-30 * max(total, 1.0)
    while not converged and iterations < max_iterations:
        shape = _batched_solve(normal, rhs, shape)
        motion, translation = _solve_frames(problem, shape, motion, translation)
        iterations += 1
        current, normal, rhs = problem.point_system(motion, translation, shape)
        converged = previous - current <= tol * previous or current <= 1e-30 * max(total, 1.0)
        previous = current
        if progress is not None:
            progress(iterations, max_iterations)
    if not converged:
        notes.append(f"alternating least squares stopped after {iterations} iterations without converging")
    return motion.reshape(frames, 2, 3), shape, translation.reshape(frames, 2), iterations, f_ok, p_ok


class _DenseProblem:
    """The normal systems from (2F, P) arrays and matrix products (small problems; the kernels' reference).

    ``weight`` and ``weighted`` (w · x, 0 where unobserved) start as the initialisation's unit
    weights and values; :meth:`restrict` gives them the user's weights and zeroes the frames
    and points left out.
    """

    def __init__(self, x: np.ndarray, w: np.ndarray | None, observed: np.ndarray) -> None:
        self.values = _rows_where(x, observed)
        self.weight = _rows_where(None, observed)  # 1 where observed: the initialisation's weights
        self.weighted = self.values  # 1 · v = v exactly, and v = 0 where w = 0
        self.w, self.observed = w, observed

    def restrict(self, f_ok: np.ndarray, p_ok: np.ndarray) -> None:
        if self.w is not None:
            self.weight = _rows_where(self.w, self.observed)
            self.weighted = self.weight * self.values
        known_rows = np.repeat(f_ok, 2)
        for array in (self.weight, self.weighted):  # in place
            array[~known_rows] = 0.0
            array[:, ~p_ok] = 0.0

    def total(self) -> float:
        """Σ w x² over the entries that take part."""
        return float(np.einsum("ij,ij->", self.weighted, self.values))

    def point_system(self, motion: np.ndarray, translation: np.ndarray, shape: np.ndarray | None
                     ) -> tuple[float, np.ndarray, np.ndarray]:
        """(cost of (motion, translation, shape) — NaN without a shape —, normal (P, 3, 3), rhs (P, 3))."""
        outer = (motion[:, :, None] * motion[:, None, :]).reshape(-1, 9)  # m mᵀ per image row
        normal = (self.weight.T @ outer).reshape(-1, 3, 3)
        rhs = self.weighted.T @ motion - self.weight.T @ (translation[:, None] * motion)
        return (np.nan if shape is None else self._cost(motion, shape, translation)), normal, rhs

    def frame_system(self, shape: np.ndarray, columns: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(normal (2F, 4, 4), rhs (2F, 4)); ``columns`` (P,) bool: only these points count."""
        homogeneous = np.hstack([shape, np.ones((shape.shape[0], 1))])
        if columns is not None:
            homogeneous[~columns] = 0.0
        outer = (homogeneous[:, :, None] * homogeneous[:, None, :]).reshape(-1, 16)
        return (self.weight @ outer).reshape(-1, 4, 4), self.weighted @ homogeneous

    def _cost(self, motion: np.ndarray, shape: np.ndarray, translation: np.ndarray) -> float:
        # Σ w (v − m·s − t)², a block of rows at a time
        result = 0.0
        for rows in row_blocks(*self.values.shape):
            difference = motion[rows] @ shape.T
            difference += translation[rows, None]
            difference -= self.values[rows]
            np.square(difference, out=difference)
            result += float(np.einsum("ij,ij->", self.weight[rows], difference))
        return result


class _CompiledProblem:
    """The normal systems from ``positions``, the mask and the weights as they lie, by numba kernels."""

    def __init__(self, x: np.ndarray, w: np.ndarray | None, observed: np.ndarray) -> None:
        from . import _als_kernels  # numba is imported only when it is used

        self.kernels = _als_kernels
        self.x = np.ascontiguousarray(x, dtype=np.float64)
        self.w = np.ones((1, 1, 2)) if w is None else np.ascontiguousarray(w, dtype=np.float64)
        self.unit = True  # the initialisation's weights; restrict() gives the user's
        self.user_weights = w is not None
        self.observed = np.ascontiguousarray(observed, dtype=np.bool_)
        frames, points = observed.shape
        self.frame_on, self.point_on = np.ones(frames, np.bool_), np.ones(points, np.bool_)

    def restrict(self, f_ok: np.ndarray, p_ok: np.ndarray) -> None:
        self.unit = not self.user_weights
        self.frame_on = np.ascontiguousarray(f_ok, dtype=np.bool_)
        self.point_on = np.ascontiguousarray(p_ok, dtype=np.bool_)

    def total(self) -> float:
        """Σ w x² over the entries that take part (once per fit: NumPy, a block of frames at a time)."""
        result = 0.0
        for block in row_blocks(*self.observed.shape):
            on = (self.observed[block] & self.frame_on[block, None] & self.point_on[None, :])[:, :, None]
            squares = np.square(self.x[block], where=on, out=np.zeros(on.shape[:2] + (2,)))
            result += float(squares.sum() if self.unit else np.einsum("fpc,fpc->", self.w[block], squares))
        return result

    def point_system(self, motion: np.ndarray, translation: np.ndarray, shape: np.ndarray | None
                     ) -> tuple[float, np.ndarray, np.ndarray]:
        points = self.observed.shape[1]
        normal, rhs = np.empty((points, 3, 3)), np.empty((points, 3))
        frame_cost = np.empty(self.observed.shape[0])
        self.kernels.point_normals(self.x, self.w, self.unit, self.observed, self.frame_on, self.point_on,
                                   np.ascontiguousarray(motion), np.ascontiguousarray(translation),
                                   np.zeros((points, 3)) if shape is None else np.ascontiguousarray(shape),
                                   normal, rhs, frame_cost)
        return (np.nan if shape is None else float(frame_cost.sum())), normal, rhs

    def frame_system(self, shape: np.ndarray, columns: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        rows = 2 * self.observed.shape[0]
        normal, rhs = np.empty((rows, 4, 4)), np.empty((rows, 4))
        point_on = self.point_on if columns is None else np.ascontiguousarray(columns & self.point_on)
        self.kernels.frame_normals(self.x, self.w, self.unit, self.observed, self.frame_on, point_on,
                                   np.ascontiguousarray(shape), normal, rhs)
        return normal, rhs


def _solve_frames(problem: _DenseProblem | _CompiledProblem, shape: np.ndarray, motion: np.ndarray,
                  translation: np.ndarray, columns: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each image row [m | t] = argmin Σ_p w (x − m·S_p − t)²; ``columns``: only these points count."""
    normal, rhs = problem.frame_system(shape, columns)
    solution = _batched_solve(normal, rhs, np.hstack([motion, translation[:, None]]))
    return solution[:, :3], solution[:, 3]


def _batched_solve(normal: np.ndarray, rhs: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Solve normal @ s = rhs per batch entry; singular systems keep ``fallback``."""
    n = normal.shape[-1]
    trace = np.trace(normal, axis1=1, axis2=2)
    ok = trace > 0
    regularised = normal + (_RIDGE * trace)[:, None, None] * np.eye(n)
    out = fallback.copy()
    if ok.any():
        out[ok] = np.linalg.solve(regularised[ok], rhs[ok][:, :, None])[:, :, 0]
    return out


def _initialise(problem: _DenseProblem | _CompiledProblem, x: np.ndarray, observed: np.ndarray):
    """Affine factors from the largest complete block, extended to all reachable frames and points."""
    frames, points = observed.shape
    rows, cols = _complete_block(observed)
    motion = np.zeros((2 * frames, 3))
    translation = np.zeros(2 * frames)
    shape = np.zeros((points, 3))
    f_ok = np.zeros(frames, bool)
    p_ok = np.zeros(points, bool)
    if rows.sum() >= 3 and cols.sum() >= 4:
        block_rows = np.repeat(rows, 2)
        block = x[np.ix_(rows, cols)].transpose(0, 2, 1).reshape(-1, int(cols.sum()))  # (2R, C) rows of W
        centroid = block.mean(axis=1)
        u, s, vt = np.linalg.svd(block - centroid[:, None], full_matrices=False)
        root = np.sqrt(s[:3])
        motion[block_rows] = u[:, :3] * root
        translation[block_rows] = centroid
        shape[cols] = vt[:3].T * root
        f_ok[rows], p_ok[cols] = True, True
    else:
        # No usable complete block: impute frame means and take the rank-3 part.
        values = _rows_where(x, observed)
        rows_of_obs = np.repeat(observed, 2, axis=0)
        counts = rows_of_obs.sum(axis=1)
        centroid = values.sum(axis=1) / np.maximum(counts, 1)
        filled = np.where(rows_of_obs, values, centroid[:, None]) - centroid[:, None]
        u, s, vt = np.linalg.svd(filled, full_matrices=False)
        root = np.sqrt(s[:3])
        return u[:, :3] * root, vt[:3].T * root, centroid, observed.sum(axis=1) >= 4, observed.sum(axis=0) >= 2
    # Unit weights. Frames (points) not yet known have zero motion (shape) rows and so add
    # nothing to a point's (frame's) normal equations; each solve covers all points (rows) and
    # only the new ones are kept, so no masked copy of the data is made.
    while True:
        seen_by_known = (observed & f_ok[:, None]).sum(axis=0)
        new_p = ~p_ok & (seen_by_known >= 2)
        if new_p.any():
            _, normal, rhs = problem.point_system(motion, translation, None)
            shape[new_p] = _batched_solve(normal, rhs, shape)[new_p]
            p_ok |= new_p
        seen_known = (observed & p_ok[None, :]).sum(axis=1)
        new_f = ~f_ok & (seen_known >= 4)
        if new_f.any():
            rows_new = np.repeat(new_f, 2)
            m, t = _solve_frames(problem, shape, motion, translation, columns=p_ok)
            motion[rows_new], translation[rows_new] = m[rows_new], t[rows_new]
            f_ok |= new_f
        if not new_p.any() and not new_f.any():
            break
    return motion, shape, translation, f_ok, p_ok


def _complete_block(observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Greedy search for a large all-observed block of frames × points.

    Repeatedly drop every point whose missing fraction is larger than that of the worst
    frame, else the worst frame; the counts are updated incrementally.
    """
    rows = np.ones(observed.shape[0], bool)
    cols = np.ones(observed.shape[1], bool)
    missing = ~observed
    row_missing = missing.sum(axis=1).astype(np.int64)
    col_missing = missing.sum(axis=0).astype(np.int64)
    while rows.sum() >= 3 and cols.sum() >= 4:
        n_rows, n_cols = int(rows.sum()), int(cols.sum())
        row_frac = np.where(rows, row_missing / n_cols, -1.0)
        col_frac = np.where(cols, col_missing / n_rows, -1.0)
        worst_row = float(row_frac.max())
        if worst_row <= 0 and col_frac.max() <= 0:
            break
        drop_cols = col_frac > worst_row
        if drop_cols.any():
            cols &= ~drop_cols
            row_missing -= missing[:, drop_cols].sum(axis=1)
        else:
            r = int(np.argmax(row_frac))
            rows[r] = False
            col_missing -= missing[r]
    return rows, cols


def _rows_where(a: np.ndarray | None, observed: np.ndarray) -> np.ndarray:
    """(2F, P) float64: a[f, p, c] at row 2f + c (1 when ``a`` is None) where observed, else 0.

    Built a block of frames at a time, so the only full-size array is the result.
    """
    frames, points = observed.shape
    out = np.zeros((frames, 2, points))
    for block in row_blocks(frames, points):
        seen = observed[block][:, None, :]
        if a is None:
            np.copyto(out[block], seen)
        else:
            np.copyto(out[block], a[block].transpose(0, 2, 1), where=seen)
    return out.reshape(2 * frames, points)


def row_blocks(rows: int, points: int, entries: int = 1 << 18) -> list[slice]:
    """Slices of consecutive rows holding about ``entries`` points each (cache-sized work)."""
    step = max(1, entries // max(points, 1))
    return [slice(start, min(start + step, rows)) for start in range(0, rows, step)]
