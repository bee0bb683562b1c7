"""Recursive fusion (iterated EKF in inverse depth) equals batch maximum likelihood in the linear-Gaussian limit.

With small image noise the projection is linear over the spread of the estimates,
so the view-by-view Kalman fusion and the all-views Gauss–Newton solution must
coincide: their difference, measured in the batch solution's own standard
deviations, vanishes with the noise (it is O(σ / depth-scale)).
"""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from kalmansfm.structure.geometry.pinhole import CameraSet, project_points
from kalmansfm.structure.fusion import fuse


def look_at(centre: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A rotation whose optical axis points from ``centre`` at the origin, with a random roll."""
    forward = -centre / np.linalg.norm(centre)
    up = rng.normal(size=3)
    right = np.cross(up, forward)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward])


@st.composite
def known_camera_problems(draw):
    views = draw(st.integers(2, 7))
    points = draw(st.integers(1, 15))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    distance = draw(st.sampled_from([3.0, 8.0, 20.0]))
    centres = rng.normal(size=(views, 3))
    centres *= distance / np.linalg.norm(centres, axis=1, keepdims=True)
    R = np.stack([look_at(c, rng) for c in centres])
    f = rng.uniform(300, 2000, views)
    K = np.zeros((views, 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = f, f * rng.uniform(0.9, 1.1, views), 320, 240, 1
    cams = CameraSet.from_pose(K, R, -np.einsum("vij,vj->vi", R, centres))
    X = rng.uniform(-1, 1, size=(points, 3))
    sigma = draw(st.sampled_from([1e-4, 1e-3]))
    obs = project_points(cams, X).pixels + rng.normal(scale=sigma, size=(views, points, 2))
    hidden = rng.random((views, points)) < draw(st.sampled_from([0.0, 0.3]))
    hidden[rng.permutation(views)[:2]] = False  # every point in at least two views
    obs[hidden] = np.nan
    return cams, obs, sigma


@settings(max_examples=60, deadline=None)
@given(known_camera_problems())
def test_recursive_equals_batch_for_small_noise(problem):
    cams, obs, sigma = problem
    kw = dict(pixel_std=sigma, outlier_probability=1.0)
    rec = fuse(obs, cams, method="recursive", **kw)
    bat = fuse(obs, cams, method="batch", **kw)
    np.testing.assert_array_equal(rec.point_status, bat.point_status)
    ok = bat.reconstructed
    d = rec.points[ok] - bat.points[ok]
    std = np.sqrt(np.diagonal(bat.point_covariances[ok], axis1=1, axis2=2))
    assert np.all(np.abs(d) <= 1e-2 * std)
    np.testing.assert_allclose(rec.point_covariances[ok], bat.point_covariances[ok], rtol=2e-2,
                               atol=2e-2 * np.abs(bat.point_covariances[ok]).max())
