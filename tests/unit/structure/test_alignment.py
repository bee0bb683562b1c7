import numpy as np
import pytest

from kalmansfm import NotEnoughDataError
from kalmansfm.structure import align_affine, align_similarity


def rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_similarity_recovers_known_transform_and_ignores_nan_rows():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    rot = rotation(rng)
    dst = 3.5 * src @ rot.T + [1.0, -2.0, 0.5]
    src[4] = np.nan
    fit = align_similarity(src, dst)
    assert fit.scale == pytest.approx(3.5, rel=1e-12)
    np.testing.assert_allclose(fit.rotation, rot, atol=1e-12)
    np.testing.assert_allclose(fit.translation, [1.0, -2.0, 0.5], atol=1e-12)
    assert fit.rms < 1e-12 and np.isnan(fit.aligned[4]).all()


def test_reflection_only_when_allowed():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    mirrored = src * [1, 1, -1]
    assert align_similarity(src, mirrored).rms > 0.1
    fit = align_similarity(src, mirrored, allow_reflection=True)
    assert fit.rms < 1e-12 and np.linalg.det(fit.rotation) == pytest.approx(-1.0)


def test_affine_fits_any_linear_map():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(15, 3))
    linear = rng.normal(size=(3, 3))
    fit = align_affine(src, src @ linear.T + 4.0)
    np.testing.assert_allclose(fit.rotation, linear, atol=1e-12)
    assert fit.rms < 1e-12


def test_too_few_points():
    with pytest.raises(NotEnoughDataError):
        align_similarity(np.ones((2, 3)), np.ones((2, 3)))
