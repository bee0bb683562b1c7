"""The kernels behind KalmanFilter: float32 arithmetic, fused predict, storage reuse, threads, errors.

The filter runs compiled kernels, or their NumPy twins below ``engine.COMPILED_MIN_TRACKS``
tracks; the tests that take ``kernel_path`` run on both.  The kernels' agreement with the
NumPy references, and the twins' with the kernels, over random problems is in
``tests/property/test_kalman_kernels_property.py``.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from kalmansfm import InvalidInputError, KalmanFilter, SingularCovarianceError
from kalmansfm.estimation import _kernels, _numpy_kernels, engine
from kalmansfm.estimation import constant_velocity_2d
from reference import decoupled as reference

CV = constant_velocity_2d()
COUPLED_Q = CV.Q + np.array([[0, 2.0, 0, 0], [2.0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]])  # x–y coupling: general form


def _measurements(rng, T, N, p_missing=0.2):
    zs = rng.normal(scale=20.0, size=(T, N, 2))
    zs[rng.random((T, N)) < p_missing] = np.nan
    return zs


# Compiling the float32 variants of the kernels takes seconds per kernel on a fresh machine: the
# compiled-path float32 tests are slow ones; the NumPy twins (the same bits, compared with the
# kernels in float64 by default and in float32 in the slow run) keep float32 in the default run.
COMPILED_SLOW = pytest.param("compiled", marks=pytest.mark.slow)


@pytest.mark.parametrize("kernels", [pytest.param(_kernels, marks=pytest.mark.slow, id="compiled"),
                                     pytest.param(_numpy_kernels, id="numpy")])
def test_float32_is_computed_in_float32_to_the_last_bit(kernels):
    """The float32 step equals the NumPy reference run in float32 bit for bit; a float64 computation rounded
    to float32 would differ from it in the last bits."""
    rng = np.random.default_rng(0)
    N = 500
    X = rng.normal(scale=300, size=(4, N)).astype(np.float32)
    C = np.empty((1, 3, N), np.float32)
    C[0, 0], C[0, 1], C[0, 2] = rng.uniform(3, 100, N), rng.uniform(-1, 1, N), rng.uniform(10, 30, N)
    z = (X[:2].T + rng.normal(scale=3, size=(N, 2))).astype(np.float32)
    z[::7] = np.nan
    q = np.array([[16, 0, 4]] * 2, np.float32)
    r = np.array([[4], [4]], np.float32)
    Xo, Co, Yo = np.empty_like(X), np.empty_like(C), np.empty((2, N), np.float32)
    assert kernels.cv_step(X, C, z.view(np.complex64)[:, 0], np.float32(1), q, r, None, True, Xo, Co, Yo) == (0, 0, 0)
    Xp, Cp = reference.predict(X, C, np.float32(1), q[:1], None)
    Xr, Cr, _ = reference.update(Xp, Cp, z, r[:, 0], True, np.isnan(z))
    assert Xr.dtype == Cr.dtype == np.float32
    np.testing.assert_array_equal(Xo, Xr)
    np.testing.assert_array_equal(Co, Cr)
    # the same step in float64, rounded: not the float32 answer
    X64, C64 = np.empty((4, N)), np.empty((1, 3, N))
    kernels.cv_step(X.astype(float), C.astype(float), z.astype(float).view(np.complex128)[:, 0], 1.0, q.astype(float),
                    r.astype(float), None, True, X64, C64, np.empty((2, N)))
    assert not np.array_equal(X64.astype(np.float32), Xo)


@pytest.mark.parametrize("Q", [CV.Q, COUPLED_Q], ids=["decoupled", "general"])
@pytest.mark.parametrize("kernel_path", [COMPILED_SLOW, "numpy"], indirect=True)
def test_float32_filter_keeps_float32_everywhere(Q, kernel_path):
    rng = np.random.default_rng(1)
    kf = KalmanFilter(rng.normal(size=(50, 4)), CV.P0, CV.F, CV.H, Q, CV.R, dtype=np.float32)
    for z in _measurements(rng, 5, 50):
        kf.predict()
        kf.update(z)
    for name in ("x", "P", "x_prior", "P_prior", "y", "S", "K", "nis", "log_likelihood"):
        assert getattr(kf, name).dtype == np.float32, name
    assert all(a.dtype == np.float32 for a in kf._engine.state)


@pytest.mark.parametrize("Q", [CV.Q, COUPLED_Q], ids=["decoupled", "general"])
def test_reading_the_prior_between_predict_and_update_changes_nothing(Q, kernel_path):
    """predict() is fused into update() unless the prior is read first; both give the same bits."""
    rng = np.random.default_rng(2)
    x0 = rng.normal(scale=10, size=(30, 4))
    u = rng.normal(size=(30, 4))
    fused = KalmanFilter(x0, CV.P0, CV.F, CV.H, Q, CV.R)
    settled = KalmanFilter(x0, CV.P0, CV.F, CV.H, Q, CV.R)
    for t, z in enumerate(_measurements(rng, 12, 30)):
        for kf in (fused, settled):
            kf.predict(u=u if t % 3 == 0 else None)
        prior = settled.x_prior.copy(), settled.P_prior.copy()  # forces the prior now
        for kf in (fused, settled):
            kf.update(z)
        np.testing.assert_array_equal(fused.x, settled.x)
        np.testing.assert_array_equal(fused.P, settled.P)
        np.testing.assert_array_equal(fused.x_prior, prior[0])  # computed afterwards, same bits
        np.testing.assert_array_equal(fused.P_prior, prior[1])
        np.testing.assert_array_equal(fused.nis, settled.nis)


def test_two_predicts_in_a_row_are_two_steps(kernel_path):
    rng = np.random.default_rng(3)
    a = KalmanFilter(rng.normal(size=(5, 4)), CV.P0, CV.F, CV.H, CV.Q, CV.R)
    b = KalmanFilter(a.x, CV.P0, CV.F, CV.H, CV.Q, CV.R)
    a.predict()
    a.predict()
    b.predict()
    b.predict(F=CV.F @ np.eye(4))
    np.testing.assert_allclose(a.P[0], CV.F @ (CV.F @ CV.P0 @ CV.F.T + CV.Q) @ CV.F.T + CV.Q, rtol=1e-14)
    np.testing.assert_array_equal(a.x, b.x)


@pytest.mark.parametrize("Q", [CV.Q, COUPLED_Q], ids=["decoupled", "general"])
def test_arrays_handed_out_keep_their_values_and_unheld_storage_is_reused(Q, kernel_path):
    rng = np.random.default_rng(4)
    N = 40
    kf = KalmanFilter(rng.normal(size=(N, 4)), CV.P0, CV.F, CV.H, Q, CV.R)
    zs = _measurements(rng, 12, N)
    kept_x, kept_col, copies = [], [], []
    storage = set()
    for z in zs:
        kf.predict()
        kf.update(z)
        kept_x.append(kf.x)  # no copy: the filter must not write into it again
        kept_col.append(kf.y[:, 0])  # a view of a view
        copies.append((kf.x.copy(), kf.y[:, 0].copy()))
    for held, col, (x, y) in zip(kept_x, kept_col, copies):
        np.testing.assert_array_equal(held, x)
        np.testing.assert_array_equal(col, y)
    del kept_x, kept_col, held, col
    for t, z in enumerate(np.concatenate([zs, zs])):
        kf.predict()
        kf.update(z)
        if t >= len(zs):
            storage.add(id(kf._engine.state[0]))
    # nobody holds them now: the states cycle through four arrays (current, previous as the
    # source of the prior, and two free)
    assert len(storage) <= 4


def test_results_do_not_depend_on_the_number_of_threads():
    rng = np.random.default_rng(5)
    N = 3 * _kernels.TRACKS_PER_THREAD  # large enough for the general form to split the tracks
    x0 = rng.normal(size=(N, 4))
    zs = _measurements(rng, 3, N)
    zs[1, ::5, 0] = np.nan  # partial rows
    runs = []
    before = numba.get_num_threads()
    try:
        for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
            numba.set_num_threads(threads)
            for Q in (CV.Q, COUPLED_Q):
                kf = KalmanFilter(x0, CV.P0, CV.F, CV.H, Q, CV.R)
                for z in zs:
                    kf.predict()
                    kf.update(z)
                runs.append((kf.x.copy(), np.array(kf.P)))
    finally:
        numba.set_num_threads(before)
    for (x1, P1), (x2, P2) in zip(runs[:2], runs[2:]):
        np.testing.assert_array_equal(x1, x2)
        np.testing.assert_array_equal(P1, P2)


@pytest.mark.parametrize("Q", [CV.Q, COUPLED_Q], ids=["decoupled", "general"])
@pytest.mark.parametrize("shared", [True, False])
def test_an_infinite_measurement_is_refused_and_the_filter_is_unchanged(Q, shared, kernel_path):
    rng = np.random.default_rng(6)
    kf = KalmanFilter(rng.normal(size=(4, 4)), CV.P0, CV.F, CV.H, Q, CV.R)
    if not shared:
        kf.predict()
        kf.update([[1.0, 1.0], [np.nan, np.nan], [2.0, 2.0], [3.0, 3.0]])
    kf.predict()
    x, P = kf.x.copy(), np.array(kf.P)
    with pytest.raises(InvalidInputError, match="z must not contain infinity"):
        kf.update([[1.0, 1.0], [np.nan, np.nan], [np.inf, 2.0], [3.0, 3.0]])
    np.testing.assert_array_equal(kf.x, x)
    np.testing.assert_array_equal(kf.P, P)


def test_the_kernels_report_a_singular_innovation_covariance(kernel_path):
    """Reachable only with zero noise, which the class refuses: the kernels count it, the caller raises."""
    N = 3
    X, z = np.zeros((4, N)), np.ones((N, 2))
    out = np.empty((4, N)), np.empty((1, 3, N)), np.empty((2, N))
    counts = _kernels.cv_step(X, np.zeros((1, 3, N)), z.view(np.complex128)[:, 0], 1.0, np.zeros((2, 3)),
                              np.zeros((2, 1)), None, True, *out)
    assert counts == (0, 0, N)
    _, post, _ = _kernels.cv_shared_blocks(np.zeros((1, 3)), 1.0, np.zeros((2, 3)), np.zeros(2), True)
    assert not np.isfinite(post).all()
    counts = _kernels.dense_step(X, np.zeros((4, 4, N)), z, np.eye(4)[None], np.zeros((1, 4, 4)), CV.H[None],
                                 np.zeros((1, 2, 2)), np.zeros((4, 0)), True, True, np.empty((4, N)),
                                 np.empty((4, 4, N)), np.empty((2, N)))
    assert counts[0] == 0 and counts[1] >= N  # one failing pivot or more per track
    kf = KalmanFilter(np.zeros((N, 4)), CV.P0, CV.F, CV.H, COUPLED_Q, CV.R)
    kf._engine._dense = (kf._engine._dense[0], np.zeros((4, 4, N)))  # a collapsed covariance, with R = 0 below
    kf.R = np.zeros((2, 2))
    with pytest.raises(SingularCovarianceError, match="innovation covariance"):
        kf.update(z)


def test_general_form_statistics_equal_kalman_update_with_partial_rows():
    """y, S, K, NIS and log-likelihood of the compiled general step (computed from the prior on
    access, masking the missing components) equal the reference kalman_update's, grouped by NaN pattern."""
    from kalmansfm.estimation.kalman import kalman_predict, kalman_update

    rng = np.random.default_rng(7)
    N = 60
    R = np.array([[4.0, 1.0], [1.0, 3.0]])
    x0 = rng.normal(scale=10, size=(N, 4))
    kf = KalmanFilter(x0, CV.P0, CV.F, CV.H, COUPLED_Q, R)
    x, P = x0, np.broadcast_to(CV.P0, (N, 4, 4))
    for z in _measurements(rng, 4, N, 0.2):
        z[rng.random((N, 2)) < 0.15] = np.nan
        kf.predict()
        kf.update(z)
        x, P = kalman_predict(x, P, CV.F, COUPLED_Q)
        ref = kalman_update(x, P, z, CV.H, R)
        x, P = ref.x, np.broadcast_to(ref.P, (N, 4, 4))
        np.testing.assert_allclose(kf.x, ref.x, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(np.isnan(kf.y), np.isnan(ref.y))
        np.testing.assert_allclose(kf.y, ref.y, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(kf.S, np.broadcast_to(ref.S, (N, 2, 2)), rtol=1e-12)
        np.testing.assert_allclose(kf.K, ref.K, rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(kf.nis, ref.nis, rtol=1e-10)
        np.testing.assert_allclose(kf.log_likelihood, ref.log_likelihood, rtol=1e-10)


def _run(kf, steps, rng, N):
    """predict/update steps with partial rows, per-track noise and an input; every public array after each."""
    seen = []
    for t in range(steps):
        kf.predict(u=rng.normal(size=(N, 4)) if t == 2 else None)
        z = rng.normal(scale=20.0, size=(N, 2))
        z[rng.random(N) < 0.2] = np.nan
        if t >= 3:
            z[rng.random(N) < 0.1, 1] = np.nan  # rows that measure x alone: the blocks part
        R = np.broadcast_to(np.diag(rng.uniform(1, 5, 2)), (N, 2, 2)) if t == 4 else None
        kf.update(z, R=R)
        seen.append([np.array(getattr(kf, name)) for name in ("x", "P", "x_prior", "P_prior", "y", "S", "K", "nis",
                                                                 "log_likelihood")])
    return seen


@pytest.mark.parametrize("Q", [CV.Q, COUPLED_Q], ids=["decoupled", "general"])
@pytest.mark.parametrize("dtype", [np.float64, pytest.param(np.float32, marks=pytest.mark.slow)])
def test_the_numpy_twins_give_the_filter_the_kernels_bits(Q, dtype, monkeypatch):
    """The same run on the compiled kernels and on their NumPy twins: every public array equal to the last bit."""
    runs = []
    for threshold in (0, 2**62):
        monkeypatch.setattr(engine, "COMPILED_MIN_TRACKS", threshold)
        rng = np.random.default_rng(8)
        N = 70
        kf = KalmanFilter(rng.normal(scale=10, size=(N, 4)), CV.P0, CV.F, CV.H, Q, CV.R, dtype=dtype)
        runs.append(_run(kf, 7, rng, N))
    for compiled, twin in zip(*runs):
        for a, b in zip(compiled, twin):
            np.testing.assert_array_equal(a, b)
