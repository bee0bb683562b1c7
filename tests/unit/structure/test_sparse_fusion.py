"""Fusion of observations given per observation (issue 29): blocks of tracks over their own views, the same result.

A long sequence of short tracks is fused block by block, each block a dense array over only the
views its tracks are seen in; the points are independent given the cameras and the global σ and
noise model, so the result must be the one the dense (views × points) array gives.
"""

from __future__ import annotations

import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError
from kalmansfm.scenes.known_cameras import known_camera_scene
from kalmansfm.structure import Observations
from kalmansfm.structure.fusion import blocks, fuse


def _short_tracks(views: int = 40, points: int = 600, length: int = 6, seed: int = 3):
    """A scene whose every point is seen in a window of ``length`` consecutive views, windows spread over all."""
    scene = known_camera_scene(points=points, views=views, pixel_std=0.5, outlier_fraction=0.03, arc_degrees=120,
                               seed=seed)
    start = np.random.default_rng(seed).integers(0, views - length + 1, size=points)
    v = np.arange(views)[:, None]
    window = (v >= start[None]) & (v < start[None] + length)
    return scene, np.where(window[..., None], scene.observations, np.nan)


def _sparse(obs: np.ndarray) -> Observations:
    v, p = np.nonzero(np.isfinite(obs[..., 0]))
    return Observations.from_sparse(obs.shape[:2], v, p, obs[v, p])


@pytest.fixture
def small_blocks(monkeypatch):
    """Blocks of a few views and points, so that a small scene is cut into many."""
    monkeypatch.setattr(blocks, "_BLOCK_VIEWS", 4)
    monkeypatch.setattr(blocks, "_BLOCK_ENTRIES", 400)
    monkeypatch.setattr(blocks, "ONE_BLOCK_VIEWS", 0)  # never one dense array


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_fusing_per_observation_in_blocks_gives_the_dense_result(small_blocks, method):
    scene, obs = _short_tracks()
    sparse = _sparse(obs)
    made = blocks.sparse_blocks(sparse)
    assert len(made) > 10 and max(b.views.size for b in made) < obs.shape[0] / 2
    assert sorted(np.concatenate([b.points for b in made]).tolist()) == list(range(obs.shape[1]))
    dense = fuse(obs, scene.cameras, method=method, history=True)
    split = fuse(sparse, scene.cameras, method=method, history=True)
    # recursive: the same transitions point by point (to the rounding of products over fewer views); batch:
    # Gauss-Newton iterates a chunk until all its points converge, so another grouping stops each point within
    # the iteration's tolerance instead
    tol = {"rtol": 1e-7, "atol": 1e-9} if method == "recursive" else {"rtol": 1e-5, "atol": 1e-5}
    assert np.array_equal(split.point_status, dense.point_status)
    assert split.noise.std == pytest.approx(dense.noise.std, rel=tol["rtol"])
    np.testing.assert_allclose(split.points, dense.points, **tol)
    np.testing.assert_allclose(split.point_covariances, dense.point_covariances, rtol=100 * tol["rtol"], atol=1e-15)
    for a, b in ((split.observations, dense.observations),):
        assert np.array_equal(a.frame, b.frame) and np.array_equal(a.point, b.point)
        assert np.array_equal(a.used, b.used) and np.array_equal(a.rejected, b.rejected)
        np.testing.assert_allclose(a.residual, b.residual, rtol=100 * tol["rtol"], atol=tol["atol"])
    np.testing.assert_allclose(split.noise.observation_std, dense.noise.observation_std, rtol=tol["rtol"])
    assert split.reprojection_rms == pytest.approx(dense.reprojection_rms, rel=tol["rtol"])
    hs, hd = split.details.history, dense.details.history
    assert np.array_equal(hs.views, hd.views) and np.array_equal(hs.points, hd.points)
    np.testing.assert_allclose(hs.estimates, hd.estimates, **tol)
    # the fitted model's parameters, except the serial correlation (fitted to a different sample of points)
    fitted = {k: v for k, v in dense.noise.parameters if not k.startswith("serial_")}
    assert {k: v for k, v in split.noise.parameters if not k.startswith("serial_")} == pytest.approx(
        fitted, rel=max(1e-6, tol["rtol"]))


def test_a_known_sigma_fuses_each_block_alone(small_blocks):
    scene, obs = _short_tracks(seed=5)
    dense = fuse(obs, scene.cameras, pixel_std=0.5)
    split = fuse(_sparse(obs), scene.cameras, pixel_std=0.5)
    assert np.array_equal(split.point_status, dense.point_status)
    np.testing.assert_allclose(split.points, dense.points, rtol=1e-7, atol=1e-9)
    ok = split.reconstructed
    assert ok.sum() > 500
    err = split.points[ok] - scene.points[ok]
    nees = np.einsum("ni,ni->n", err, np.linalg.solve(split.point_covariances[ok], err[..., None])[..., 0])
    assert 1.9 < np.median(nees) < 2.9


def test_progress_counts_every_point_once_in_each_pass(small_blocks):
    """Reported after each chunk: within a pass the points done rise to all of them; a fit of σ passes again."""
    scene, obs = _short_tracks(seed=6)
    calls: list[tuple[int, int]] = []
    fuse(_sparse(obs), scene.cameras, chunk_points=50, progress=lambda done, total: calls.append((done, total)))
    passes = np.split(np.array(calls), np.flatnonzero(np.diff([d for d, _ in calls]) <= 0) + 1)
    for one in passes:
        assert (np.diff(one[:, 0]) > 0).all() and (one[:, 1] == one[0, 1]).all() and one[-1, 0] == one[0, 1]
    assert sum(one[0, 1] == obs.shape[1] for one in passes) >= 2  # the pilot for σ, then the gated pass


def test_small_observations_per_observation_are_fused_as_the_dense_array():
    scene, obs = _short_tracks(views=12, points=120)
    dense = fuse(obs, scene.cameras)
    given = fuse(_sparse(obs), scene.cameras)
    assert blocks.fits_one_block(obs.shape[:2])
    np.testing.assert_array_equal(given.points, dense.points)
    np.testing.assert_array_equal(given.point_covariances, dense.point_covariances)
    assert given.noise == dense.noise


def test_observations_per_observation_must_match_the_cameras():
    scene, obs = _short_tracks(views=10, points=50)
    sparse = _sparse(obs[:8])
    with pytest.raises(InvalidInputError, match="over the 10 views"):
        fuse(sparse, scene.cameras)
