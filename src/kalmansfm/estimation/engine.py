"""The engine under :class:`~kalmansfm.estimation.kalman.KalmanFilter`: storage forms, lazy priors, buffers (internal).

:class:`FilterEngine` keeps N filters' states and covariances between calls in the
cheapest exact form for the model, with the track index last (structure of arrays):

* **decoupled constant-velocity** (:mod:`._decoupled`): X (4, N) and covariance blocks
  C (B, 3) shared or (B, 3, N), B = 1 while the x and y blocks agree, else 2;
* **general**: x (n, N) and P (n, n) shared or (n, n, N).

A ``predict`` is only recorded; the next ``update`` predicts and updates in one pass
over memory (one compiled kernel, or its NumPy twin for small problems: see
:func:`kernels_for`).  The step's prior is then not written: it is a :class:`_Prior`,
recomputed with the same arithmetic from the previous posterior when someone reads it
(``x_prior``, ``P_prior``, gating, the update's statistics).  A step writes its posterior
into arrays other than its input, taken from a :class:`~._buffers.BufferPool` that hands
an array out again only when nothing outside the filter holds it.

The model (F, Q, H, R) stays with the filter and is passed to every call, so that a
model matrix assigned between steps is used from the next one on.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from ..errors import InvalidInputError, SingularCovarianceError
from . import _decoupled, _kernels, _numpy_kernels
from ._buffers import BufferPool
from ._linalg import (LOG_2PI, cholesky_checked, gain_and_posterior, not_positive_definite, solve_lower,
                      solve_upper_transposed, symmetrize)

__all__ = ["COMPILED_MIN_TRACKS", "FilterEngine", "kernels_for"]

#: Fewer tracks than this run the NumPy twins of the compiled kernels (:mod:`._numpy_kernels`,
#: the same numbers bit for bit).  A kernel is compiled the first time it runs on a machine
#: (1–6 s, then cached); below this size its twin costs at most about 0.05 ms (constant-velocity
#: form) or 0.7 ms (general form) more per step (docs/performance.md), so a run of a few
#: thousand steps costs less than the compilation would.
COMPILED_MIN_TRACKS = 1024


def kernels_for(N: int):
    """The kernels that run a step of N tracks: the compiled ones, or their NumPy twins below
    :data:`COMPILED_MIN_TRACKS` (same functions, same outputs, bit for bit)."""
    return _kernels if N >= COMPILED_MIN_TRACKS else _numpy_kernels


class _MaskedUpdate:
    """Statistics of one compiled update of the general form, computed from the prior on access.

    ``prior`` is the step's :class:`_Prior` (internal layout: x (n, N), P (n, n, N) or
    shared (n, n)); ``Y`` (m, N) the innovations the kernel wrote (NaN where not
    measured).  Missing components are masked as in the kernel: their rows and
    columns of S become the identity's, so one factorisation serves every NaN pattern.
    """

    def __init__(self, prior: _Prior, Y: np.ndarray, H: np.ndarray, R: np.ndarray) -> None:
        self._prior = prior
        self._Y = Y
        self._H = H
        self._R = R
        self._stats: dict[str, np.ndarray] | None = None

    @property
    def y(self) -> np.ndarray:
        return self._Y.T

    @property
    def measured(self) -> np.ndarray:
        return ~np.isnan(self._Y.T)

    def _compute(self) -> dict[str, np.ndarray]:
        if self._stats is None:
            P = self._prior.get()[1]
            if P.ndim == 3:
                P = np.moveaxis(P, -1, 0)
            self._stats = _masked_statistics(P, self.y, self._H, self._R)
        return self._stats

    S = property(lambda self: self._compute()["S"])
    K = property(lambda self: self._compute()["K"])
    nis = property(lambda self: self._compute()["nis"])
    log_likelihood = property(lambda self: self._compute()["log_likelihood"])


def _masked_statistics(P: np.ndarray, y: np.ndarray, H: np.ndarray, R: np.ndarray) -> dict[str, np.ndarray]:
    """S, K, NIS and log-likelihood of innovations y (N, m) (NaN = not measured) under prior covariances P.

    The NumPy form of the compiled update's masking: S' is S with the unmeasured rows
    and columns replaced by the identity's, and (P Hᵀ)' has their columns set to 0, so
    K = (P Hᵀ)' S'⁻¹ is the gain of the measured components alone (0 for the others),
    yᵀ S'⁻¹ y over the measured components is the NIS, and log det S' = log det S of the
    measured block.  S itself is returned for every filter, measured or not.
    """
    N, m = y.shape
    seen = ~np.isnan(y)
    HPHt = H @ P @ np.swapaxes(H, -1, -2)
    S = np.broadcast_to(symmetrize(HPHt + R), (N, m, m))
    both = seen[:, :, None] & seen[:, None, :]
    L = cholesky_checked(np.where(both, S, np.eye(m, dtype=S.dtype)), "the innovation covariance S = H P Hᵀ + R")
    PHt = (P @ np.swapaxes(H, -1, -2)) * seen[:, None, :]
    K = np.swapaxes(solve_upper_transposed(L, solve_lower(L, np.swapaxes(PHt, -1, -2))), -1, -2)
    w = solve_lower(L, np.where(seen, y, 0.0)[..., None])[..., 0]
    nis = np.sum(w * w, axis=-1)
    log_det = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    count = seen.sum(axis=1)
    ll = -0.5 * (nis + log_det + count * LOG_2PI)
    nothing = count == 0
    return {"S": S, "K": K, "nis": np.where(nothing, np.nan, nis).astype(y.dtype),
            "log_likelihood": np.where(nothing, np.nan, ll).astype(y.dtype)}


class _Prior:
    """A step's prior in the filter's internal layout, computed on first use from the previous posterior.

    The compiled step predicts and updates in one pass without writing the prior;
    ``compute`` (a function of the previous posterior and the transition, holding
    no reference to the filter) recomputes it with the same arithmetic when asked.
    """

    __slots__ = ("_compute", "_value")

    def __init__(self, value: tuple[np.ndarray, np.ndarray] | None = None, compute=None) -> None:
        self._value = value
        self._compute = compute

    def get(self) -> tuple[np.ndarray, np.ndarray]:
        if self._value is None:
            self._value = self._compute()
            self._compute = None
        return self._value

    def arrays(self) -> tuple[np.ndarray, ...]:
        return self._value if self._value is not None else ()


def _cv_prior(X, C, dt, q, u, take) -> tuple[np.ndarray, np.ndarray]:
    """The decoupled prior (X⁻, C⁻) of the posterior (X, C); C (B, 3) shared or (B, 3, N)."""
    Xp = take(X.shape, X.dtype)
    Cp = take(C.shape, C.dtype) if C.ndim == 3 else np.empty_like(C)
    kernels = kernels_for(X.shape[1])
    with kernels.threads_for(X.shape[1]):
        kernels.cv_predict(X, C if C.ndim == 3 else C[:, :, None], dt, q, u, Xp, Cp if C.ndim == 3 else Cp[:, :, None])
    return Xp, Cp


def _dense_prior(x, P, F, Q, u, take) -> tuple[np.ndarray, np.ndarray]:
    """The general form's prior (x⁻, P⁻) of the posterior (x (n, N), P (n, n) shared or (n, n, N))."""
    xp = take(x.shape, x.dtype)
    u = _no_input(x) if u is None else u
    kernels = kernels_for(x.shape[1])
    with kernels.threads_for(x.shape[1]):
        if P.ndim == 2 and F.ndim == 2 and Q.ndim == 2:
            kernels.dense_predict_states(x, _plain(F), u, xp)
            # the shared covariance's prior as kalman_predict computes it
            return xp, symmetrize(F @ P @ F.T + Q)
        if P.ndim == 2:
            P = _per_track(P, x.shape[1])
        Pp = take(P.shape, P.dtype)
        kernels.dense_predict(x, P, _stacked(F), _stacked(Q), u, xp, Pp)
    return xp, Pp


