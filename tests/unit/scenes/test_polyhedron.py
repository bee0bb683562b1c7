import numpy as np
import pytest

from kalmansfm import InvalidInputError
from kalmansfm.scenes import Occluder, render_scene


@pytest.fixture(scope="module")
def scene():
    return render_scene()


def test_same_seed_same_frames_other_seed_other_textures(scene):
    again = render_scene()
    other = render_scene(seed=1)
    np.testing.assert_array_equal(scene.frames, again.frames)
    np.testing.assert_array_equal(scene.positions, again.positions)
    assert np.mean(scene.frames != other.frames) > 0.5
    # the geometry does not depend on the seed
    np.testing.assert_array_equal(scene.positions, other.positions)


def test_shapes_and_defaults(scene):
    assert scene.frames.shape == (30, 240, 320) and scene.frames.dtype == np.uint8
    P = len(scene.points_3d)
    assert 9 <= P <= 12
    assert scene.positions.shape == (30, P, 2)
    assert scene.visible.shape == (30, P) and scene.visible.dtype == bool
    assert scene.rotations.shape == (30, 3, 3) and scene.translations.shape == (30, 2)
    np.testing.assert_array_equal(scene.track_ids, np.arange(P))
    np.testing.assert_allclose(scene.points_3d.mean(axis=0), 0.0, atol=1e-12)


def test_positions_are_the_scaled_orthographic_projection(scene):
    for f in range(scene.n_frames):
        R = scene.rotations[f]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        expected = scene.scale * (R[:2] @ scene.points_3d.T).T + scene.translations[f]
        np.testing.assert_allclose(scene.positions[f], expected, atol=1e-9)
    radius = np.sqrt(np.mean(np.sum(scene.points_3d**2, axis=1)))
    assert scene.object_radius == pytest.approx(radius)


def test_bad_arguments_are_refused():
    with pytest.raises(InvalidInputError, match="n_frames"):
        render_scene(n_frames=2)
    with pytest.raises(InvalidInputError, match="image_size"):
        render_scene(image_size=(0, 240))
    with pytest.raises(InvalidInputError, match="pixel_noise_std"):
        render_scene(pixel_noise_std=-1.0)
    with pytest.raises(InvalidInputError, match="occluder"):
        render_scene(occluder=Occluder(track_id=99))
