"""The per-point refinement summed over the list of observations equals the dense reference."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from kalmansfm.structure import PointStatus
from kalmansfm.structure.geometry.pinhole import CameraSet, project_points
from kalmansfm.structure.geometry import refinement
from kalmansfm.structure.geometry.refinement import LISTED_FILL, refine_points


@st.composite
def refinement_problems(draw):
    """Cameras around the scene, points seen by a random subset of them (some by one, some started at NaN
    or behind the cameras), noisy pixels and a gross error or two."""
    views = draw(st.integers(2, 12))
    points = draw(st.integers(1, 40))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    angles = rng.uniform(-0.8, 0.8, views)
    rotations = Rotation.from_rotvec(np.c_[np.zeros(views), angles, np.zeros(views)]).as_matrix()
    centres = 10.0 * np.c_[np.sin(angles), np.zeros(views), -np.cos(angles)]
    translations = -np.einsum("vij,vj->vi", rotations, centres)
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    cameras = CameraSet.from_pose(K, rotations, translations)
    X = rng.normal(size=(points, 3))
    observations = project_points(cameras, X).pixels + rng.normal(scale=0.5, size=(views, points, 2))
    seen = rng.random((views, points)) < draw(st.sampled_from([0.15, 0.5, 1.0]))
    observations[~seen] = np.nan
    observations[rng.random((views, points)) < 0.05] += 40.0
    start = X + rng.normal(scale=0.3, size=X.shape)
    start[rng.random(points) < 0.1] = np.nan
    flipped = rng.random(points) < 0.1
    start[flipped] = -3.0 * start[flipped] + [0.0, 0.0, -30.0]
    return cameras, observations, start


@settings(max_examples=120, deadline=None)
@given(refinement_problems(), st.sampled_from([1.0, 0.7]))
def test_listed_normal_equations_give_the_dense_result(problem, pixel_std):
    cameras, observations, start = problem
    dense = refine_points(cameras, observations, start, pixel_std=pixel_std, listed=False)
    listed = refine_points(cameras, observations, start, pixel_std=pixel_std, listed=True)
    np.testing.assert_array_equal(listed.status, dense.status)
    np.testing.assert_array_equal(listed.views, dense.views)
    np.testing.assert_array_equal(np.isnan(listed.points), np.isnan(dense.points))
    ok = dense.status == PointStatus.OK
    # the sums differ by rounding, and each run stops where its own step is negligible: compared in the
    # point's standard deviations, not in scene units (400 examples: at most 2·10⁻⁶ σ apart, residuals
    # 1.3·10⁻⁶ px, covariances 3·10⁻⁷ relative)
    step = listed.points[ok] - dense.points[ok]
    distance = np.sqrt(np.einsum("ni,nij,nj->n", step, np.linalg.inv(dense.covariances[ok]), step))
    assert np.all(distance < 1e-4)
    np.testing.assert_allclose(listed.covariances[ok], dense.covariances[ok], rtol=1e-5, atol=0)
    np.testing.assert_allclose(listed.residuals, dense.residuals, rtol=0, atol=1e-4)


@pytest.mark.parametrize("share, listed", [(7 / 48, True), (0.9, False)])
def test_the_listed_sums_are_used_when_few_views_see_each_point(monkeypatch, share, listed):
    """dinoRing's front end: a track is seen by 7 of its 48 views; below LISTED_FILL the list is summed."""
    made = []
    dense_kind, listed_kind = refinement._DenseEquations, refinement._ListedEquations
    for kind in (dense_kind, listed_kind):
        monkeypatch.setattr(refinement, kind.__name__, lambda *args, kind=kind: made.append(kind) or kind(*args))
    rng = np.random.default_rng(3)
    cameras, observations, start = _ring_problem(rng, share)
    refine_points(cameras, observations, start)
    assert made == [listed_kind if listed else dense_kind]
    assert (share < LISTED_FILL) == listed


def _ring_problem(rng, share):
    views, points = 48, 60
    angles = np.linspace(-1.0, 1.0, views)
    rotations = Rotation.from_rotvec(np.c_[np.zeros(views), angles, np.zeros(views)]).as_matrix()
    centres = 10.0 * np.c_[np.sin(angles), np.zeros(views), -np.cos(angles)]
    cameras = CameraSet.from_pose(np.diag([600.0, 600.0, 1.0]), rotations, -np.einsum("vij,vj->vi", rotations, centres))
    X = rng.normal(size=(points, 3))
    observations = project_points(cameras, X).pixels
    observations[rng.random((views, points)) >= share] = np.nan
    return cameras, observations, X


@settings(max_examples=80, deadline=None)
@given(refinement_problems())
def test_listed_leave_one_out_residuals_equal_the_dense_ones(problem):
    """The fusion's outlier test statistic rᵀ (I - J N⁻¹ Jᵀ)⁻¹ r, on the list of observations and densely."""
    from kalmansfm.structure.fusion.batch import _leave_one_out

    cameras, observations, start = problem
    fit = refine_points(cameras, observations, start, listed=False)
    ok = fit.status == PointStatus.OK
    mask = np.isfinite(observations).all(axis=2)[:, ok]
    mask &= mask.sum(axis=0) >= 3
    residuals = np.nan_to_num(fit.residuals[:, ok])
    dense = _leave_one_out(cameras.matrices, fit.points[ok], residuals, mask, listed=False)
    listed = _leave_one_out(cameras.matrices, fit.points[ok], residuals, mask, listed=True)
    np.testing.assert_array_equal(np.isnan(listed), np.isnan(dense))
    np.testing.assert_allclose(listed, dense, rtol=1e-9, atol=1e-12)
    assert np.isnan(dense[~mask]).all()


def test_the_listed_sums_refuse_a_point_without_observations():
    """reduceat would give such a point its successor's sums: the listed form checks instead."""
    P = np.tile(np.hstack([np.eye(3), [[0.0], [0.0], [5.0]]]), (3, 1, 1))
    seen = np.array([[True, False], [True, False], [False, False]])
    equations = refinement._ListedEquations(P, np.zeros((3, 2, 2)), seen, 1)
    with pytest.raises(ValueError, match="1 of the points to refine have no observation"):
        equations.evaluate(np.array([0, 1]), np.zeros((2, 3)))
