"""Structure fusion with known cameras: every point's 3-D position and covariance, view by view
(recursive inverse-depth Kalman updates, :mod:`.recursive`), by per-point maximum likelihood
(:mod:`.batch`) or by the report's pair fusion (:mod:`.pairs`); :func:`fuse` drives them in chunks
of points and estimates the pixel noise (:mod:`.fuse`).  Task 7's landmarks from a moving camera
are in :mod:`.landmark`."""

from .fuse import fuse
from .history import FusionHistory
from .inverse_depth import GatedUpdate, iterated_update
from .pairs import PairTriangulations, pair_triangulations
from .settings import (
    DEFAULT_CHUNK_POINTS,
    DEFAULT_OUTLIER_PROBABILITY,
    FUSION_METHODS,
    UNRELIABLE_RELATIVE_DEPTH,
    FusionSettings,
)

__all__ = [
    "DEFAULT_CHUNK_POINTS",
    "DEFAULT_OUTLIER_PROBABILITY",
    "FUSION_METHODS",
    "UNRELIABLE_RELATIVE_DEPTH",
    "FusionHistory",
    "FusionSettings",
    "GatedUpdate",
    "PairTriangulations",
    "fuse",
    "iterated_update",
    "pair_triangulations",
]
