"""reconstruction.npz keeps each observation's σ under the fitted noise model, one per observation."""

from __future__ import annotations

import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError
from kalmansfm.io.reconstruction import read_reconstruction, write_reconstruction
from kalmansfm.scenes.known_cameras import known_camera_scene
from kalmansfm.structure.fusion import fuse


def test_each_observations_sigma_reads_back_in_the_observations_order(tmp_path):
    scene = known_camera_scene(points=80, views=5, outlier_fraction=0.05, seed=2)
    fused = fuse(scene.observations, scene.cameras)
    std = fused.noise.observation_std
    assert std.shape == (len(fused.observations),)
    # NaN exactly where the model left an observation out
    assert np.array_equal(np.isnan(std), fused.observations.rejected)
    write_reconstruction(fused, tmp_path / "r.npz")
    back = read_reconstruction(tmp_path / "r.npz")
    np.testing.assert_array_equal(back.noise.observation_std, std)
    grid = back.observations.grid(back.noise.observation_std)
    assert np.isnan(grid[~np.isfinite(scene.observations[..., 0])]).all()


def test_a_file_whose_sigmas_do_not_match_its_observations_is_refused(tmp_path):
    scene = known_camera_scene(points=40, views=4, seed=1)
    write_reconstruction(fuse(scene.observations, scene.cameras), tmp_path / "r.npz")
    with np.load(tmp_path / "r.npz") as data:
        arrays = dict(data)
    arrays["obs_std"] = arrays["obs_std"][:-1]
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InvalidInputError, match=r"bad.npz: not a reconstruction .*obs_std holds 159 values for 160"):
        read_reconstruction(tmp_path / "bad.npz")
