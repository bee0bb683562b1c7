"""What every reconstruction says about each of its points: one status code, and the size of a covariance.

Factorization (:func:`~kalmansfm.structure.point_uncertainty`), structure fusion with known
cameras (:func:`~kalmansfm.structure.fuse`) and calibrated reconstruction
(:func:`~kalmansfm.structure.reconstruct_perspective`) all mark each point with a
:class:`PointStatus`, and every ``structure.csv`` writes its :attr:`~PointStatus.label`.
Which outcomes a method can reach:

================  ==================================================================
``ok``            every method: a point with a covariance, trusted
``too_few_views`` every method: seen (after outlier rejection) in fewer than 2 usable views
``degenerate``    every method: the views do not fix the point (no parallax, a
                  singular normal matrix, or not linked to the reconstructed frames)
``behind_camera`` fusion with known cameras: the only solution lies behind a camera
``unreliable``    factorization: reconstructed, but seen in fewer than 4 frames or with a
                  1σ axis longer than a quarter of the shape's radius
================  ==================================================================
"""

from __future__ import annotations

import numpy as np

from .._validation import LabelledEnum

__all__ = ["PointStatus", "rms_std"]


class PointStatus(LabelledEnum):
    """The outcome of estimating one 3-D point; ``label`` (the lower-case name) is the word files use.

    Examples
    --------
    >>> [s.label for s in PointStatus]
    ['ok', 'too_few_views', 'degenerate', 'behind_camera', 'unreliable']
    >>> PointStatus.from_label("behind_camera").value
    3
    """

    OK = 0  #: estimated, with a covariance, and trusted
    TOO_FEW_VIEWS = 1  #: seen (after outlier rejection) in fewer than 2 usable views
    DEGENERATE = 2  #: the views do not determine it (no parallax, a singular normal matrix)
    BEHIND_CAMERA = 3  #: the only solution lies behind a camera that sees it
    UNRELIABLE = 4  #: estimated, but too weakly (too few views, or too uncertain) to be trusted


def rms_std(covariances: np.ndarray) -> np.ndarray:
    """√(tr Σ / 3) of each (..., 3, 3) covariance: the RMS per-axis standard deviation.

    The one number by which the PLY files, the summaries and the plots size a point's
    uncertainty (NaN where the covariance is).

    Examples
    --------
    >>> rms_std(np.diag([1.0, 4.0, 4.0])[None]).tolist()
    [1.7320508075688772]
    """
    return np.sqrt(np.trace(np.asarray(covariances, dtype=np.float64), axis1=-2, axis2=-1) / 3.0)
