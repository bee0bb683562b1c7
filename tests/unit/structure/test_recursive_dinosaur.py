"""The recursive perspective method on the Oxford dinosaur: every frame the batch method registers.

A narrow view (f ≈ 3 000 px) of a small object turning 10° a frame: the essential matrix of
several consecutive pairs is ambiguous (every match fits one that puts none in front of both
cameras).  The chain then starts those pairs from the neighbouring pair's motion.
Data: ``../shared/data/oxford_dinosaur`` (Oxford VGG; see its README).
"""

from pathlib import Path

import numpy as np
import pytest
from scipy import io as scipy_io

from kalmansfm.structure.perspective.reconstruct import reconstruct_perspective
from kalmansfm.structure.geometry.pinhole import decompose_projection

DINO = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "oxford_dinosaur"


@pytest.fixture(scope="module")
def dinosaur():
    if not DINO.is_dir():
        pytest.fail(f"real data missing: {DINO}")
    xy = np.loadtxt(DINO / "viff.xy")
    obs = xy.reshape(xy.shape[0], 36, 2).transpose(1, 0, 2).copy()
    obs[obs == -1] = np.nan
    cells = scipy_io.loadmat(DINO / "dino_Ps.mat")["P"]
    P = np.stack([np.asarray(cells[0, i], dtype=np.float64) for i in range(36)])
    return obs, decompose_projection(P).intrinsics


def test_the_recursive_method_registers_all_36_frames(dinosaur):
    obs, K = dinosaur
    rec = reconstruct_perspective(obs, K, method="recursive")
    assert rec.registered.all()
    assert not any("could not be registered" in w for w in rec.warnings)
    # the chain accumulates error over 36 relative orientations: points that do not fit their own observations
    # with the chained poses are 'unreliable', with a warning; the rest fit to a pixel
    counts = rec.status_counts()
    assert counts["ok"] > 2000 and rec.reprojection_rms < 1.0
    assert counts["unreliable"] == 0 or any("chained poses" in w for w in rec.warnings)
