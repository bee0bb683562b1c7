"""What a camera given from outside must be (issues 27, 30): rotations repaired only where rounding explains, sane K."""

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kalmansfm.errors import InvalidInputError, KalmanSfmWarning
from kalmansfm.structure.geometry.camera_checks import (
    ROTATION_EXACT,
    ROTATION_ROUNDED,
    check_rotations,
    intrinsics_problem,
)
from kalmansfm.structure.geometry.pinhole import CameraSet, intrinsic_matrices

R = Rotation.random(5, random_state=3).as_matrix()
K = np.diag([800.0, 800.0, 1.0])


def test_rotations_printed_to_six_digits_are_replaced_by_the_nearest_rotation():
    printed = np.round(R, 6)  # what a published calibration file holds
    checked = check_rotations(printed)
    off = np.abs(printed @ np.swapaxes(printed, 1, 2) - np.eye(3)).max(axis=(1, 2))
    np.testing.assert_array_equal(checked.deviations, off)
    assert checked.repaired.tolist() == (off > ROTATION_EXACT).tolist() and checked.repaired.any()
    # the nearest rotation: orthonormal, det +1, and it moved no farther than the rounding did
    fixed = checked.rotations
    np.testing.assert_allclose(fixed @ np.swapaxes(fixed, 1, 2), np.broadcast_to(np.eye(3), (5, 3, 3)), atol=1e-15)
    np.testing.assert_allclose(np.linalg.det(fixed), 1.0, atol=1e-15)
    assert np.abs(fixed - R).max() < 1e-6 and np.abs(fixed - printed).max() <= np.abs(R - printed).max() * 1.5
    assert f"{checked.repaired.sum()} of 5 rotation(s) orthonormal only to {off.max():.2g}" in checked.warning()
    exact = check_rotations(R)
    assert not exact.repaired.any() and exact.warning() is None
    np.testing.assert_array_equal(exact.rotations, R)  # an exact rotation is used bit for bit


def test_what_is_not_a_rotation_is_told_apart():
    mirror = R[0] @ np.diag([1.0, 1.0, -1.0])
    far = R[1] * (1 + 10 * ROTATION_ROUNDED)
    checked = check_rotations(np.stack([mirror, far, np.full((3, 3), np.nan), R[2]]))
    assert checked.reflections.tolist() == [True, False, False, False]
    assert checked.not_rotations.tolist() == [False, True, True, False]


def test_from_pose_repairs_rounded_rotations_with_a_warning_and_refuses_the_rest():
    printed = np.round(R, 6)
    t = np.tile([0.0, 0.0, 5.0], (5, 1))
    with pytest.warns(KalmanSfmWarning, match=r"rotations: \d of 5 rotation\(s\) orthonormal only to"):
        cams = CameraSet.from_pose(K, printed, t)
    np.testing.assert_allclose(cams.decompose().rotations, check_rotations(printed).rotations, atol=1e-12)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        CameraSet.from_pose(K, R, t)  # exact rotations: no warning
    with pytest.raises(InvalidInputError, match=r"rotations\[2\] is a reflection \(det R = -1\), not a rotation"):
        CameraSet.from_pose(K, np.stack([R[0], R[1], -R[2]]), t[:3])
    with pytest.raises(InvalidInputError, match=r"rotations\[1\] is not a rotation: R Rᵀ differs from I by 0\.0"):
        CameraSet.from_pose(K, np.stack([R[0], R[1] * 1.01]), t[:2])


@pytest.mark.parametrize("fx, fy, skew, message", [
    (800.0, 800.0, 1e6, r"skew 1e\+06 px is larger than the focal length 800 px"),
    (1e300, 800.0, 0.0, r"fx and fy must be at most 1e\+07 px; got 1e\+300, 800"),
    (-800.0, 800.0, 0.0, r"fx and fy must be > 0"),
    (800.0, 0.5, 0.0, r"fy / fx = 0\.000625: pixels that far from square"),
])
def test_absurd_intrinsics_are_refused_with_one_line_and_no_numpy_warning(fx, fy, skew, message):
    bad = intrinsic_matrices([800.0, fx], [800.0, fy], 320.0, 240.0, [0.0, skew])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning printed before the error line would fail here
        index, text = intrinsics_problem(bad)
        assert index == 1
        with pytest.raises(InvalidInputError, match=r"intrinsics\[1\]: " + message):
            CameraSet.from_pose(bad, np.stack([np.eye(3)] * 2), [[0.0, 0.0, 5.0]] * 2)
    assert intrinsics_problem(intrinsic_matrices(3310.4, 3325.5, 316.73, 200.55, 0.0)) is None


def test_projection_matrices_are_checked_for_what_is_meaningful_not_for_pixel_bounds():
    georeferenced = CameraSet.from_pose(K, R[:2], -np.einsum("vij,vj->vi", R[:2], [[5e5, 4e6, 300.0]] * 2))
    assert np.abs(georeferenced.matrices[:, :, 3]).max() > 1e8  # p14 is not a pixel: accepted
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # and the refusals below print no NumPy warning first
        for scale in (1e300, 1e-300):
            with pytest.raises(InvalidInputError, match=r"frame 0 has entries up to 1e[+-]300; a projection matrix is "
                                                        r"defined up to scale: divide it"):
                CameraSet.from_matrices(np.eye(3, 4) * scale)
        with pytest.raises(InvalidInputError, match="left 3x3 block is not invertible"):
            CameraSet.from_matrices(np.eye(3, 4)[[0, 1, 1]])
