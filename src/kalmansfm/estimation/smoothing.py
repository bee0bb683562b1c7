"""Offline smoothing of a finished run of N Kalman filters (Rauch–Tung–Striebel).

The story has three steps and one object each:

* ``KalmanFilter.predict`` / ``KalmanFilter.update``: online, one step, no history;
* ``KalmanFilter.run(zs)``: T steps in a batch, returns a :class:`FilterRun`
  holding the per-step priors and posteriors (the only place history is kept);
* :func:`smooth` ``(run)``: the smoothed estimates, a :class:`SmoothedRun`.

A tracker that runs its filter online (its measurements depend on the gate, so
it cannot call ``run``) builds the :class:`FilterRun` itself with
:meth:`FilterRun.from_steps` from copies of ``kf.x_prior``, ``kf.P_prior``,
``kf.x`` and ``kf.P`` taken after each ``update``; a step where a filter had no
measurement (NaN row) is an ordinary step whose posterior equals its prior.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError, SingularCovarianceError
from .._validation import as_float_array, check_shape

__all__ = ["FilterRun", "SmoothedRun", "smooth"]


@dataclass(frozen=True)
class FilterRun:
    """History of T predict + update steps of N filters with state dimension n.

    Attributes
    ----------
    x_initial : (N, n) states before the first predict.
    P_initial : (N, n, n) covariances before the first predict.
    x_prior, P_prior : (T, N, n), (T, N, n, n) after the predict of each step.
    x, P : (T, N, n), (T, N, n, n) after the update of each step (equal to the
        prior where a filter was not measured).
    F : (T, n, n) or (T, N, n, n) the transition of each step's predict
        (x_prior[t] = F[t] x[t-1] + u), which the smoother needs.
    nis, log_likelihood : (T, N) the measurement statistics from the prior, NaN
        where nothing was measured (all NaN when built by ``from_steps`` without them).
    """

    x_initial: np.ndarray
    P_initial: np.ndarray
    x_prior: np.ndarray
    P_prior: np.ndarray
    x: np.ndarray
    P: np.ndarray
    F: np.ndarray
    nis: np.ndarray
    log_likelihood: np.ndarray

    @classmethod
    def from_steps(
        cls,
        x_initial: object,
        P_initial: object,
        x_prior: Sequence[object],
        P_prior: Sequence[object],
        x: Sequence[object],
        P: Sequence[object],
        F: object,
    ) -> FilterRun:
        """Assemble a run from per-step arrays recorded while filtering online.

        Parameters
        ----------
        x_initial : (N, n) states before the first step; P_initial (n, n) or (N, n, n).
        x_prior, P_prior, x, P : sequences of T arrays (N, n) and (N, n, n) (or (n, n)
            shared), e.g. copies of ``kf.x_prior``, ``kf.P_prior``, ``kf.x``, ``kf.P``.
        F : the transition used by every predict, (n, n), or per step (T, n, n) or
            (T, N, n, n).

        Examples
        --------
        >>> import numpy as np
        >>> from kalmansfm import KalmanFilter
        >>> kf = KalmanFilter(np.zeros((2, 1)), np.eye(1), np.eye(1), np.eye(1), np.eye(1), np.eye(1))
        >>> steps = {"x_prior": [], "P_prior": [], "x": [], "P": []}
        >>> for z in ([[1.0], [np.nan]], [[2.0], [0.5]]):
        ...     kf.predict(); kf.update(z)
        ...     for name in steps:
        ...         steps[name].append(getattr(kf, name).copy())
        >>> run = FilterRun.from_steps(np.zeros((2, 1)), np.eye(1), F=np.eye(1), **steps)
        >>> run.x.shape, run.P.shape
        ((2, 2, 1), (2, 2, 1, 1))
        """
        x0 = as_float_array("x_initial", x_initial)
        if x0.ndim != 2:
            raise InvalidInputError(f"x_initial must have shape (N, n); got {x0.shape}")
        N, n = x0.shape
        P0 = np.broadcast_to(as_float_array("P_initial", P_initial), (N, n, n)).copy()
        stacked = {}
        for name, seq, tail in (("x_prior", x_prior, (N, n)), ("x", x, (N, n)),
                                ("P_prior", P_prior, (N, n, n)), ("P", P, (N, n, n))):
            if len(seq) == 0:
                raise InvalidInputError(f"{name} must hold at least one step; got an empty sequence")
            try:
                stacked[name] = np.stack([np.broadcast_to(as_float_array(name, a), tail) for a in seq])
            except ValueError as exc:
                raise InvalidInputError(f"every step of {name} must have shape {tail}; {exc}") from None
        T = stacked["x"].shape[0]
        for name in stacked:
            if stacked[name].shape[0] != T:
                raise InvalidInputError(f"{name} has {stacked[name].shape[0]} steps, x has {T}")
        F_arr = as_float_array("F", F)
        if F_arr.shape == (n, n):
            F_arr = np.broadcast_to(F_arr, (T, n, n))
        elif F_arr.shape not in ((T, n, n), (T, N, n, n)):
            raise InvalidInputError(f"F must have shape ({n}, {n}), ({T}, {n}, {n}) or ({T}, {N}, {n}, {n}); "
                                    f"got {F_arr.shape}")
        nan = np.full((T, N), np.nan, dtype=x0.dtype)
        return cls(x0, P0, stacked["x_prior"], stacked["P_prior"], stacked["x"], stacked["P"], F_arr, nan,
                   nan.copy())


@dataclass(frozen=True)
class SmoothedRun:
    """Smoothed estimates of a :class:`FilterRun`.

    Attributes
    ----------
    x : (T, N, n) smoothed states (mean given the measurements of the whole run,
        or up to ``lag`` steps ahead for fixed-lag smoothing).
    P : (T, N, n, n) their covariances.
    x_initial, P_initial : (N, n), (N, n, n) the smoothed initial state.
    lag : the fixed lag, or None for the fixed-interval smoother.
    """

    x: np.ndarray
    P: np.ndarray
    x_initial: np.ndarray
    P_initial: np.ndarray
    lag: int | None


def _smoother_gains(P_filt: np.ndarray, F: np.ndarray, P_pred: np.ndarray) -> np.ndarray:
    """C_t = P_t F_{t+1}ᵀ (P⁻_{t+1})⁻¹ for all t at once, via Cᵀ = (P⁻)⁻¹ F P (all symmetric)."""
    FP = F @ P_filt
    try:
        Ct = np.linalg.solve(P_pred, FP)
    except np.linalg.LinAlgError:
        raise SingularCovarianceError(
            "a predicted covariance P⁻ of the run is singular; the smoother needs Q or P positive definite"
        ) from None
    return np.swapaxes(Ct, -1, -2)


def smooth(run: FilterRun, lag: int | None = None) -> SmoothedRun:
    """Rauch–Tung–Striebel smoothing of all N filters of a finished run.

    Backward pass, vectorised over the N filters, with the smoother gain
    C_t = P_t F_{t+1}ᵀ (P⁻_{t+1})⁻¹::

        x̂_t = x_t + C_t (x̂_{t+1} - x⁻_{t+1})
        P̂_t = P_t + C_t (P̂_{t+1} - P⁻_{t+1}) C_tᵀ

    Parameters
    ----------
    run : a :class:`FilterRun` from ``KalmanFilter.run`` or ``FilterRun.from_steps``.
    lag : None for the fixed-interval smoother (every estimate uses all T
        measurements); an integer L >= 0 for fixed-lag smoothing: the estimate
        at step t uses the measurements up to step t + L (L = 0 returns the
        filtered estimates), i.e. what an online smoother with a delay of L
        steps reports.

    Returns
    -------
    SmoothedRun

    Examples
    --------
    >>> import numpy as np
    >>> from kalmansfm import KalmanFilter
    >>> from kalmansfm.estimation import constant_velocity_2d
    >>> m = constant_velocity_2d()
    >>> kf = KalmanFilter(np.zeros((5, 4)), m.P0, m.F, m.H, m.Q, m.R)
    >>> zs = np.random.default_rng(0).normal(size=(20, 5, 2))
    >>> run = kf.run(zs)
    >>> s = smooth(run)
    >>> bool(np.all(s.P[:, :, 0, 0] <= run.P[:, :, 0, 0] + 1e-12))   # smoothing never adds uncertainty
    True
    >>> np.allclose(s.x[-1], run.x[-1])                             # the last step has nothing ahead
    True
    """
    if not isinstance(run, FilterRun):
        raise InvalidInputError(f"smooth expects a FilterRun (from KalmanFilter.run or FilterRun.from_steps); "
                                f"got {type(run).__name__}")
    if lag is not None and (int(lag) != lag or lag < 0):
        raise InvalidInputError(f"lag must be None or an integer >= 0; got {lag}")
    T, N, n = run.x.shape
    check_shape("run.P", run.P, (T, N, n, n), "(steps, filters, n, n)")
    # The initial state joins the sequence as step 0: all arrays indexed 0..T.
    x_f = np.concatenate([run.x_initial[None], run.x])
    P_f = np.concatenate([run.P_initial[None], run.P])
    F = run.F if run.F.ndim == 4 else run.F[:, None]
    # gains[t] links step t to step t + 1 of the extended sequence.
    gains = _smoother_gains(P_f[:-1], F, run.P_prior)
    x_p, P_p = run.x_prior, run.P_prior

    if lag is None:
        xs = np.empty_like(x_f)
        Ps = np.empty_like(P_f)
        xs[-1], Ps[-1] = x_f[-1], P_f[-1]
        for t in range(T - 1, -1, -1):
            C = gains[t]
            xs[t] = x_f[t] + np.matmul(C, (xs[t + 1] - x_p[t])[..., None])[..., 0]
            Ps[t] = P_f[t] + C @ (Ps[t + 1] - P_p[t]) @ np.swapaxes(C, -1, -2)
            Ps[t] = 0.5 * (Ps[t] + np.swapaxes(Ps[t], -1, -2))
    else:
        # One backward chain per step t, from its horizon e_t = min(t + L, T) down to t,
        # all chains advanced together: after j passes chain t sits at e_t - j.
        steps = np.arange(T + 1)
        end = np.minimum(steps + lag, T)
        xs = x_f[end].copy()
        Ps = P_f[end].copy()
        for j in range(1, min(lag, T) + 1):
            active = np.flatnonzero(end - j >= steps)
            s = end[active] - j  # the position the chain moves to
            C = gains[s]
            xs[active] = x_f[s] + np.matmul(C, (xs[active] - x_p[s])[..., None])[..., 0]
            Pn = P_f[s] + C @ (Ps[active] - P_p[s]) @ np.swapaxes(C, -1, -2)
            Ps[active] = 0.5 * (Pn + np.swapaxes(Pn, -1, -2))
    return SmoothedRun(x=xs[1:], P=Ps[1:], x_initial=xs[0], P_initial=Ps[0], lag=lag)
