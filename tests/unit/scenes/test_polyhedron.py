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


def plain(**options):
    """The scene with flat faces, flat background and no noise: every edge and marker is exact."""
    return render_scene(pixel_noise_std=0.0, texture_contrast=0.0, shading=0.0, **options)


def test_markers_are_centred_on_the_ground_truth_to_subpixel_accuracy():
    with_markers = plain().frames.astype(float)
    without = plain(marker_size_px=0.0).frames.astype(float)
    scene = plain()
    half = 6
    checked = 0
    for f, p in zip(*np.nonzero(scene.visible)):
        x, y = np.rint(scene.positions[f, p]).astype(int)
        window = np.s_[f, y - half : y + half + 1, x - half : x + half + 1]
        # the marker's share of each pixel, from the picture with and without it (marker intensity 20)
        coverage = (without[window] - with_markers[window]) / (without[window] - 20.0)
        rows, cols = np.mgrid[y - half : y + half + 1, x - half : x + half + 1]
        centroid = np.array([np.sum(coverage * cols), np.sum(coverage * rows)]) / coverage.sum()
        assert coverage.sum() == pytest.approx(36.0, rel=0.01)
        assert np.abs(centroid - scene.positions[f, p]).max() < 0.05
        checked += 1
    assert checked > 200


def polygon_area_centroid(vertices):
    x, y = vertices[:, 0], vertices[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    area = cross.sum() / 2
    return area, np.array([np.sum((x + np.roll(x, -1)) * cross), np.sum((y + np.roll(y, -1)) * cross)]) / (6 * area)


def test_supersampled_faces_have_no_half_pixel_offset():
    scene = plain(marker_size_px=0.0)
    background = 95.0
    normals = []
    centre = scene.points_3d.mean(axis=0)
    for face in scene.faces:
        v = scene.points_3d[list(face)]
        n = np.cross(v[1] - v[0], v[2] - v[0])
        normals.append(n if n @ (v.mean(axis=0) - centre) > 0 else -n)
    normals = np.array(normals)
    rows, cols = np.mgrid[: scene.frames.shape[1], : scene.frames.shape[2]]
    for f in (0, 13, 29):
        image = scene.frames[f].astype(float) - background
        mass, moment = 0.0, np.zeros(2)
        for face, normal in zip(scene.faces, normals):
            if (scene.rotations[f] @ normal)[2] >= 0:  # turned away from the camera
                continue
            area, centroid = polygon_area_centroid(scene.positions[f, list(face)])
            brightness = image[int(round(centroid[1])), int(round(centroid[0]))]
            mass += brightness * abs(area)
            moment += brightness * abs(area) * centroid
        measured = np.array([np.sum(image * cols), np.sum(image * rows)]) / image.sum()
        assert image.sum() == pytest.approx(mass, rel=0.01)
        np.testing.assert_allclose(measured, moment / mass, atol=0.03)


def marker_window(frames, f, position, half=3):
    x, y = np.rint(position).astype(int)
    return frames[f, y - half : y + half + 1, x - half : x + half + 1].astype(float)


def test_a_self_occluded_corner_has_no_marker_and_a_visible_one_has():
    scene, bare = plain(), plain(marker_size_px=0.0)
    hidden = ~scene.visible & np.all((scene.positions > 10) & (scene.positions < [310, 230]), axis=-1)
    assert hidden.sum() >= 30  # the back corners are hidden in every frame
    for f, p in zip(*np.nonzero(hidden)):
        np.testing.assert_array_equal(
            marker_window(scene.frames, f, scene.positions[f, p]), marker_window(bare.frames, f, scene.positions[f, p])
        )
    for f, p in zip(*np.nonzero(scene.visible)):
        assert marker_window(scene.frames, f, scene.positions[f, p], half=1).max() <= 21


def test_a_corner_turning_into_view_becomes_visible(scene):
    # the back-left eave comes round in the last frames as the house turns
    appears = np.flatnonzero(scene.visible.any(axis=0) & ~scene.visible.all(axis=0))
    assert len(appears) >= 1
    column = scene.visible[:, appears[0]]
    assert not column[0] and column[-1]


@pytest.mark.parametrize("track_id, first, n", [(2, 10, 3), (0, 5, 1), (7, 20, 4)])
def test_occluder_hides_exactly_the_frames_it_says(track_id, first, n):
    scene = plain(occluder=Occluder(track_id=track_id, first_frame=first, n_frames=n))
    hidden = np.zeros(30, dtype=bool)
    hidden[first : first + n] = True
    np.testing.assert_array_equal(scene.visible[:, track_id], ~hidden)
    for f in range(first, first + n):  # covered: the card's light stripes, no dark pixel
        assert marker_window(scene.frames, f, scene.positions[f, track_id]).min() > 100
    for f in (first - 1, first + n):
        if 0 <= f < 30:
            assert marker_window(scene.frames, f, scene.positions[f, track_id], half=1).max() <= 21
    # every marker the card touches is reported hidden
    box = scene.occluder_boxes[:, None, :]
    touched = (np.abs(scene.positions[..., 0] - (box[..., 0] + box[..., 2]) / 2) < (box[..., 2] - box[..., 0]) / 2 + 3) & (
        np.abs(scene.positions[..., 1] - (box[..., 1] + box[..., 3]) / 2) < (box[..., 3] - box[..., 1]) / 2 + 3
    )
    assert not (scene.visible & touched).any()


def test_occluder_marker_crosses_the_hidden_marker():
    scene = plain(occluder={"track_id": 2, "first_frame": 10, "n_frames": 3, "marker": True})
    gap = scene.occluder_marker_positions[:, 0] - scene.positions[:, 2, 0]
    assert gap[10] < 0 < gap[12]  # it passes from the left of the hidden marker to its right
    assert marker_window(scene.frames, 11, scene.occluder_marker_positions[11], half=1).max() <= 21


def test_occluder_with_impossible_speed_is_refused():
    with pytest.raises(InvalidInputError, match="speed"):
        render_scene(occluder=Occluder(track_id=2, first_frame=10, n_frames=3, speed_px=-3.0))


def test_exit_scenario_moves_markers_out_of_the_image():
    scene = render_scene(scenario="exit")
    assert scene.visible[0].sum() >= 8
    assert scene.visible[-1].sum() <= scene.visible[0].sum() // 2
    assert (scene.positions[-1, :, 0] < 0).any()
    # visibility ends with the marker reaching the border, not before
    leaving = scene.positions[..., 0] - 3 < -0.5
    assert not (scene.visible & leaving).any()


def test_shape_is_not_planar_and_motion_makes_the_measurements_rank_3(scene):
    centred_points = scene.points_3d - scene.points_3d.mean(axis=0)
    assert np.linalg.svd(centred_points, compute_uv=False)[2] > 0.3 * scene.object_radius
    # Tomasi–Kanade: the registered 2F x P measurement matrix has rank 3 exactly
    registered = scene.positions - scene.positions.mean(axis=1, keepdims=True)
    W = np.concatenate([registered[..., 0], registered[..., 1]], axis=0)
    singular = np.linalg.svd(W, compute_uv=False)
    assert singular[2] > 0.05 * singular[0]
    assert singular[3] < 1e-9 * singular[0]
    # total rotation between the first and the last frame
    relative = scene.rotations[-1] @ scene.rotations[0].T
    angle = np.degrees(np.arccos((np.trace(relative) - 1) / 2))
    assert 20 < angle < 45