def _stacked(M: np.ndarray) -> np.ndarray:
    """A model matrix as the dense kernels take it: (1, r, c) when shared, (N, r, c) as it is."""
    return _plain(M if M.ndim == 3 else M[None])


def _plain(a: np.ndarray) -> np.ndarray:
    """``a`` as a C-contiguous writable array (copied only if it is not): one compiled kernel per dtype."""
    return a if a.flags.c_contiguous and a.flags.writeable else np.array(a, order="C")


def _no_input(x: np.ndarray) -> np.ndarray:
    """The dense kernels' "no known input u": an (n, 0) array."""
    return np.zeros((x.shape[0], 0), dtype=x.dtype)


def _per_track(P: np.ndarray, N: int) -> np.ndarray:
    """A shared (n, n) covariance as (n, n, N) structure-of-arrays copies."""
    return np.ascontiguousarray(np.broadcast_to(P[:, :, None], (*P.shape, N)))


def _as_complex(z: np.ndarray) -> np.ndarray:
    """(N, 2) positions as (N,) complex x + i y, a view (the compiled loop reads them as one stream)."""
    z = _plain(z)
    return z.view(np.complex128 if z.dtype == np.float64 else np.complex64)[:, 0]


def _structure_of_arrays(P: np.ndarray) -> np.ndarray:
    """(N, n, n) → (n, n, N) (a new array); a shared (n, n) is copied as it is."""
    return np.ascontiguousarray(np.moveaxis(P, 0, -1)) if P.ndim == 3 else P.copy()


