"""Batched linear Kalman filter: N independent filters advanced together.

The pure functions :func:`kalman_predict` and :func:`kalman_update` do the
arithmetic; :class:`KalmanFilter` keeps the state between calls and is built on
them.  Shapes: states ``(N, n)``, covariances ``(N, n, n)`` or one shared
``(n, n)``, measurements ``(N, m)`` with NaN for "not measured".

Symbols (as in every textbook and in FilterPy):

* ``F`` state transition (n, n), ``Q`` process noise covariance (n, n)
* ``H`` measurement matrix (m, n), ``R`` measurement noise covariance (m, m)
* ``y`` innovation z - H x⁻, ``S`` its covariance H P⁻ Hᵀ + R, ``K`` the gain

The storage behind the class (the cheapest exact form for the model, predictions fused
into the next update, priors recomputed when read, reused buffers) is its engine,
:mod:`kalmansfm.estimation.engine`; the arithmetic it shares with the functions here is
in :mod:`._linalg`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from .._validation import as_float_array, check_covariance, check_finite, check_fits_in_memory, check_shape
from . import _decoupled
from ._linalg import LOG_2PI, cholesky_checked, gain_and_posterior, mat_vec, solve_lower, symmetrize, times_transposed
from .engine import FilterEngine
from .smoothing import FilterRun

__all__ = [
    "InnovationStatistics",
    "KalmanFilter",
    "UpdateResult",
    "innovation_statistics",
    "kalman_predict",
    "kalman_update",
]


def kalman_predict(
    x: np.ndarray,
    P: np.ndarray,
    F: np.ndarray,
    Q: np.ndarray,
    u: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Propagate states and covariances one step: x⁻ = F x + u, P⁻ = F P Fᵀ + Q.

    Parameters
    ----------
    x : (N, n) states.
    P : (n, n) shared covariance or (N, n, n) per-filter covariances.
    F : (n, n) transition, or (N, n, n) one per filter.
    Q : (n, n) or (N, n, n) process noise covariance.
    u : (n,) or (N, n) known offset added to the predicted state, or None.

    Returns
    -------
    x_prior, P_prior : the predicted states and covariances (new arrays).
    """
    x_prior = x @ F.T if F.ndim == 2 else mat_vec(F, x)
    if u is not None:
        x_prior = x_prior + u
    if F.ndim == 2 and P.ndim == 3:
        # F P Fᵀ with a shared F as two GEMMs over the whole stack: P Fᵀ, then (F P) Fᵀ where
        # F P = (P Fᵀ)ᵀ because P is symmetric.
        FP = np.ascontiguousarray(np.swapaxes(times_transposed(P, F), -1, -2))
        FPF = times_transposed(FP, F)
    else:
        FPF = F @ P @ np.swapaxes(F, -1, -2)
    P_prior = symmetrize(FPF + Q)
    return x_prior, P_prior


@dataclass(frozen=True)
class UpdateResult:
    """Everything one measurement update produces, for all N filters.

    ``x`` (N, n) and ``P`` ((n, n) when still shared, else (N, n, n)) are the
    posterior.  ``y`` (N, m) is the innovation z - H x⁻ (NaN where a component was
    not measured), ``S`` the innovation covariance H P⁻ Hᵀ + R computed from the
    prior for every filter (measured or not; (m, m) when shared, else (N, m, m)),
    ``K`` the gain ((n, m) or (N, n, m); zero where not measured), ``nis`` the
    squared Mahalanobis distance yᵀ S⁻¹ y over the measured components and
    ``log_likelihood`` the Gaussian log density of the measurement under the
    prior (both NaN where nothing was measured), ``measured`` (N, m) the mask of
    components used.
    """

    x: np.ndarray
    P: np.ndarray
    y: np.ndarray
    S: np.ndarray
    K: np.ndarray
    nis: np.ndarray
    log_likelihood: np.ndarray
    measured: np.ndarray


