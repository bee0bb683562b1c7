"""Random rigid orthographic scenes with random holes: factorize never crashes and flags degeneracy."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from kalmansfm import NotEnoughDataError
from kalmansfm.structure import factorize


def scene(seed: int, frames: int, points: int, missing: float, noise: float, flat: bool):
    rng = np.random.default_rng(seed)
    shape = rng.normal(size=(points, 3)) * [50.0, 40.0, 0.0 if flat else 30.0]
    rotations = [np.linalg.qr(rng.normal(size=(3, 3)))[0][:2] for _ in range(frames)]
    positions = np.stack([shape @ r.T for r in rotations]) + rng.uniform(0, 300, (frames, 1, 2))
    positions += noise * rng.normal(size=positions.shape)
    positions[rng.random((frames, points)) < missing] = np.nan
    return positions


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    frames=st.integers(3, 9),
    points=st.integers(4, 16),
    missing=st.sampled_from([0.0, 0.1, 0.3, 0.6]),
    noise=st.sampled_from([0.0, 0.5]),
    flat=st.booleans(),
)
def test_factorize_never_crashes(seed, frames, points, missing, noise, flat):
    positions = scene(seed, frames, points, missing, noise, flat)
    try:
        rec = factorize(positions)
    except NotEnoughDataError:
        return
    rows = np.isfinite(rec.motion).all(axis=(1, 2))
    cols = np.isfinite(rec.points).all(axis=1)
    assert rows.sum() >= 3 and cols.sum() >= 4
    assert np.isfinite(rec.reprojection_rms) and rec.reprojection_rms >= 0
    assert np.isfinite(rec.image_translation[rows]).all()
    assert np.array_equal(np.isfinite(rec.observations.residual_matrix()), rec.observations.used_mask())
    if flat and noise == 0.0 and missing == 0.0:
        # (with holes, a planar scene can have exact non-planar completions: not flaggable)
        assert any("coplanar" in w or "rank 3" in w for w in rec.warnings)
    if not flat and noise == 0.0 and missing == 0.0:
        assert rec.reprojection_rms < 1e-6
