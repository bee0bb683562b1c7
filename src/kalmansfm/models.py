"""Motion models (re-exported from :mod:`kalmansfm.estimation.models`)."""

from .estimation.models import LinearGaussianModel, constant_velocity_2d, initial_state

__all__ = ["LinearGaussianModel", "constant_velocity_2d", "initial_state"]
