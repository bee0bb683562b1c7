"""Every compiled kernel equals its NumPy reference to 1e-12 relative in float64 (hypothesis).

Relative means: the largest difference over a track's state (covariance) divided by
the largest entry of that track's reference state (covariance) — or of its prior, when the
update cancels the state to near zero (a one-state track whose posterior is 1e-3 of its
prior, say): entries that cancel cannot be compared one by one.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from kalmansfm.estimation import _kernels, _numpy_kernels
from kalmansfm.estimation.kalman import kalman_predict, kalman_update
from reference import decoupled as reference

TOL = 1e-12


def _relative(a: np.ndarray, b: np.ndarray, axes: tuple[int, ...], prior: np.ndarray | None = None) -> float:
    """max over tracks of max |a - b| / max(|b|, |prior|) within a track (axes = the per-track axes)."""
    scale = np.abs(b).max(axis=axes)
    if prior is not None:
        scale = np.maximum(scale, np.abs(np.broadcast_to(prior, b.shape)).max(axis=axes))
    scale = np.maximum(scale, np.finfo(float).tiny)
    return float((np.abs(a - b).max(axis=axes) / scale).max())


def _blocks(rng: np.random.Generator, B: int, N: int, scale: float) -> np.ndarray:
    """Valid 2×2 covariance blocks (p00, p01, p11), shape (B, 3, N)."""
    C = np.empty((B, 3, N))
    C[:, 0] = scale * rng.uniform(0.1, 100.0, (B, N))
    C[:, 2] = scale * rng.uniform(0.1, 30.0, (B, N))
    C[:, 1] = rng.uniform(-0.95, 0.95, (B, N)) * np.sqrt(C[:, 0] * C[:, 2])
    return C


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    N=st.integers(1, 300),
    split=st.booleans(),
    per_track_r=st.booleans(),
    with_u=st.booleans(),
    joseph=st.booleans(),
    p_row=st.sampled_from([0.0, 0.1, 0.5, 1.0]),
    p_component=st.sampled_from([0.0, 0.2]),
    scale=st.sampled_from([1e-6, 1.0, 1e6]),
    dt=st.sampled_from([0.0, 0.04, 1.0, 3.0]),
)
def test_decoupled_step_equals_the_numpy_predict_then_update(seed, N, split, per_track_r, with_u, joseph, p_row,
                                                             p_component, scale, dt):
    rng = np.random.default_rng(seed)
    B = 2 if split else 1
    X = rng.normal(scale=30 * np.sqrt(scale), size=(4, N))
    C = _blocks(rng, B, N, scale)
    z = rng.normal(scale=30 * np.sqrt(scale), size=(N, 2))
    z[rng.random(N) < p_row] = np.nan
    if split:  # rows with one component only need two blocks
        z[rng.random((N, 2)) < p_component] = np.nan
    q = scale * np.array([[16.0, 1.5, 4.0], [9.0, -0.5, 1.0]]) if split else scale * np.array([[16.0, 1.5, 4.0]] * 2)
    if per_track_r:
        r = scale * rng.uniform(1.0, 9.0, (2, N))
        if not split:
            r[1] = r[0]
    else:
        r = scale * (np.array([4.0, 2.0]) if split else np.array([4.0, 4.0]))
    u = rng.normal(size=(4, N)) if with_u else None

    Xo, Co, Yo = np.empty((4, N)), np.empty((B, 3, N)), np.empty((2, N))
    counts = _kernels.cv_step(X, C, z.view(np.complex128)[:, 0], dt, q, r if per_track_r else r[:, None], u,
                              joseph, Xo, Co, Yo)
    assert counts == (0, 0, 0)

    Xp, Cp = reference.predict(X, C, dt, q[:B], u)
    Xr, Cr, stats = reference.update(Xp, Cp, z, r, joseph, np.isnan(z))
    assert _relative(Xo, Xr, (0,)) <= TOL
    assert _relative(Co, Cr, (0, 1)) <= TOL
    np.testing.assert_array_equal(np.isnan(Yo.T), np.isnan(stats.y))
    assert _relative(np.nan_to_num(Yo.T), np.nan_to_num(stats.y), (1,)) <= TOL

    # the prior alone
    Xq, Cq = np.empty_like(X), np.empty_like(C)
    _kernels.cv_predict(X, C, dt, q, u, Xq, Cq)
    assert _relative(Xq, Xp, (0,)) <= TOL and _relative(Cq, Cp, (0, 1)) <= TOL


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), N=st.integers(1, 200), joseph=st.booleans(), dt=st.sampled_from([0.0, 0.5, 1.0]))
def test_shared_covariance_kernels_equal_the_numpy_shared_update(seed, N, joseph, dt):
    rng = np.random.default_rng(seed)
    X = rng.normal(scale=30, size=(4, N))
    C = _blocks(rng, 1, 1, 1.0)[:, :, 0]
    z = rng.normal(scale=30, size=(N, 2))
    q = np.array([[16.0, 1.5, 4.0]] * 2)
    r = np.array([4.0, 4.0])
    C_prior, C_post, gains = _kernels.cv_shared_blocks(C, dt, q, r, joseph)
    Xo, Yo = np.empty((4, N)), np.empty((2, N))
    assert _kernels.cv_step_shared(X, z.view(np.complex128)[:, 0], dt, gains, None, Xo, Yo) == (0, 0)
    Xp, Cp = reference.predict(X, C, dt, q[:1], None)
    Xr, Cr, _ = reference.update(Xp, Cp, z, r, joseph, None)
    assert _relative(Xo, Xr, (0,)) <= TOL
    assert _relative(C_prior, Cp, (0, 1)) <= TOL and _relative(C_post, Cr, (0, 1)) <= TOL


def _spd(rng: np.random.Generator, n: int, size: tuple[int, ...] = ()) -> np.ndarray:
    """Positive definite matrices with eigenvalues in [0.5, 5] (condition number <= 10)."""
    A = rng.normal(size=(*size, n, n))
    Qm, _ = np.linalg.qr(A)
    eig = rng.uniform(0.5, 5.0, size=(*size, n))
    return (Qm * eig[..., None, :]) @ np.swapaxes(Qm, -1, -2)


# the dense kernels' cases (N, the tracks, is given by each test)
DENSE_CASES = dict(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 5),
    m=st.integers(1, 3),
    predict=st.booleans(),
    joseph=st.booleans(),
    per_track=st.sampled_from(["", "F", "Q", "H", "R", "FQHR"]),
    with_u=st.booleans(),
    p_row=st.sampled_from([0.0, 0.2, 1.0]),
    p_component=st.sampled_from([0.0, 0.3]),
)


@settings(max_examples=80, deadline=None)
@given(N=st.integers(1, 300), **DENSE_CASES)
# a one-state track whose update cancels most of its prior (found by hypothesis)
@example(seed=67824, N=271, n=1, m=3, predict=False, joseph=False, per_track="FQHR", with_u=False, p_row=0.0,
         p_component=0.0)
def test_dense_step_equals_kalman_predict_then_kalman_update(seed, N, n, m, predict, joseph, per_track, with_u, p_row,
                                                             p_component):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(N, n))
    P = _spd(rng, n, (N,))
    F = np.eye(n) + 0.2 * rng.normal(size=(N, n, n) if "F" in per_track else (n, n))
    Q = 0.3 * _spd(rng, n, (N,) if "Q" in per_track else ())
    H = rng.normal(size=(N, m, n) if "H" in per_track else (m, n)) / np.sqrt(n)
    R = _spd(rng, m, (N,) if "R" in per_track else ())
    u = rng.normal(size=(N, n)) if with_u and predict else None
    z = rng.normal(size=(N, m))
    z[rng.random(N) < p_row] = np.nan
    z[rng.random((N, m)) < p_component] = np.nan

    stacked = [M if M.ndim == 3 else M[None] for M in (F, Q, H, R)]
    u_soa = np.zeros((n, 0)) if u is None else np.ascontiguousarray(u.T)
    xo, Po, yo = np.empty((n, N)), np.empty((n, n, N)), np.empty((m, N))
    counts = _kernels.dense_step(np.ascontiguousarray(x.T), np.ascontiguousarray(np.moveaxis(P, 0, -1)), z, *stacked,
                                 u_soa, predict, joseph, xo, Po, yo)
    assert counts == (0, 0)

    x_prior, P_prior = kalman_predict(x, P, F, Q, u) if predict else (x, P)
    ref = kalman_update(x_prior, P_prior, z, H, R, joseph=joseph)
    assert _relative(xo.T, ref.x, (1,), x_prior) <= TOL
    assert _relative(np.moveaxis(Po, -1, 0), np.broadcast_to(ref.P, (N, n, n)), (1, 2), P_prior) <= TOL
    np.testing.assert_array_equal(np.isnan(yo.T), np.isnan(ref.y))

    if predict:
        xq, Pq = np.empty((n, N)), np.empty((n, n, N))
        _kernels.dense_predict(np.ascontiguousarray(x.T), np.ascontiguousarray(np.moveaxis(P, 0, -1)), stacked[0],
                               stacked[1], u_soa, xq, Pq)
        assert _relative(xq.T, x_prior, (1,)) <= TOL
        assert _relative(np.moveaxis(Pq, -1, 0), P_prior, (1, 2)) <= TOL


# -- the NumPy twins (the small-problem path) against the compiled kernels: bit for bit -----------

def _same(a: tuple, b: tuple) -> None:
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


DECOUPLED_CASES = dict(
    seed=st.integers(0, 2**32 - 1),
    N=st.integers(1, 200),
    split=st.booleans(),
    per_track_r=st.booleans(),
    with_u=st.booleans(),
    joseph=st.booleans(),
    p_row=st.sampled_from([0.0, 0.1, 1.0]),
    p_component=st.sampled_from([0.0, 0.2]),
    dt=st.sampled_from([0.0, 0.04, 1.0]),
)


@settings(max_examples=60, deadline=None)
@given(**DECOUPLED_CASES)
def test_the_numpy_twins_of_the_decoupled_kernels_are_bit_identical(seed, N, split, per_track_r, with_u, joseph, p_row,
                                                                    p_component, dt):
    _decoupled_twin_case(seed, N, split, per_track_r, with_u, joseph, p_row, p_component, dt, np.float64)


@pytest.mark.slow  # compiles the float32 variants of the decoupled kernels; the float64 test above is its fast sibling
@settings(max_examples=40, deadline=None)
@given(**DECOUPLED_CASES)
def test_the_numpy_twins_of_the_decoupled_kernels_are_bit_identical_in_float32(seed, N, split, per_track_r, with_u,
                                                                               joseph, p_row, p_component, dt):
    _decoupled_twin_case(seed, N, split, per_track_r, with_u, joseph, p_row, p_component, dt, np.float32)


def _decoupled_twin_case(seed, N, split, per_track_r, with_u, joseph, p_row, p_component, dt, dtype):
    cdtype = np.complex64 if dtype == np.float32 else np.complex128
    rng = np.random.default_rng(seed)
    B = 2 if split else 1
    X = rng.normal(scale=30, size=(4, N)).astype(dtype)
    C = _blocks(rng, B, N, 1.0).astype(dtype)
    z = rng.normal(scale=30, size=(N, 2)).astype(dtype)
    z[rng.random(N) < p_row] = np.nan
    z[rng.random((N, 2)) < p_component] = np.nan  # with one block: partial rows, counted
    q = np.array([[16.0, 1.5, 4.0], [9.0, -0.5, 1.0] if split else [16.0, 1.5, 4.0]], dtype)
    r = rng.uniform(1.0, 9.0, (2, N) if per_track_r else (2, 1)).astype(dtype)
    u = rng.normal(size=(4, N)).astype(dtype) if with_u else None
    dt = dtype(dt)
    zc = z.view(cdtype)[:, 0]

    def step(kernels):
        out = np.empty((4, N), dtype), np.empty((B, 3, N), dtype), np.empty((2, N), dtype)
        counts = kernels.cv_step(X, C, zc, dt, q, r, u, joseph, *out)
        prior = np.empty((4, N), dtype), np.empty((B, 3, N), dtype)
        kernels.cv_predict(X, C, dt, q, u, *prior)
        return counts, (*out, *prior)

    counts, arrays = step(_kernels)
    twin_counts, twin_arrays = step(_numpy_kernels)
    assert counts == twin_counts and all(type(c) is int for c in twin_counts)
    _same(arrays, twin_arrays)

    if not per_track_r and not split:
        shared = _kernels.cv_shared_blocks(C[:, :, 0], dt, q, r[:, 0], joseph)
        _same(shared, _numpy_kernels.cv_shared_blocks(C[:, :, 0], dt, q, r[:, 0], joseph))
        outputs = []
        for kernels in (_kernels, _numpy_kernels):
            Xo, Yo = np.empty((4, N), dtype), np.empty((2, N), dtype)
            outputs.append((kernels.cv_step_shared(X, zc, dt, shared[2], u, Xo, Yo), Xo, Yo))
        assert outputs[0][0] == outputs[1][0]
        _same(outputs[0][1:], outputs[1][1:])


@settings(max_examples=60, deadline=None)
@given(N=st.integers(1, 200), **DENSE_CASES)
def test_the_numpy_twins_of_the_dense_kernels_are_bit_identical(seed, N, n, m, predict, joseph, per_track, with_u,
                                                                p_row, p_component):
    rng = np.random.default_rng(seed)
    x = np.ascontiguousarray(rng.normal(size=(n, N)))
    P = np.ascontiguousarray(np.moveaxis(_spd(rng, n, (N,)), 0, -1))
    F = np.eye(n) + 0.2 * rng.normal(size=(N, n, n) if "F" in per_track else (1, n, n))
    Q = 0.3 * _spd(rng, n, (N,) if "Q" in per_track else (1,))
    H = rng.normal(size=(N, m, n) if "H" in per_track else (1, m, n)) / np.sqrt(n)
    R = _spd(rng, m, (N,) if "R" in per_track else (1,))
    u = rng.normal(size=(n, N)) if with_u else np.zeros((n, 0))
    z = rng.normal(size=(N, m))
    z[rng.random(N) < p_row] = np.nan
    z[rng.random((N, m)) < p_component] = np.nan
    z[rng.random(N) < 0.02] = np.inf  # counted, as the kernel counts them

    def run(kernels):
        out = np.empty((n, N)), np.empty((n, n, N)), np.empty((m, N))
        counts = kernels.dense_step(x, P, z, F, Q, H, R, u, predict, joseph, *out)
        prior = np.empty((n, N)), np.empty((n, n, N))
        kernels.dense_predict(x, P, F, Q, u, *prior)
        shared = np.empty((n, N)), np.empty((m, N))
        gain = rng_gain.normal(size=(n, m))
        counts_shared = kernels.dense_step_shared(x, z, F[0], u, H[0], gain, predict, *shared)
        states = np.empty((n, N))
        kernels.dense_predict_states(x, F[0], u, states)
        return (counts, counts_shared), (*out, *prior, *shared, states)

    rng_gain = np.random.default_rng(seed)
    counts, arrays = run(_kernels)
    rng_gain = np.random.default_rng(seed)
    twin_counts, twin_arrays = run(_numpy_kernels)
    assert counts == twin_counts
    _same(arrays, twin_arrays)


@pytest.mark.slow  # compiles the float32 dense kernel; the float64 property test above is its fast sibling
def test_the_numpy_twin_of_the_dense_step_is_bit_identical_in_float32():
    rng = np.random.default_rng(11)
    N, n, m = 150, 4, 2
    x = np.ascontiguousarray(rng.normal(size=(n, N)), np.float32)
    P = np.ascontiguousarray(np.moveaxis(_spd(rng, n, (N,)), 0, -1), np.float32)
    F = (np.eye(n) + 0.2 * rng.normal(size=(1, n, n))).astype(np.float32)
    Q = (0.3 * _spd(rng, n, (1,))).astype(np.float32)
    H = (rng.normal(size=(1, m, n)) / 2).astype(np.float32)
    R = _spd(rng, m, (N,)).astype(np.float32)
    z = rng.normal(size=(N, m)).astype(np.float32)
    z[rng.random((N, m)) < 0.2] = np.nan
    results = []
    for kernels in (_kernels, _numpy_kernels):
        out = np.empty((n, N), np.float32), np.empty((n, n, N), np.float32), np.empty((m, N), np.float32)
        counts = kernels.dense_step(x, P, z, F, Q, H, R, np.zeros((n, 0), np.float32), True, True, *out)
        results.append((counts, out))
    assert results[0][0] == results[1][0] == (0, 0)
    _same(results[0][1], results[1][1])
