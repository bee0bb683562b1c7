"""How structure fusion with known cameras runs: its methods, defaults and :class:`FusionSettings`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from ...errors import InvalidInputError
from ..._validation import check_choice, check_count, check_positive
from ...estimation.noise_model import NOISE_MODELS

__all__ = ["DEFAULT_CHUNK_POINTS", "DEFAULT_NOISE_MODEL", "DEFAULT_OUTLIER_PROBABILITY", "FUSION_METHODS",
           "UNRELIABLE_RELATIVE_DEPTH", "FusionSettings", "check_orientation"]

FUSION_METHODS = ("recursive", "batch", "pairs")
DEFAULT_OUTLIER_PROBABILITY = 0.999
DEFAULT_CHUNK_POINTS = 65_536
#: The largest image noise σ a fusion takes (pixels).
MAX_PIXEL_STD = 1e6
DEFAULT_NOISE_MODEL = "mixture"
#: A fused point whose distance from its first camera has a relative standard deviation above this is
#: ``unreliable`` (little parallax), not ``ok`` (the perspective refinement applies the same test).
UNRELIABLE_RELATIVE_DEPTH = 0.1


@dataclass(frozen=True)
class FusionSettings:
    """How :func:`fuse` runs; validated on construction.

    Attributes
    ----------
    method : ``"recursive"``, ``"batch"`` or ``"pairs"``.
    pixel_std : float > 0 in pixels, or None to estimate it (``"auto"``).
    outlier_probability : in (0, 1]; the gate is the χ² quantile of this probability
        (1 turns outlier rejection off).
    history : keep every point's estimate after every view that observed it.
    chunk_points : points processed together (bounds the memory).
    orientation : +1 (points in front of the cameras), -1 (a mirrored reconstruction) or
        None to take the sign most points' depths agree on.
    noise_model : the model of the image noise fitted to the residuals when σ is estimated
        (:data:`~kalmansfm.estimation.noise_model.NOISE_MODELS`): ``"gaussian"`` (one σ for
        every observation, the χ² gate), ``"student-t"`` (heavy tails), ``"mixture"``
        (Gaussian core and uniform outliers) or ``"student-t+uniform"``; every model but
        ``"gaussian"`` gives each track a pooled scale.  A given ``pixel_std`` is a Gaussian.
    track_scales : with a fitted model, give each track its own pooled noise scale.
    """

    method: str = "recursive"
    pixel_std: float | None = None
    outlier_probability: float = DEFAULT_OUTLIER_PROBABILITY
    history: bool = False
    chunk_points: int = DEFAULT_CHUNK_POINTS
    orientation: int | None = None
    noise_model: str = DEFAULT_NOISE_MODEL
    track_scales: bool = False

    def __post_init__(self) -> None:
        check_choice("method", self.method, FUSION_METHODS)
        if self.pixel_std is not None:
            sigma = check_positive("pixel_std", self.pixel_std, "pixels")
            if not 1e-9 <= sigma <= MAX_PIXEL_STD:
                raise InvalidInputError(f"pixel_std must be between 1e-09 and {MAX_PIXEL_STD:g} pixels (a noise larger "
                                        f"than any image measures nothing); got {sigma:g}")
            object.__setattr__(self, "pixel_std", sigma)
        try:
            p = float(self.outlier_probability)
        except (TypeError, ValueError):
            raise InvalidInputError(f"outlier_probability must be a number in (0, 1]; got "
                                    f"{self.outlier_probability!r}") from None
        if not 0.0 < p <= 1.0:
            raise InvalidInputError(f"outlier_probability must be in (0, 1]; got {p}")
        object.__setattr__(self, "outlier_probability", p)
        object.__setattr__(self, "chunk_points", check_count("chunk_points", self.chunk_points, 1))
        object.__setattr__(self, "history", bool(self.history))
        object.__setattr__(self, "track_scales", bool(self.track_scales))
        if self.orientation is not None:
            object.__setattr__(self, "orientation", check_orientation(self.orientation))
        check_choice("noise_model", self.noise_model, NOISE_MODELS)

    @property
    def gate2(self) -> float:
        """χ²(2) quantile of ``outlier_probability`` (inf when 1)."""
        return float(stats.chi2.ppf(self.outlier_probability, 2)) if self.outlier_probability < 1 else np.inf

    @property
    def gate1(self) -> float:
        """χ²(1) quantile of ``outlier_probability`` (inf when 1)."""
        return float(stats.chi2.ppf(self.outlier_probability, 1)) if self.outlier_probability < 1 else np.inf


def check_orientation(orientation: object) -> int:
    if orientation not in (1, -1) or isinstance(orientation, bool):
        raise InvalidInputError(f"orientation must be +1, -1 or None; got {orientation!r}")
    return int(orientation)  # type: ignore[arg-type]
