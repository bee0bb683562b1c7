"""Batched linear Kalman filter: N independent filters advanced together.

The pure functions :func:`kalman_predict` and :func:`kalman_update` do the
arithmetic; :class:`KalmanFilter` keeps the state between calls and is built on
them.  Shapes: states ``(N, n)``, covariances ``(N, n, n)`` or one shared
``(n, n)``, measurements ``(N, m)`` with NaN for "not measured".

Symbols (as in every textbook and in FilterPy):

* ``F`` state transition (n, n), ``Q`` process noise covariance (n, n)
* ``H`` measurement matrix (m, n), ``R`` measurement noise covariance (m, m)
* ``y`` innovation z - H x⁻, ``S`` its covariance H P⁻ Hᵀ + R, ``K`` the gain
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError, SingularCovarianceError
from ._checks import as_float_array, check_covariance, check_finite, check_shape

__all__ = ["KalmanFilter", "UpdateResult", "kalman_predict", "kalman_update"]

_LOG_2PI = float(np.log(2.0 * np.pi))


def _symmetrize(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + np.swapaxes(P, -1, -2))


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
    x_prior = np.einsum("...ij,...j->...i", F, x)
    if u is not None:
        x_prior = x_prior + u
    P_prior = _symmetrize(F @ P @ np.swapaxes(F, -1, -2) + Q)
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


def _cholesky_checked(S: np.ndarray, what: str) -> np.ndarray:
    try:
        return np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise SingularCovarianceError(
            f"{what} is not positive definite; check that R is positive definite and P has not collapsed"
        ) from None


def _gain_and_posterior(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Dense update of filters that measured every component of ``z``.

    ``P`` and ``R`` may be shared ((n, n), (m, m)) or stacked ((k, n, n), (k, m, m));
    the outputs broadcast accordingly.
    """
    HP = H @ P
    S = _symmetrize(HP @ H.T + R)
    L = _cholesky_checked(S, "the innovation covariance S = H P Hᵀ + R")
    # K = P Hᵀ S⁻¹, computed as (S⁻¹ H P)ᵀ because S and P are symmetric.
    K = np.swapaxes(np.linalg.solve(S, HP), -1, -2)
    y = z - x @ H.T
    x_post = x + np.einsum("...ij,...j->...i", K, y)
    # Joseph form: P = (I - KH) P (I - KH)ᵀ + K R Kᵀ, symmetric PSD even when K is not optimal.
    A = np.eye(P.shape[-1], dtype=P.dtype) - K @ H
    P_post = _symmetrize(A @ P @ np.swapaxes(A, -1, -2) + K @ R @ np.swapaxes(K, -1, -2))
    # yᵀ S⁻¹ y through the Cholesky factor: |L⁻¹ y|².
    if L.ndim == 2:
        w = np.linalg.solve(L, y.T).T
    else:
        w = np.linalg.solve(L, y[..., None])[..., 0]
    nis = np.sum(w * w, axis=-1)
    log_det = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    log_likelihood = -0.5 * (nis + log_det + H.shape[0] * _LOG_2PI)
    return x_post, P_post, y, S, K, nis, log_likelihood  # type: ignore[return-value]


def kalman_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> UpdateResult:
    """Condition N filters on their measurements; NaN components are not measured.

    Parameters
    ----------
    x : (N, n) prior states.
    P : (n, n) shared prior covariance or (N, n, n).
    z : (N, m) measurements; a whole row of NaN means "predict only", a row with
        some NaN components updates with the measured components alone.
    H : (m, n) measurement matrix.
    R : (m, m) shared or (N, m, m) per-filter measurement noise covariance.

    Returns
    -------
    UpdateResult
        The posterior stays a single shared ``(n, n)`` covariance when P and R are
        shared and every filter measured every component (one 4×4 update instead
        of N).
    """
    N, n = x.shape
    m = H.shape[0]
    measured = ~np.isnan(z)
    full = measured.all(axis=1)
    shared = P.ndim == 2 and R.ndim == 2

    if shared and full.all():
        x_post, P_post, y, S, K, nis, ll = _gain_and_posterior(x, P, z, H, R)
        return UpdateResult(x_post, P_post, y, S, K, nis, ll, measured)

    # From here on every filter gets its own covariance.
    P_each = np.broadcast_to(P, (N, n, n))
    R_each = np.broadcast_to(R, (N, m, m))
    x_post = x.copy()
    P_post = np.array(P_each, copy=True)
    y = np.full((N, m), np.nan, dtype=x.dtype)
    K = np.zeros((N, n, m), dtype=x.dtype)
    nis = np.full(N, np.nan, dtype=x.dtype)
    ll = np.full(N, np.nan, dtype=x.dtype)
    S = _symmetrize(H @ P_each @ H.T + R_each)

    any_measured = measured.any(axis=1)
    if any_measured.any():
        patterns, group = np.unique(measured[any_measured], axis=0, return_inverse=True)
        rows_measured = np.flatnonzero(any_measured)
        for p, pattern in enumerate(patterns):
            rows = rows_measured[group.ravel() == p]
            cols = np.flatnonzero(pattern)
            H_sub = H[cols]
            R_sub = R_each[rows][:, cols[:, None], cols]
            xs, Ps, ys, _, Ks, nis_s, ll_s = _gain_and_posterior(
                x[rows], P_each[rows], z[rows][:, cols], H_sub, R_sub
            )
            x_post[rows] = xs
            P_post[rows] = Ps
            y[rows[:, None], cols] = ys
            K[rows[:, None], :, cols] = np.swapaxes(Ks, 1, 2)
            nis[rows] = nis_s
            ll[rows] = ll_s
    return UpdateResult(x_post, P_post, y, S, K, nis, ll, measured)