def _measurement_patterns(measured: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Group the rows of a (N, m) mask by pattern: [(rows, measured columns), ...], empty rows left out.

    Patterns are encoded as integers (bit j = component j measured) so that the
    grouping is a bincount, not a row-wise ``np.unique``.
    """
    N, m = measured.shape
    if m <= 62:
        code = measured.astype(np.int64) @ (np.int64(1) << np.arange(m, dtype=np.int64))
        if np.all(code == code[0]):  # one pattern for everybody: no fancy indexing
            groups = [(np.arange(N), code[0])]
        else:
            order = np.argsort(code, kind="stable")
            sorted_code = code[order]
            cuts = np.flatnonzero(np.diff(sorted_code)) + 1
            groups = [(rows, sorted_code[rows_start]) for rows, rows_start in
                      zip(np.split(order, cuts), np.concatenate([[0], cuts]))]
        return [(rows, np.flatnonzero((int(c) >> np.arange(m)) & 1)) for rows, c in groups if c != 0]
    patterns, group = np.unique(measured, axis=0, return_inverse=True)
    return [(np.flatnonzero(group.ravel() == p), np.flatnonzero(pat)) for p, pat in enumerate(patterns) if pat.any()]


def kalman_update(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray, *, joseph: bool = True
) -> UpdateResult:
    """Condition N filters on their measurements; NaN components are not measured.

    Parameters
    ----------
    x : (N, n) prior states.
    P : (n, n) shared prior covariance or (N, n, n).
    z : (N, m) measurements; a whole row of NaN means "predict only", a row with
        some NaN components updates with the measured components alone (exactly
        the update with the rows of H and the rows/columns of R of the measured
        components).
    H : (m, n) measurement matrix, or (N, m, n) one per filter.
    R : (m, m) shared or (N, m, m) per-filter measurement noise covariance.
    joseph : use the Joseph form of the covariance update (default); False uses
        the cheaper P = (I - K H) P.

    Returns
    -------
    UpdateResult
        The posterior stays a single shared ``(n, n)`` covariance when P, H and R
        are shared and every filter measured every component (one n×n update
        instead of N).
    """
    N, n = x.shape
    m = H.shape[-2]
    measured = ~np.isnan(z)
    full = measured.all(axis=1)
    shared = P.ndim == 2 and R.ndim == 2 and H.ndim == 2

    if shared and full.all():
        x_post, P_post, y, S, K, nis, ll = gain_and_posterior(x, P, z, H, R, joseph)
        return UpdateResult(x_post, P_post, y, S, K, nis, ll, measured)

    # From here on every filter gets its own covariance.
    P_each = np.broadcast_to(P, (N, n, n))
    R_each = np.broadcast_to(R, (N, m, m))
    H_each = np.broadcast_to(H, (N, m, n))
    rows_complete_or_empty = bool((measured == full[:, None]).all())
    if rows_complete_or_empty and P.ndim == 3:
        # Rows are either complete or empty: one pass over all filters with a zero gain for
        # the empty rows (no gather/scatter by pattern).
        z_filled = np.where(measured, z, 0.0) if not full.all() else z
        x_post, P_post, y, S, K, nis, ll = gain_and_posterior(
            x, P, z_filled, H, R, joseph, None if full.all() else full)
        return UpdateResult(x_post, P_post, y, np.broadcast_to(S, (N, m, m)), K, nis, ll, measured)
    S = symmetrize(H_each @ P_each @ np.swapaxes(H_each, -1, -2) + R_each)
    groups = _measurement_patterns(measured)

    x_post = x.copy()
    P_post = np.array(P_each, copy=True)
    y = np.full((N, m), np.nan, dtype=x.dtype)
    K = np.zeros((N, n, m), dtype=x.dtype)
    nis = np.full(N, np.nan, dtype=x.dtype)
    ll = np.full(N, np.nan, dtype=x.dtype)
    for rows, cols in groups:
        H_sub = H[cols] if H.ndim == 2 else H_each[rows][:, cols]
        R_sub = R[np.ix_(cols, cols)] if R.ndim == 2 else R_each[rows][:, cols[:, None], cols]
        P_sub = P if P.ndim == 2 else P_each[rows]
        xs, Ps, ys, _, Ks, nis_s, ll_s = gain_and_posterior(x[rows], P_sub, z[rows][:, cols], H_sub, R_sub, joseph)
        x_post[rows] = xs
        P_post[rows] = Ps
        y[rows[:, None], cols] = ys
        K[rows[:, None], :, cols] = np.swapaxes(np.broadcast_to(Ks, (rows.size, n, cols.size)), 1, 2)
        nis[rows] = nis_s
        ll[rows] = ll_s
    return UpdateResult(x_post, P_post, y, S, K, nis, ll, measured)


@dataclass(frozen=True)
class InnovationStatistics:
    """Statistics of candidate measurements under the predicted (prior) state, for N filters.

    Attributes
    ----------
    y : (N, K, m) innovations z - H x⁻ (NaN where the candidate has NaN).
    S : (N, m, m) innovation covariances H P⁻ Hᵀ + R.
    nis : (N, K) squared Mahalanobis distances yᵀ S⁻¹ y (the gating distance;
        chi-square with m degrees of freedom for a correct model).
    log_likelihood : (N, K) log N(z; H x⁻, S).
    """

    y: np.ndarray
    S: np.ndarray
    nis: np.ndarray
    log_likelihood: np.ndarray


def innovation_statistics(
    x_prior: np.ndarray, P_prior: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray
) -> InnovationStatistics:
    """Innovation, its covariance, squared Mahalanobis distance and log-likelihood from the prior.

    Nothing is updated: use it to gate K candidate measurements per filter before
    choosing one (FilterPy's ``mahalanobis`` uses the posterior, which is not the
    gating distance).

    Parameters
    ----------
    x_prior : (N, n) predicted states.
    P_prior : (n, n) shared or (N, n, n) predicted covariances.
    z : (N, K, m) K candidate measurements per filter, or (N, m) one each.
    H : (m, n) or (N, m, n) measurement matrix.
    R : (m, m) or (N, m, m) measurement noise covariance.

    Returns
    -------
    InnovationStatistics
        With ``y`` (N, K, m) and ``nis``/``log_likelihood`` (N, K); the K axis is
        absent when ``z`` was (N, m).  NaN where a candidate holds NaN.

    Examples
    --------
    >>> import numpy as np
    >>> stats = innovation_statistics(np.zeros((1, 2)), np.eye(2), np.array([[[3.0, 0.0], [0.0, 1.0]]]),
    ...                               np.eye(2), np.eye(2))
    >>> stats.nis          # S = 2 I: distances 9/2 and 1/2
    array([[4.5, 0.5]])
    """
    one = z.ndim == 2
    Z = z[:, None, :] if one else z
    Ht = np.swapaxes(H, -1, -2)
    S = symmetrize(H @ P_prior @ Ht + R)
    L = cholesky_checked(S, "the innovation covariance S = H P Hᵀ + R")
    y = Z - mat_vec(H, x_prior)[:, None, :]
    # |L⁻¹ y|² for all K candidates at once: solve with the K candidates as columns.
    w = solve_lower(L, np.swapaxes(y, -1, -2))
    nis = np.sum(w * w, axis=-2)
    log_det = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    ll = -0.5 * (nis + np.asarray(log_det)[..., None] + H.shape[-2] * LOG_2PI)
    S_out = np.broadcast_to(S, (x_prior.shape[0], *S.shape[-2:]))
    if one:
        return InnovationStatistics(y[:, 0], S_out, nis[:, 0], ll[:, 0])
    return InnovationStatistics(y, S_out, nis, ll)


def _check_memory(shape: tuple[int, ...], itemsize: int) -> None:
    """Refuse N filters whose states and covariances cannot fit in this machine's memory, naming ``x``."""
    N, n = shape
    check_fits_in_memory(N * (n + n * n) * itemsize * 2,  # state and covariance, prior and posterior
                         f"x holds {N} filters of {n} states: their states and covariances",
                         "use fewer filters per KalmanFilter or dtype=np.float32")


class KalmanFilter:
    """N independent linear Kalman filters that share one model (F, H, Q; R shared or per filter).

    Parameters
    ----------
    x : (N, n) initial states, or (n,) for a single filter.
    P : (n, n) initial covariance shared by all filters, or (N, n, n).
    F : (n, n) state transition, or (N, n, n) one per filter.
    H : (m, n) measurement matrix, or (N, m, n) one per filter.
    Q : (n, n) process noise covariance, or (N, n, n).
    R : (m, m) measurement noise covariance, or (N, m, m) one per filter.
    dtype : ``np.float64`` (default) or ``np.float32`` (half the memory, computed in
        float32 throughout; on the constant-velocity model at pixel scale the
        states stay within 3e-4 px of float64 over 100 steps, tested < 2e-3 px,
        see ``docs/kalman.md``).
    joseph : Joseph-form covariance update (default, keeps P symmetric PSD);
        False uses P = (I - K H) P, which is cheaper.

    Attributes use FilterPy's names: ``x``, ``P`` (posterior after ``update``, prior
    after ``predict``), ``x_prior``, ``P_prior``, ``y`` (innovation), ``S``
    (innovation covariance), ``K`` (gain), plus ``nis`` and ``log_likelihood`` of
    the last measurement computed from the prior.  No history is kept: use
    :meth:`run` for a batch with history, :func:`~kalmansfm.estimation.smoothing.smooth`
    to smooth it.

    The arithmetic runs in compiled kernels (numba) that read and write each
    filter's state and covariance once per step: ``predict`` only records the
    transition, and the following ``update`` predicts and updates in one pass (the
    prior is computed when it is read, with the same arithmetic).  The filter
    picks the cheapest exact form for the model, with the same results:

    * the covariance is kept as one shared matrix for as long as every filter has
      the same history (same P0, all measured every step), so 100 000 tracks cost
      one n×n update, not 100 000; ``P`` still shows shape (N, n, n) (a read-only
      broadcast view);
    * when F is the constant-velocity transition and Q, R, P do not couple x with
      y (the model of :func:`~kalmansfm.estimation.constant_velocity_2d`), the filter
      runs as two 2-state filters with a scalar measurement, storing three
      numbers per covariance block (one block for x and y while their histories
      agree); ``P`` is then assembled as (N, 4, 4) on access (read-only; assign
      ``kf.P = ...`` to change it).

    The arrays a step returns (``kf.x``, ``kf.P``, ...) keep their values as long as
    they are held; the filter reuses its storage only for arrays nobody holds.

    Examples
    --------
    >>> import numpy as np
    >>> from kalmansfm.estimation import constant_velocity_2d
    >>> model = constant_velocity_2d()
    >>> kf = KalmanFilter(np.zeros((3, 4)), model.P0, model.F, model.H, model.Q, model.R)
    >>> kf.predict()
    >>> kf.update(np.array([[1.0, 2.0], [np.nan, np.nan], [0.5, 0.5]]))
    >>> kf.x.shape, kf.P.shape
    ((3, 4), (3, 4, 4))
    >>> bool(np.isnan(kf.y[1]).all())   # filter 1 was not measured: it only predicted
    True
    >>> round(float(kf.P[0, 0, 0]), 6)
    3.889655
    >>> kf.predict()
    >>> kf.gating_distance(np.array([[[1.0, 2.0], [9.0, 9.0]]] * 3)).shape   # 2 candidates per filter
    (3, 2)
    """

    def __init__(
        self,
        x: object,
        P: object,
        F: object,
        H: object,
        Q: object,
        R: object,
        *,
        dtype: type | np.dtype = np.float64,
        joseph: bool = True,
    ) -> None:
        try:
            self.dtype = np.dtype(dtype)
        except TypeError:
            raise InvalidInputError(f"dtype must be float64 or float32; got {dtype!r}") from None
        if self.dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise InvalidInputError(f"dtype must be float64 or float32; got {self.dtype}")
        self.joseph = bool(joseph)
        x_arr = self._array("x", x)
        if x_arr.ndim not in (1, 2):
            raise InvalidInputError(f"x must have shape (N, n) or (n,); got {x_arr.shape}")
        self._single = x_arr.ndim == 1
        _check_memory(np.atleast_2d(x_arr).shape, self.dtype.itemsize)
        x_arr = np.atleast_2d(x_arr).copy()
        check_finite("x", x_arr)
        self._N, self._n = x_arr.shape
        self.F = self._transition("F", F)
        self.Q = self._transition("Q", Q)
        check_covariance("Q", self.Q, allow_singular=True)
        self.H = self._measurement_matrix(H)
        self.R = self._measurement_noise(R)
        P_arr = self._covariance(P)
        self._engine = FilterEngine(x_arr, P_arr, self._model(), joseph=self.joseph)
        self._last_F = self.F

    # -- construction helpers -------------------------------------------------
    def _array(self, name: str, value: object) -> np.ndarray:
        return as_float_array(name, value, dtype=self.dtype)

    def _transition(self, name: str, value: object) -> np.ndarray:
        """F or Q: (n, n) or (N, n, n)."""
        arr = self._array(name, value)
        n = self.dim_x
        meaning = "(state transition)" if name == "F" else "(process noise covariance)"
        if arr.ndim == 3:
            check_shape(name, arr, (self.n_filters, n, n), f"{meaning}, one per filter, or ({n}, {n}) shared")
        else:
            check_shape(name, arr, (n, n), f"{meaning}, or ({self.n_filters}, {n}, {n}) one per filter")
        check_finite(name, arr)
        return arr

    def _measurement_matrix(self, H: object) -> np.ndarray:
        arr = self._array("H", H)
        n = self.dim_x
        ok = (arr.ndim == 2 and arr.shape[1] == n) or (arr.ndim == 3 and arr.shape[0] == self.n_filters
                                                       and arr.shape[2] == n)
        if not ok:
            raise InvalidInputError(f"H must have shape (m, {n}) or ({self.n_filters}, m, {n}) "
                                    f"(measurement matrix); got {arr.shape}")
        check_finite("H", arr)
        return arr

    def _measurement_noise(self, R: object) -> np.ndarray:
        m = self.H.shape[-2]
        arr = self._array("R", R)
        if arr.shape != (m, m):
            check_shape("R", arr, (self.n_filters, m, m), f"(one per filter) or ({m}, {m}) shared")
        diagonal = np.diagonal(arr, axis1=-2, axis2=-1)
        if arr.ndim == 3 and np.count_nonzero(arr) == np.count_nonzero(diagonal):
            # Per-filter diagonal R (e.g. noise from the match quality): positive definite iff the
            # diagonal is, which avoids one eigen-decomposition per filter.
            check_finite("R", arr)
            if not np.all(diagonal > 0):
                bad = np.argwhere(~(diagonal > 0))[0]
                raise InvalidInputError(f"R must be positive definite (matrix ({bad[0]},)); "
                                        f"diagonal entry {bad[1]} is {diagonal[tuple(bad)]}")
            return arr
        check_covariance("R", arr)
        return arr

    def _covariance(self, P: object) -> np.ndarray:
        arr = self._array("P", P)
        n = self.dim_x
        if arr.shape != (n, n):
            if self._single and arr.shape == (1, n, n):
                arr = arr[0]
            else:
                check_shape("P", arr, (self.n_filters, n, n), "(one covariance per filter) or (n, n) shared")
        if not _decoupled.clearly_positive_definite_blocks(arr):
            check_covariance("P", arr)
        return arr

    def _model(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return self.F, self.Q, self.H, self.R

    # -- public state ----------------------------------------------------------
    @property
    def n_filters(self) -> int:
        """Number of filters N."""
        return self._N

    @property
    def dim_x(self) -> int:
        """State dimension n."""
        return self._n

    @property
    def dim_z(self) -> int:
        """Measurement dimension m."""
        return self.H.shape[-2]

    @property
    def decoupled(self) -> bool:
        """True while the filter runs in the decoupled constant-velocity form."""
        return self._engine.decoupled

    @property
    def shared_covariance(self) -> bool:
        """True while all filters have one covariance (stored once)."""
        return self._engine.shared_covariance

    def _present(self, a: np.ndarray, per_filter_ndim: int) -> np.ndarray:
        if a.ndim < per_filter_ndim:  # shared: show it per filter without copying
            a = np.broadcast_to(a, (self.n_filters, *a.shape))
        return a[0] if self._single else a

    @property
    def x(self) -> np.ndarray:
        """Current states, (N, n) (or (n,) for a single filter)."""
        return self._present(self._engine.x(), 2)

    @x.setter
    def x(self, value: object) -> None:
        arr = np.atleast_2d(self._array("x", value))
        check_shape("x", arr, (self.n_filters, self.dim_x), "(one state per filter)")
        check_finite("x", arr)
        self._engine.set_states(arr)

    @property
    def P(self) -> np.ndarray:
        """Current covariances, (N, n, n) (read-only when shared or assembled from the decoupled form)."""
        return self._present(self._engine.P(), 3)

    @P.setter
    def P(self, value: object) -> None:
        P = self._covariance(value)
        self._engine.set_state(np.ascontiguousarray(self._engine.x()), P, self._model())

    @property
    def x_prior(self) -> np.ndarray:
        """States after the last ``predict``."""
        return self._present(self._engine.x_prior(), 2)

    @property
    def P_prior(self) -> np.ndarray:
        """Covariances after the last ``predict``."""
        return self._present(self._engine.P_prior(), 3)

    def _from_last(self, field: str, per_filter_ndim: int) -> np.ndarray:
        if self._engine.last is None:
            raise AttributeError(f"{field} is available after the first update()")
        return self._present(getattr(self._engine.last, field), per_filter_ndim)

    @property
    def y(self) -> np.ndarray:
        """Innovation z - H x⁻ of the last update, (N, m); NaN where not measured."""
        return self._from_last("y", 2)

    @property
    def S(self) -> np.ndarray:
        """Innovation covariance H P⁻ Hᵀ + R of the last update, (N, m, m)."""
        return self._from_last("S", 3)

    @property
    def K(self) -> np.ndarray:
        """Kalman gain of the last update, (N, n, m); zero where not measured."""
        return self._from_last("K", 3)

    @property
    def nis(self) -> np.ndarray:
        """Squared Mahalanobis distance yᵀ S⁻¹ y of the last measurement, (N,); NaN if none."""
        return self._from_last("nis", 1)

    @property
    def log_likelihood(self) -> np.ndarray:
        """log N(z; H x⁻, S) of the last measurement, (N,); NaN if none."""
        return self._from_last("log_likelihood", 1)

    # -- the two steps -----------------------------------------------------------
    def predict(
        self,
        u: object | None = None,
        B: object | None = None,
        F: object | None = None,
        Q: object | None = None,
    ) -> None:
        """Advance every filter one step: x⁻ = F x + B u, P⁻ = F P Fᵀ + Q.

        The transition is applied by the next ``update`` in the same pass over memory,
        or as soon as the prior is read (``x``, ``P``, ``x_prior``, gating).

        Parameters
        ----------
        u : optional known input, (n,) or (N, n) when ``B`` is None (added to the
            state directly), else (k,) or (N, k).
        B : optional (n, k) input matrix.
        F, Q : optional matrices for this step only (time-varying model, e.g. a
            variable frame interval): (n, n), or (N, n, n) one per filter.
        """
        n = self.dim_x
        F_arr = self.F if F is None else self._transition("F", F)
        Q_arr = self.Q if Q is None else self._transition("Q", Q)
        if Q is not None:
            check_covariance("Q", Q_arr, allow_singular=True)
        offset = None
        if u is not None:
            u_arr = self._array("u", u)
            if B is not None:
                B_arr = self._array("B", B)
                if B_arr.ndim != 2 or B_arr.shape[0] != n:
                    raise InvalidInputError(f"B must have shape ({n}, k); got {B_arr.shape}")
                u_arr = u_arr @ B_arr.T
            if u_arr.shape not in ((n,), (self.n_filters, n)):
                raise InvalidInputError(f"u must have shape ({n},) or ({self.n_filters}, {n}); got {u_arr.shape}")
            check_finite("u", u_arr)
            # (n, N), the layout of the states
            offset = np.ascontiguousarray(np.broadcast_to(u_arr, (self.n_filters, n)).T)
        self._last_F = F_arr
        self._engine.predict(F_arr, Q_arr, offset)

    def update(self, z: object, R: object | None = None, H: object | None = None) -> None:
        """Condition every filter on its measurement.

        Parameters
        ----------
        z : (N, m) measurements (or (m,) for a single filter).  A row of NaN means
            "no measurement for this filter this step"; some NaN components in a row
            update with the others only.
        R : optional measurement noise for this step only, (m, m) or (N, m, m)
            (e.g. per-measurement noise from the match quality).
        H : optional measurement matrix for this step only, (m, n) or (N, m, n);
            it must keep the measurement dimension m.
        """
        z_arr = np.atleast_2d(self._array("z", z))
        check_shape("z", z_arr, (self.n_filters, self.dim_z), "(one measurement row per filter, NaN = missing)")
        H_arr = self.H
        if H is not None:
            H_arr = self._measurement_matrix(H)
            if H_arr.shape[-2] != self.dim_z:
                raise InvalidInputError(f"H must keep the measurement dimension {self.dim_z}; got {H_arr.shape}")
        R_arr = self.R if R is None else self._measurement_noise(R)
        self._engine.update(z_arr, H_arr, R_arr, self._model())

    # -- statistics from the prior, batch runs ---------------------------------------
    def innovation_statistics(
        self, z: object, R: object | None = None, H: object | None = None
    ) -> InnovationStatistics:
        """Innovation, S, squared Mahalanobis distance and log-likelihood of candidates under the prior.

        Uses the state after the last ``predict`` (``x_prior``, ``P_prior``) and
        changes nothing.  ``z`` is (N, K, m) (K candidates per filter) or (N, m).
        """
        z_arr = self._array("z", z)
        if z_arr.ndim not in (2, 3) or z_arr.shape[0] != self.n_filters or z_arr.shape[-1] != self.dim_z:
            raise InvalidInputError(f"z must have shape ({self.n_filters}, K, {self.dim_z}) or "
                                    f"({self.n_filters}, {self.dim_z}); got {z_arr.shape}")
        H_arr = self.H if H is None else self._measurement_matrix(H)
        R_arr = self.R if R is None else self._measurement_noise(R)
        x_prior, P_prior = self._engine.prior_for_statistics()  # (N, n) and (N, n, n) or a shared (n, n)
        return innovation_statistics(x_prior, P_prior, z_arr, H_arr, R_arr)

    def gating_distance(self, candidates: object, R: object | None = None) -> np.ndarray:
        """Squared Mahalanobis distance of candidate measurements from the prediction, (N, K).

        ``candidates`` (N, K, m); the distance is yᵀ S⁻¹ y with y = z - H x⁻ and
        S = H P⁻ Hᵀ + R from the last ``predict`` (chi-square with m degrees of
        freedom under the model, e.g. accept d² < 9.21 for 99 % with m = 2).
        NaN where a candidate holds NaN.
        """
        c = self._array("candidates", candidates)
        if c.ndim != 3:
            raise InvalidInputError(f"candidates must have shape ({self.n_filters}, K, {self.dim_z}); got {c.shape}")
        return self.innovation_statistics(c, R=R).nis

    def run(
        self,
        zs: object,
        *,
        F: object | None = None,
        Q: object | None = None,
        H: object | None = None,
        R: object | None = None,
    ) -> FilterRun:
        """Run T predict + update steps and return their history (the filter advances too).

        Parameters
        ----------
        zs : (T, N, m) measurements, NaN for missing (rows or components).
        F, Q : optional per-step models, (T, n, n) or (T, N, n, n); default the filter's.
        H : optional per-step measurement matrices, (T, m, n) or (T, N, m, n).
        R : optional per-step measurement noise, (T, m, m) or (T, N, m, m).

        Returns
        -------
        FilterRun
            Per-step priors and posteriors, the transitions used, NIS and
            log-likelihood; give it to :func:`~kalmansfm.estimation.smoothing.smooth`.

        Examples
        --------
        >>> import numpy as np
        >>> from kalmansfm.estimation import constant_velocity_2d
        >>> m = constant_velocity_2d()
        >>> kf = KalmanFilter(np.zeros((2, 4)), m.P0, m.F, m.H, m.Q, m.R)
        >>> run = kf.run(np.zeros((10, 2, 2)))
        >>> run.x.shape, run.P_prior.shape, run.nis.shape
        ((10, 2, 4), (10, 2, 4, 4), (10, 2))
        """
        Z = self._array("zs", zs)
        if self._single and Z.ndim == 2:
            Z = Z[:, None, :]
        check_shape("zs", Z, (None, self.n_filters, self.dim_z), "(steps, filters, m), NaN = missing")
        T = Z.shape[0]
        if T == 0:
            raise InvalidInputError("zs must hold at least one step; got 0")
        per_step = {}
        for name, value in (("F", F), ("Q", Q), ("H", H), ("R", R)):
            if value is not None:
                arr = self._array(name, value)
                if arr.ndim < 3 or arr.shape[0] != T:
                    raise InvalidInputError(f"{name} in run() is one matrix per step: shape ({T}, ...); "
                                            f"got {arr.shape}")
                per_step[name] = arr
        x0 = np.array(self.x if not self._single else self.x[None])
        P0 = np.array(np.broadcast_to(self.P if not self._single else self.P[None],
                                      (self.n_filters, self.dim_x, self.dim_x)))
        hist = {k: [] for k in ("x_prior", "P_prior", "x", "P", "F", "nis", "log_likelihood")}
        for t in range(T):
            step = {k: v[t] for k, v in per_step.items()}
            self.predict(F=step.get("F"), Q=step.get("Q"))
            self.update(Z[t], R=step.get("R"), H=step.get("H"))
            for k in ("x_prior", "P_prior", "x", "P", "nis", "log_likelihood"):
                v = getattr(self, k)
                hist[k].append(np.array(v if not self._single else v[None]))
            hist["F"].append(self._last_F)
        n, N = self.dim_x, self.n_filters
        Fs = hist["F"]
        F_hist = np.stack(Fs) if all(f.ndim == 2 for f in Fs) else np.stack([np.broadcast_to(f, (N, n, n))
                                                                            for f in Fs])
        P_hist = [np.broadcast_to(p, (N, n, n)) for p in hist["P"]]
        return FilterRun(
            x_initial=x0,
            P_initial=P0,
            x_prior=np.stack(hist["x_prior"]),
            P_prior=np.stack(hist["P_prior"]),
            x=np.stack(hist["x"]),
            P=np.stack(P_hist),
            F=F_hist,
            nis=np.stack(hist["nis"]).reshape(T, N),
            log_likelihood=np.stack(hist["log_likelihood"]).reshape(T, N),
        )
