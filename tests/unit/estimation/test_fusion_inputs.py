"""Bad input to fuse_recursive / fuse_closed_form: a ValueError that names the argument and what was expected."""

import numpy as np
import pytest

from kalmansfm import InvalidInputError, fuse_closed_form, fuse_recursive

FUSERS = [fuse_recursive, fuse_closed_form]
EYE3 = np.tile(np.eye(3), (3, 1, 1))


@pytest.mark.parametrize("fuse", FUSERS)
def test_non_positive_definite_covariance_names_the_caller_index(fuse):
    p = np.array([[1.0, 1.0], [np.nan, np.nan], [1.0, 1.0]])  # row 1 missing: its covariance is unused
    R = np.array([np.eye(2), np.full((2, 2), np.nan), np.diag([1.0, -1.0])])
    with pytest.raises(ValueError, match=r"covariances must be positive definite \(matrix \(2,\)\); smallest eigenvalue -1"):
        fuse(p, R)


@pytest.mark.parametrize("fuse", FUSERS)
def test_zero_variance_of_a_scalar_is_rejected(fuse):
    with pytest.raises(InvalidInputError, match=r"covariances must be positive definite \(matrix \(1,\)\)"):
        fuse([1.0, 2.0], [1.0, 0.0])


@pytest.mark.parametrize("fuse", FUSERS)
def test_asymmetric_covariance_is_rejected(fuse):
    with pytest.raises(InvalidInputError, match="covariances must be symmetric"):
        fuse(np.zeros((2, 2)), np.array([[[1.0, 0.5], [0.0, 1.0]]] * 2))


@pytest.mark.parametrize("fuse", FUSERS)
@pytest.mark.parametrize("first", [[np.nan, np.nan, np.nan], [1.0, np.nan, 1.0]])
def test_nan_first_measurement_is_rejected(fuse, first):
    p = np.array([first, [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]])
    with pytest.raises(InvalidInputError, match=r"measurements\[0\] must be finite"):
        fuse(p, EYE3)


@pytest.mark.parametrize("fuse", FUSERS)
def test_infinite_measurement_is_rejected(fuse):
    with pytest.raises(InvalidInputError, match="measurements must not contain infinity"):
        fuse([1.0, np.inf], [1.0, 1.0])


@pytest.mark.parametrize("fuse", FUSERS)
@pytest.mark.parametrize(
    "measurements, covariances, kwargs, message",
    [
        (np.zeros((3, 3)), EYE3[:2], {}, r"covariances must have shape \(3, 3, 3\); got \(2, 3, 3\)"),
        ([1.0, 2.0, 3.0], [1.0, 1.0], {}, r"covariances must have shape \(3,\) .*; got \(2,\)"),
        (np.zeros((3, 2, 3)), EYE3, {}, r"covariances must have shape \(3, 2, 3, 3\); got \(3, 3, 3\)"),
        (np.zeros((2, 2, 2, 2)), np.zeros((2, 2, 2, 2)), {}, r"measurements must have shape \(K,\), \(K, d\) or \(K, L, d\)"),
        (np.zeros((0, 3)), np.zeros((0, 3, 3)), {}, "measurements must hold at least one measurement"),
        (np.zeros((3, 3)), EYE3, {"rotations": np.eye(2)}, r"rotations must have shape \(2, 3, 3\) or \(3, 3\); got \(2, 2\)"),
        (np.zeros((3, 3)), EYE3, {"translations": np.zeros((5, 3))}, r"translations must have shape \(2, 3\) or \(3,\); got \(5, 3\)"),
        ([1.0, 2.0, 3.0], [1.0] * 3, {"translations": [1.0, 2.0, 3.0]}, r"translations must have shape \(2,\) or a scalar; got \(3,\)"),
        (np.zeros((3, 3)), EYE3, {"rotations": np.full((2, 3, 3), np.nan)}, r"rotations must be finite; entry \(0, 0, 0\) is nan"),
        (np.zeros((3, 3)), EYE3, {"translations": [0.0, np.inf, 0.0]}, "translations must be finite"),
        ([["a"]], [[1.0]], {}, "measurements must be numeric"),
    ],
)
def test_mismatched_shapes_name_the_argument_and_the_expected_shape(fuse, measurements, covariances, kwargs, message):
    with pytest.raises(ValueError, match=message):
        fuse(measurements, covariances, **kwargs)


def test_missing_measurement_only_moves_the_estimate():
    # Task 3 style: walking 1 m closer; the second reading is missing.
    r = fuse_recursive([10.0, np.nan, 8.5], [1.0, 1.0, 1.0], translations=1.0)
    np.testing.assert_allclose(r.estimates, [10.0, 9.0, 8.25])
    np.testing.assert_allclose(r.covariances, [1.0, 1.0, 0.5])
