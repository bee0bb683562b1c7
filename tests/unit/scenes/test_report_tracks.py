import numpy as np

from kalmansfm.experiments import report_tracks
from kalmansfm.structure import factorize

# Section 2.2 of the report: X_1 Y_1 X_2 Y_2 of the nine corners.
TABLE = np.array(
    [[118, 78, 115, 78], [117, 89, 114, 89], [122, 158, 120, 158], [232, 92, 229, 91], [254, 80, 251, 80],
     [273, 79, 270, 78], [273, 163, 270, 163], [297, 69, 295, 69], [296, 138, 295, 138]],
    dtype=float,
)


def test_frames_1_and_2_are_the_printed_table():
    t = report_tracks()
    np.testing.assert_array_equal(t.positions[0], TABLE[:, :2])
    np.testing.assert_array_equal(t.positions[1], TABLE[:, 2:])


def test_printed_states_as_printed():
    t = report_tracks()
    assert np.isfinite(t.positions).all()
    # "Point 1: Frame# 3 X: 114.02758620689656 Y: 77.02758620689656"
    np.testing.assert_array_equal(t.positions[2, 0], [114.02758620689656, 77.02758620689656])
    # "Point 9: Frame# 30 X: 228.1341987369889 Y: 136.8827595242939"
    np.testing.assert_array_equal(t.positions[29, 8], [228.1341987369889, 136.8827595242939])


def test_report_tracks_factorize():
    rec = factorize(report_tracks().positions)
    assert rec.method == "svd" and rec.points.shape == (9, 3)
    assert 2.5 < rec.reprojection_rms < 3.2  # 2.88 px: a weak rank-3 fit, little rotation
    np.testing.assert_allclose(np.linalg.norm(rec.motion, axis=2), 1.0, atol=0.05)