class KalmanFilter:
    """N independent linear Kalman filters that share one model (F, H, Q; R shared or per filter).

    Parameters
    ----------
    x : (N, n) initial states, or (n,) for a single filter.
    P : (n, n) initial covariance shared by all filters, or (N, n, n).
    F : (n, n) state transition.
    H : (m, n) measurement matrix.
    Q : (n, n) process noise covariance.
    R : (m, m) measurement noise covariance, or (N, m, m) one per filter.

    Attributes use FilterPy's names: ``x``, ``P`` (posterior after ``update``, prior
    after ``predict``), ``x_prior``, ``P_prior``, ``y`` (innovation), ``S``
    (innovation covariance), ``K`` (gain), plus ``nis`` and ``log_likelihood`` of
    the last measurement computed from the prior.  The covariance is kept as one
    shared matrix for as long as every filter has the same history (same P0, all
    measured every step), so 100 000 tracks cost one 4×4 update, not 100 000;
    ``P`` still shows shape (N, n, n) (a read-only broadcast view).

    Examples
    --------
    >>> import numpy as np
    >>> from kalmansfm.models import constant_velocity_2d
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
    """

    def __init__(self, x: object, P: object, F: object, H: object, Q: object, R: object) -> None:
        x_arr = as_float_array("x", x)
        if x_arr.ndim not in (1, 2):
            raise InvalidInputError(f"x must have shape (N, n) or (n,); got {x_arr.shape}")
        self._single = x_arr.ndim == 1
        x_arr = np.atleast_2d(x_arr).copy()
        check_finite("x", x_arr)
        N, n = x_arr.shape
        self.F = self._model_matrix("F", F, (n, n), "(state transition)")
        self.Q = self._model_matrix("Q", Q, (n, n), "(process noise covariance)")
        check_covariance("Q", self.Q, allow_singular=True)
        H_arr = as_float_array("H", H)
        if H_arr.ndim != 2 or H_arr.shape[1] != n:
            raise InvalidInputError(f"H must have shape (m, {n}) (measurement matrix); got {H_arr.shape}")
        check_finite("H", H_arr)
        self.H = H_arr
        self.R = self._measurement_noise(R, N)
        P_arr = as_float_array("P", P)
        if P_arr.shape == (n, n):
            check_covariance("P", P_arr)
        else:
            check_shape("P", P_arr, (N, n, n), "(one covariance per filter) or (n, n) shared")
            check_covariance("P", P_arr)
        self._x = x_arr
        self._P = P_arr.copy()
        self._x_prior = self._x.copy()
        self._P_prior = self._P.copy()
        self._last: UpdateResult | None = None

    # -- construction helpers -------------------------------------------------
    @staticmethod
    def _model_matrix(name: str, value: object, shape: tuple[int, int], meaning: str) -> np.ndarray:
        arr = as_float_array(name, value)
        check_shape(name, arr, shape, meaning)
        check_finite(name, arr)
        return arr

    def _measurement_noise(self, R: object, N: int) -> np.ndarray:
        m = self.H.shape[0]
        arr = as_float_array("R", R)
        if arr.shape != (m, m):
            check_shape("R", arr, (N, m, m), f"(one per filter) or ({m}, {m}) shared")
        check_covariance("R", arr)
        return arr

    # -- public state ----------------------------------------------------------
    @property
    def n_filters(self) -> int:
        """Number of filters N."""
        return self._x.shape[0]

    @property
    def dim_x(self) -> int:
        """State dimension n."""
        return self._x.shape[1]

    @property
    def dim_z(self) -> int:
        """Measurement dimension m."""
        return self.H.shape[0]

    @property
    def shared_covariance(self) -> bool:
        """True while all filters have one covariance (stored once)."""
        return self._P.ndim == 2

    def _present(self, a: np.ndarray, per_filter_ndim: int) -> np.ndarray:
        if a.ndim < per_filter_ndim:  # shared: show it per filter without copying
            a = np.broadcast_to(a, (self.n_filters, *a.shape))
        return a[0] if self._single else a

    @property
    def x(self) -> np.ndarray:
        """Current states, (N, n) (or (n,) for a single filter)."""
        return self._x[0] if self._single else self._x

    @x.setter
    def x(self, value: object) -> None:
        arr = np.atleast_2d(as_float_array("x", value))
        check_shape("x", arr, self._x.shape, "(one state per filter)")
        self._x = arr.copy()

    @property
    def P(self) -> np.ndarray:
        """Current covariances, (N, n, n) (a read-only view when shared)."""
        return self._present(self._P, 3)

    @P.setter
    def P(self, value: object) -> None:
        arr = as_float_array("P", value)
        n = self.dim_x
        if arr.shape != (n, n):
            arr = arr.reshape(1, n, n) if self._single and arr.shape == (n, n) else arr
            check_shape("P", arr, (self.n_filters, n, n), "(one covariance per filter) or (n, n) shared")
        check_covariance("P", arr)
        self._P = arr.copy()

    @property
    def x_prior(self) -> np.ndarray:
        """States after the last ``predict``."""
        return self._x_prior[0] if self._single else self._x_prior

    @property
    def P_prior(self) -> np.ndarray:
        """Covariances after the last ``predict``."""
        return self._present(self._P_prior, 3)

    def _from_last(self, field: str, per_filter_ndim: int) -> np.ndarray:
        if self._last is None:
            raise AttributeError(f"{field} is available after the first update()")
        return self._present(getattr(self._last, field), per_filter_ndim)

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

        Parameters
        ----------
        u : optional known input, (n,) or (N, n) when ``B`` is None (added to the
            state directly), else (k,) or (N, k).
        B : optional (n, k) input matrix.
        F, Q : optional (n, n) matrices for this step only (time-varying model).
        """
        n = self.dim_x
        F_arr = self.F if F is None else self._model_matrix("F", F, (n, n), "(state transition)")
        Q_arr = self.Q if Q is None else self._model_matrix("Q", Q, (n, n), "(process noise covariance)")
        offset = None
        if u is not None:
            u_arr = as_float_array("u", u)
            if B is not None:
                B_arr = as_float_array("B", B)
                if B_arr.ndim != 2 or B_arr.shape[0] != n:
                    raise InvalidInputError(f"B must have shape ({n}, k); got {B_arr.shape}")
                u_arr = u_arr @ B_arr.T
            if u_arr.shape not in ((n,), (self.n_filters, n)):
                raise InvalidInputError(f"u must have shape ({n},) or ({self.n_filters}, {n}); got {u_arr.shape}")
            check_finite("u", u_arr)
            offset = u_arr
        self._x, self._P = kalman_predict(self._x, self._P, F_arr, Q_arr, offset)
        self._x_prior, self._P_prior = self._x, self._P

    def update(self, z: object, R: object | None = None) -> None:
        """Condition every filter on its measurement.

        Parameters
        ----------
        z : (N, m) measurements (or (m,) for a single filter).  A row of NaN means
            "no measurement for this filter this step"; some NaN components in a row
            update with the others only.
        R : optional measurement noise for this step only, (m, m) or (N, m, m).
        """
        z_arr = np.atleast_2d(as_float_array("z", z))
        check_shape("z", z_arr, (self.n_filters, self.dim_z), "(one measurement row per filter, NaN = missing)")
        if np.isinf(z_arr).any():
            raise InvalidInputError("z must not contain infinity (use NaN for a missing measurement)")
        R_arr = self.R if R is None else self._measurement_noise(R, self.n_filters)
        result = kalman_update(self._x, self._P, z_arr, self.H, R_arr)
        self._x, self._P = result.x, result.P
        self._last = result
