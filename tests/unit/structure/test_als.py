"""The weighted ALS of factorization: compiled kernels vs NumPy, the compiled fit vs the dense one, progress."""

import numpy as np
import pytest

from kalmansfm.structure import factorize
from kalmansfm.structure.affine import _als, _als_kernels

from factorization_scenes import orthographic_scene


def problem(rng, frames=9, points=37, missing=0.3):
    x, _, _ = orthographic_scene(rng, frames=frames, points=points, noise_px=1.0)
    observed = rng.random((frames, points)) > missing
    x[~observed] = np.nan
    weights = np.where(observed[:, :, None], rng.uniform(0.5, 2.0, size=x.shape), 0.0)
    return x, weights, observed


@pytest.mark.parametrize("unit", [True, False])
def test_kernels_equal_their_numpy_references(unit):
    rng = np.random.default_rng(0)
    x, weights, observed = problem(rng)
    frames, points = observed.shape
    frame_on, point_on = rng.random(frames) > 0.2, rng.random(points) > 0.2
    motion, translation = rng.normal(size=(2 * frames, 3)), rng.normal(size=2 * frames) * 100
    shape = rng.normal(size=(points, 3)) * 30
    w = np.ones((1, 1, 2)) if unit else weights
    reference_w = None if unit else weights

    normal, rhs, cost = np.full((points, 3, 3), np.nan), np.full((points, 3), np.nan), np.full(frames, np.nan)
    _als_kernels.point_normals(x, w, unit, observed, frame_on, point_on, motion, translation, shape, normal, rhs, cost)
    want = _als_kernels.point_normals_reference(x, reference_w, observed, frame_on, point_on, motion, translation, shape)
    for got, expected in zip((normal, rhs, cost), want):
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-9)
    assert (normal[~point_on] == 0).all() and (cost[~frame_on] == 0).all()

    normal, rhs = np.full((2 * frames, 4, 4), np.nan), np.full((2 * frames, 4), np.nan)
    _als_kernels.frame_normals(x, w, unit, observed, frame_on, point_on, shape, normal, rhs)
    want = _als_kernels.frame_normals_reference(x, reference_w, observed, frame_on, point_on, shape)
    for got, expected in zip((normal, rhs), want):
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-9)
    assert (normal[np.repeat(~frame_on, 2)] == 0).all()


@pytest.mark.parametrize("weighted", [False, True])
def test_the_compiled_fit_is_the_dense_fit(weighted):
    rng = np.random.default_rng(1)
    x, weights, observed = problem(rng, frames=12, points=60)
    observed[0, :] = False  # a frame and a point with too little to be reached by the initialisation's block
    observed[:, 0] = False
    runs = {}
    for compiled in (False, True):
        notes, calls = [], []
        runs[compiled] = _als.weighted_als(x, weights if weighted else None, observed, 500, 1e-10, notes,
                                           progress=lambda i, n: calls.append((i, n)), compiled=compiled)
        iterations = runs[compiled][3]
        assert notes == [] and calls == [(i, 500) for i in range(1, iterations + 1)]
    dense, compiled = runs[False], runs[True]
    assert dense[3] == compiled[3] > 1
    for a, b in zip(dense[:3], compiled[:3]):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)
    for a, b in zip(dense[4:], compiled[4:]):
        np.testing.assert_array_equal(a, b)


def test_factorize_reports_progress_of_the_weighted_fit_only():
    rng = np.random.default_rng(2)
    x, _, _ = orthographic_scene(rng, frames=10, points=30, noise_px=0.5)
    calls = []
    complete = factorize(x, progress=lambda i, n: calls.append((i, n)))
    assert complete.method == "svd" and calls == []
    x[rng.random(x.shape[:2]) < 0.2] = np.nan
    rec = factorize(x, max_iterations=300, progress=lambda i, n: calls.append((i, n)))
    assert rec.method == "als" and calls == [(i, 300) for i in range(1, rec.details.iterations + 1)]


def test_factorize_with_the_compiled_path_of_large_input_gives_the_same_answer(monkeypatch):
    rng = np.random.default_rng(3)
    x, _, _ = orthographic_scene(rng, frames=40, points=700, noise_px=1.0)
    x[rng.random(x.shape[:2]) < 0.3] = np.nan
    dense = factorize(x)
    monkeypatch.setattr(_als, "_COMPILED_ENTRIES", 2 * 40 * 700)  # as if this were large input
    compiled = factorize(x)
    assert compiled.details.iterations == dense.details.iterations
    np.testing.assert_allclose(compiled.points, dense.points, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(compiled.observations.residual_matrix(), dense.observations.residual_matrix(),
                               rtol=1e-9, atol=1e-9, equal_nan=True)
