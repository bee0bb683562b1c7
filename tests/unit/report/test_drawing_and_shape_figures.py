"""Drawings of tracks (initialising marks, colours by id) and the shape plots' limits and ticks."""

import numpy as np
import pytest

from kalmansfm.report import figures
from kalmansfm.report.drawing import render_tracked_frames, track_colors
from kalmansfm.tracking import INITIALISING, MEASURED, Tracks


def three_tracks(covariance_scale: float, ids=(5, 36, 7)) -> Tracks:
    """Three tracks over three frames: initialising in frames 0-1, measured in frame 2."""
    tracks = Tracks.empty(3, 3)
    positions = np.array([[20.0, 20.0], [60.0, 25.0], [40.0, 50.0]])
    for f in range(3):
        tracks.states[f] = np.hstack([positions + f, np.zeros((3, 2))])
        tracks.covariances[f] = np.eye(4) * covariance_scale
    tracks.status[:2] = INITIALISING
    tracks.status[2] = MEASURED
    return tracks.replace(positions=tracks.states[..., :2].copy(), track_ids=np.array(ids))


def test_an_initialising_point_is_a_square_in_its_colour_without_a_gate():
    small, large = three_tracks(1.0), three_tracks(60.0)
    blank = [np.full((80, 100), 90, np.uint8)] * 3
    (start_small, measured_small) = render_tracked_frames(blank, small, [0, 2], target_width=100)
    (start_large, measured_large) = render_tracked_frames(blank, large, [0, 2], target_width=100)
    # frame 0: the covariance (the start-up prior) draws nothing: the same picture for any prior
    np.testing.assert_array_equal(start_small, start_large)
    # frame 2 (measured): the gate grows with the covariance
    assert (measured_small != measured_large).any()
    for (x, y), colour in zip(small.positions[0], track_colors(small.track_ids)):
        expected = [int(colour[k:k + 2], 16) for k in (5, 3, 1)]
        np.testing.assert_array_equal(start_small[int(y), int(x)], expected)


def test_a_track_is_coloured_by_its_id_whatever_its_column():
    assert track_colors([36]) == track_colors([6]) != track_colors([5])
    tracks = three_tracks(1.0, ids=(5, 36, 7))
    swapped = three_tracks(1.0, ids=(36, 5, 7))
    blank = [np.full((80, 100), 90, np.uint8)] * 3
    (a,) = render_tracked_frames(blank, tracks, [2], target_width=100)
    (b,) = render_tracked_frames(blank, swapped, [2], target_width=100)
    x0, y0 = tracks.positions[2, 0].astype(int)
    x1, y1 = tracks.positions[2, 1].astype(int)
    np.testing.assert_array_equal(a[y0, x0], b[y1, x1])  # id 5 keeps its colour in either column
    assert (a[y0, x0] != a[y1, x1]).any()


def test_a_far_point_leaves_the_axes_instead_of_shrinking_the_shape():
    rng = np.random.default_rng(0)
    points = np.vstack([rng.uniform(-6000, 6000, (60, 3)) * [0.02, 0.02, 0.01], [[10.0, -20.0, 5000.0]]])
    fig = figures.shape_views(points, list(range(61)), hidden=3)
    try:
        front, side, top, oblique = fig.axes
        low, high = sorted(side.get_xlim())  # Z
        assert high - low < 500 and not low <= 5000 <= high
        assert "1 outside the axes" in fig._suptitle.get_text() and "3 unreliable not shown" in fig._suptitle.get_text()
        fig.canvas.draw()
        for ax in (front, side, top):
            for axis in (ax.xaxis, ax.yaxis):
                shown = [t for t in axis.get_major_ticks() if t.label1.get_visible() and t.label1.get_text()]
                limits = sorted(axis.get_view_interval())
                inside = [t for t in axis.get_majorticklocs() if limits[0] <= t <= limits[1]]
                assert len(inside) <= 5 and len(shown) <= 6
        for axis in (oblique.xaxis, oblique.yaxis, oblique.zaxis):
            assert len(axis.get_majorticklocs()) <= 6
    finally:
        figures.plt.close(fig)


@pytest.mark.parametrize("count", [1, 5, 200])
def test_robust_half_width_holds_all_of_a_set_without_stray_points(count):
    points = np.random.default_rng(count).normal(size=(count, 3)) * 10
    centre, half = figures.robust_half_width(points)
    assert (np.abs(points - centre) <= half).all()


def one_moving_track(frames: int, step: float, row: float) -> Tracks:
    """One measured track moving right by ``step`` px a frame from x = 10 along image row ``row``."""
    tracks = Tracks.empty(frames, 1)
    tracks.states[:, 0, 0], tracks.states[:, 0, 1] = 10.0 + step * np.arange(frames), row
    tracks.covariances[:] = np.eye(4)
    tracks.status[:] = MEASURED
    return tracks.replace(positions=tracks.states[..., :2].copy())


def test_a_trail_draws_only_the_recent_path():
    """A track that moved right along 40 frames: with a trail of 5 the start of its path is not drawn,
    with the whole path (trail=None) it is; the current mark is the same in both."""
    tracks = one_moving_track(40, step=2.0, row=30.0)
    blank = [np.full((60, 100), 90, np.uint8)] * 40
    (short,) = render_tracked_frames(blank, tracks, [39], target_width=100, trail=5)
    (whole,) = render_tracked_frames(blank, tracks, [39], target_width=100, trail=None)
    start = (30, 12)  # (row, column) on the path near frame 1, far from the current mark at x=88
    assert (whole[start] != 90).any() and (short[start] == 90).all()
    np.testing.assert_array_equal(short[:, 80:], whole[:, 80:])  # the last 5 frames: x from 78


def test_a_shrunken_picture_draws_the_path_through_every_stride_th_frame():
    """Shrunk to half size, the path runs through every second frame back from the drawn one: moving the
    positions of the frames in between changes nothing, moving one on the stride does."""
    tracks = one_moving_track(41, step=4.0, row=60.0)
    blank = [np.full((120, 200), 90, np.uint8)] * 41
    (drawn,) = render_tracked_frames(blank, tracks, [40], target_width=100, trail=None)
    between, on_stride = tracks.positions.copy(), tracks.positions.copy()
    between[1:40:2, 0, 1] += 30.0  # frames 39, 37, …: off the stride back from frame 40
    on_stride[20, 0, 1] += 30.0
    (same,) = render_tracked_frames(blank, tracks.replace(positions=between), [40], target_width=100, trail=None)
    (moved,) = render_tracked_frames(blank, tracks.replace(positions=on_stride), [40], target_width=100, trail=None)
    np.testing.assert_array_equal(same, drawn)
    assert (moved != drawn).any()
