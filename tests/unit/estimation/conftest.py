"""The Kalman filter's two arithmetic paths as a fixture: compiled kernels or their NumPy twins.

The engine runs the NumPy twins below ``engine.COMPILED_MIN_TRACKS`` tracks and the
compiled kernels above; both give the same bits.  A test that takes ``kernel_path``
runs once on each, whatever its number of tracks.
"""

import pytest

from kalmansfm.estimation import engine


@pytest.fixture(params=["compiled", "numpy"])
def kernel_path(request, monkeypatch):
    monkeypatch.setattr(engine, "COMPILED_MIN_TRACKS", 0 if request.param == "compiled" else 2**62)
    return request.param