def _infinite_measurement() -> InvalidInputError:
    return InvalidInputError("z must not contain infinity (use NaN for a missing measurement)")


def decoupled_motion(F: np.ndarray, Q: np.ndarray) -> tuple[float, np.ndarray] | None:
    """(dt, q (2, 3)) when F is the constant-velocity transition and Q does not couple x and y."""
    if F.ndim != 2 or Q.ndim != 2:
        return None
    dt = _decoupled.cv_transition_dt(F)
    q = None if dt is None else _decoupled.axis_blocks(Q)
    return None if q is None else (dt, q)


def decoupled_measurement(H: np.ndarray, R: np.ndarray) -> np.ndarray | None:
    """r (2,) or (2, N) when H measures the position and R is diagonal, else None."""
    if H.ndim != 2 or not _decoupled.is_position_measurement(H):
        return None
    r = _decoupled.diagonal_noise(R)
    return None if r is None else (r if r.ndim == 1 else np.ascontiguousarray(r.T))


class FilterEngine:
    """N filters' states and covariances in the cheapest exact storage form (module docs).

    Parameters
    ----------
    x : (N, n) validated initial states (the engine keeps its own copy).
    P : (n, n) shared or (N, n, n) validated initial covariances.
    model : (F, Q, H, R) the filter's current model matrices.
    joseph : Joseph-form covariance update, else P = (I - K H) P.
    """

    def __init__(self, x: np.ndarray, P: np.ndarray, model: tuple[np.ndarray, ...], *, joseph: bool) -> None:
        self.n_filters, self.dim_x = x.shape
        self.dtype = x.dtype
        self.joseph = joseph
        self._fast: tuple[np.ndarray, np.ndarray] | None = None
        self._dense: tuple[np.ndarray, np.ndarray] | None = None
        self._pending: tuple[str, tuple] | None = None  # a predict recorded, not applied yet
        self._prior: _Prior | None = None  # the prior of the last predict (or the state before the last update)
        self._dense_cache: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        #: the statistics of the last update (y, S, K, nis, log_likelihood), or None before the first
        self.last: object | None = None
        self._last_buffers: tuple[np.ndarray, ...] = ()
        self._pool = BufferPool()
        self.set_state(x, P, model, initial=True)

    # -- the two internal forms ------------------------------------------------
    @property
    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """The current (states, covariances) in the internal layout."""
        return self._fast if self._fast is not None else self._dense

    @property
    def decoupled(self) -> bool:
        """True while the filter runs in the decoupled constant-velocity form."""
        return self._fast is not None

    @property
    def shared_covariance(self) -> bool:
        """True while all filters have one covariance (stored once)."""
        return self.state[1].ndim == 2

    def set_state(self, x: np.ndarray, P: np.ndarray, model: tuple[np.ndarray, ...], *, initial: bool = False) -> None:
        """Store (x, P) in the decoupled form when the model allows it (and we are in it), else densely."""
        F, Q, H, R = model
        self._dense_cache = {}
        fits = decoupled_motion(F, Q) is not None and decoupled_measurement(H, R) is not None
        blocks = _decoupled.axis_blocks(P) if fits and (initial or self._fast is not None) else None
        if blocks is not None:
            self._fast = (np.ascontiguousarray(x.T), _decoupled.compact_covariance(blocks))
        else:
            self._to_dense()
            self._dense = (np.ascontiguousarray(x.T), _structure_of_arrays(P))
        if initial:
            self._prior = _Prior(self.state)

    def set_states(self, x: np.ndarray) -> None:
        """Replace the states (N, n), keeping the covariances."""
        self.settle()
        state = (np.ascontiguousarray(x.T), self.state[1])
        if self._fast is not None:
            self._fast = state
        else:
            self._dense = state

    def _to_dense(self) -> None:
        """Leave the decoupled form for good (a step that couples x and y, or a general H)."""
        if self._fast is None:
            return
        self.settle()
        expand = lambda C: _structure_of_arrays(_decoupled.dense_covariance(C, self.n_filters))  # noqa: E731
        X, C = self._fast
        self._dense = (X, expand(C))
        Xp, Cp = self._prior.get()
        self._prior = _Prior((Xp, expand(Cp)))
        self._fast = None
        self._dense_cache = {}

    def settle(self) -> None:
        """Apply a recorded predict (someone reads the prior, or a second predict comes)."""
        if self._pending is None:
            return
        kind, transition = self._pending
        self._pending = None
        prior = (_cv_prior if kind == "cv" else _dense_prior)(*self.state, *transition, self._pool.take)
        self._commit(prior, _Prior(prior))

    def _commit(self, state: tuple[np.ndarray, np.ndarray], prior: _Prior, last: object | None = None,
                buffers: tuple[np.ndarray, ...] = ()) -> None:
        """Make ``state`` current; the arrays no longer referenced directly go back to the pool."""
        released = (*self.state, *self._prior.arrays(), *(self._last_buffers if last is not None else ()))
        if self._fast is not None:
            self._fast = state
        else:
            self._dense = state
        self._prior = prior
        if last is not None:
            self.last = last
            self._last_buffers = buffers
        self._dense_cache = {}
        self._pool.release(*released)

    # -- what the filter shows ------------------------------------------------
    def _public_P(self, key: str, state: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """(N, n, n) view, or the shared (n, n), of a state's covariance (assembled once from decoupled
        blocks, then cached)."""
        C = state[1]
        if self._fast is None:
            return np.moveaxis(C, -1, 0) if C.ndim == 3 else C
        cached = self._dense_cache.get(key)
        if cached is None or cached[0] is not C:
            P = _decoupled.dense_covariance(C, self.n_filters)
            P.flags.writeable = False
            cached = self._dense_cache[key] = (C, P)
        return cached[1]

    def x(self) -> np.ndarray:
        """Current states (N, n), a view."""
        self.settle()
        return self.state[0].T

    def P(self) -> np.ndarray:
        """Current covariances: (N, n, n) view, or the shared (n, n)."""
        self.settle()
        return self._public_P("P", self.state)

    def x_prior(self) -> np.ndarray:
        """States after the last predict (N, n)."""
        self.settle()
        return self._prior.get()[0].T

    def P_prior(self) -> np.ndarray:
        """Covariances after the last predict: (N, n, n), or the shared (n, n)."""
        self.settle()
        return self._public_P("P_prior", self._prior.get())

    # -- the two steps -----------------------------------------------------------
    def predict(self, F: np.ndarray, Q: np.ndarray, offset: np.ndarray | None) -> None:
        """Record x⁻ = F x + offset, P⁻ = F P Fᵀ + Q; offset (n, N) or None (validated by the caller)."""
        self.settle()  # a predict not applied yet (two predicts in a row)
        self._dense_cache = {}
        if self._fast is not None:
            parts = decoupled_motion(F, Q)
            if parts is not None:
                dt, q = parts
                X, C = self._fast
                if C.shape[0] == 1 and not np.array_equal(q[0], q[1]):
                    self._fast = (X, np.concatenate([C, C]))  # x and y blocks part
                self._pending = ("cv", (self.dtype.type(dt), np.ascontiguousarray(q), offset))
                return
            self._to_dense()
        self._pending = ("dense", (F, Q, offset))

    def update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray, model: tuple[np.ndarray, ...]) -> None:
        """Condition every filter on z (N, m), NaN = not measured; H, R of this step (validated)."""
        kernels = kernels_for(self.n_filters)
        if self._fast is not None:
            r = decoupled_measurement(H, R)
            if r is not None:
                with kernels.threads_for(self.n_filters):
                    self._update_decoupled(kernels, z, r)
                return
            self._to_dense()
        with kernels.threads_for(self.n_filters):
            self._update_dense(kernels, z, H, R, model)

    def _update_decoupled(self, kernels, z: np.ndarray, r: np.ndarray) -> None:
        """One pass: the recorded predict (if any) and the update, decoupled form."""
        N, dtype, take = self.n_filters, self.dtype, self._pool.take
        X, C = self._fast
        if self._pending is not None:
            dt, q, u = self._pending[1]
        else:  # update alone: the identity transition, exactly (x + 0 v = x, p + 0 = p)
            dt, q, u = dtype.type(0.0), np.zeros((2, 3), dtype=dtype), None
        zc = _as_complex(z)
        if C.shape[0] == 1 and not np.array_equal(r[0], r[1]):
            C = np.concatenate([C, C])  # the two axes' noises differ: their blocks part
        if C.ndim == 2 and r.ndim == 1:
            C_prior, C_post, gains = kernels.cv_shared_blocks(C, dt, q, r, self.joseph)
            if not np.all(np.isfinite(C_post)):
                raise SingularCovarianceError("the innovation covariance S = H P Hᵀ + R is not positive definite")
            Xo, Yo = take((4, N), dtype), take((2, N), dtype)
            n_infinite, n_missing = kernels.cv_step_shared(X, zc, dt, gains, u, Xo, Yo)
            if n_infinite:
                raise _infinite_measurement()
            if n_missing == 0:
                self._finish_decoupled((Xo, C_post), Yo, X, C, dt, q, u, r)
                return
        if C.ndim == 2:
            C = _per_track(C, N)  # not everyone measured, or per-filter noise: the covariances part for good
        r2 = r[:, None] if r.ndim == 1 else r
        Xo, Co, Yo = take((4, N), dtype), take((C.shape[0], 3, N), dtype), take((2, N), dtype)
        n_infinite, n_partial, n_singular = kernels.cv_step(X, C, zc, dt, q, r2, u, self.joseph, Xo, Co, Yo)
        if n_partial and not n_infinite:
            # a row measured x or y alone: the two axes' histories part, two blocks from now on
            C, Co = np.concatenate([C, C]), take((2, 3, N), dtype)
            n_infinite, n_partial, n_singular = kernels.cv_step(X, C, zc, dt, q, r2, u, self.joseph, Xo, Co, Yo)
        if n_infinite:
            raise _infinite_measurement()
        if n_singular:
            raise SingularCovarianceError("the innovation covariance S = H P Hᵀ + R is not positive definite")
        self._finish_decoupled((Xo, Co), Yo, X, C, dt, q, u, r)

    def _finish_decoupled(self, state, Yo, X, C, dt, q, u, r) -> None:
        if self._pending is not None:
            prior = _Prior(compute=partial(_cv_prior, X, C, dt, q, u, self._pool.take))
            self._pending = None
        else:
            prior = _Prior((X, C))
        stats = _decoupled.DecoupledUpdate(lambda: prior.get()[1], Yo, r, None, self.n_filters)
        self._commit(state, prior, stats, (Yo,))

    def _update_dense(self, kernels, z: np.ndarray, H: np.ndarray, R: np.ndarray, model: tuple[np.ndarray, ...]) -> None:
        """One pass: the recorded predict (if any) and the update, general form."""
        N, n, m, dtype, take = self.n_filters, self.dim_x, z.shape[1], self.dtype, self._pool.take
        x, P = self._dense
        predict = self._pending is not None
        F, Q, u = self._pending[1] if predict else (model[0], model[1], None)
        z = _plain(z)
        u_in = _no_input(x) if u is None else u
        if P.ndim == 2 and H.ndim == 2 and R.ndim == 2 and F.ndim == 2 and Q.ndim == 2:
            # shared covariance: one n×n update (the NumPy reference), the states in one pass
            P_prior = symmetrize(F @ P @ F.T + Q) if predict else P
            _, P_post, _, _, gain, _, _ = gain_and_posterior(np.zeros((1, n), dtype), P_prior, np.zeros((1, m), dtype),
                                                             H, R, self.joseph)
            xo, yo = take((n, N), dtype), take((m, N), dtype)
            n_infinite, n_missing = kernels.dense_step_shared(x, z, _plain(F), u_in, _plain(H), _plain(gain),
                                                              predict, xo, yo)
            if n_infinite:
                raise _infinite_measurement()
            if n_missing == 0:
                self._finish_dense((xo, P_post), yo, x, P, F, Q, u, H, R)
                return
        if P.ndim == 2:
            P = _per_track(P, N)  # the covariances part for good
        xo, Po, yo = take((n, N), dtype), take((n, n, N), dtype), take((m, N), dtype)
        n_infinite, n_singular = kernels.dense_step(x, P, z, _stacked(F), _stacked(Q), _stacked(H), _stacked(R), u_in,
                                                    predict, self.joseph, xo, Po, yo)
        if n_infinite:
            raise _infinite_measurement()
        if n_singular:
            raise not_positive_definite("the innovation covariance S = H P Hᵀ + R")
        self._finish_dense((xo, Po), yo, x, P, F, Q, u, H, R)

    def _finish_dense(self, state, yo, x, P, F, Q, u, H, R) -> None:
        if self._pending is not None:
            prior = _Prior(compute=partial(_dense_prior, x, P, F, Q, u, self._pool.take))
            self._pending = None
        else:
            prior = _Prior((x, P))
        self._commit(state, prior, _MaskedUpdate(prior, yo, H, R), (yo,))

    def prior_for_statistics(self) -> tuple[np.ndarray, np.ndarray]:
        """(x⁻ (N, n), P⁻ (N, n, n) or the shared (n, n)) for statistics of candidates under the prior."""
        self.settle()
        if self._fast is None and self._prior.get()[1].ndim == 2:
            return self.x_prior(), self._prior.get()[1]
        return self.x_prior(), np.broadcast_to(self.P_prior(), (self.n_filters, self.dim_x, self.dim_x))
