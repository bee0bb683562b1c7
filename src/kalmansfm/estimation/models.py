"""Motion models for the Kalman filter.

:func:`constant_velocity_2d` is the pixel model of the polyhedron-tracking
report (``000_3a84a3544ad80a84.txt``, equations 2, 4, 11-13): state
``[x, y, vx, vy]`` in pixels and pixels per frame, position measured.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import as_float_array, check_positive, check_shape

__all__ = ["LinearGaussianModel", "constant_velocity_2d", "initial_state"]


@dataclass(frozen=True, eq=False)
class LinearGaussianModel:
    """A linear-Gaussian state-space model and its initial covariance.

    Attributes
    ----------
    F : (n, n) state transition (the report's Φ).
    H : (m, n) measurement matrix.
    Q : (n, n) process noise covariance.
    R : (m, m) measurement noise covariance.
    P0 : (n, n) initial state covariance (the report's Σ0).
    """

    F: np.ndarray
    H: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    P0: np.ndarray

    def __iter__(self):  # allows ``F, H, Q, R, P0 = constant_velocity_2d()``
        return iter((self.F, self.H, self.Q, self.R, self.P0))

    def __eq__(self, other: object) -> bool:
        """Two models are equal when all their matrices are (so settings holding models compare)."""
        if not isinstance(other, LinearGaussianModel):
            return NotImplemented
        return all(np.array_equal(a, b) for a, b in zip(self, other))

    __hash__ = None  # type: ignore[assignment]  # the matrices are mutable arrays


def constant_velocity_2d(
    position_noise_std: float = 4.0,
    velocity_noise_std: float = 2.0,
    measurement_noise_std: float = 2.0,
    initial_position_std: float = 10.0,
    initial_velocity_std: float = 5.0,
    dt: float = 1.0,
) -> LinearGaussianModel:
    """Constant-velocity model in the image plane, with the report's defaults.

    Q = diag(16, 16, 4, 4), R = diag(4, 4), Σ0 = diag(100, 100, 25, 25) with the
    default standard deviations (4 px, 2 px/frame, 2 px, 10 px, 5 px/frame).

    Parameters
    ----------
    position_noise_std, velocity_noise_std : process noise standard deviations
        (pixels, pixels per frame) on the diagonal of Q.
    measurement_noise_std : standard deviation of a measured position, pixels.
    initial_position_std, initial_velocity_std : square roots of the diagonal of Σ0.
    dt : frame interval (the velocity enters the position as ``x + dt * vx``).

    Examples
    --------
    >>> m = constant_velocity_2d()
    >>> m.F
    array([[1., 0., 1., 0.],
           [0., 1., 0., 1.],
           [0., 0., 1., 0.],
           [0., 0., 0., 1.]])
    >>> np.diag(m.Q), np.diag(m.R), np.diag(m.P0)
    (array([16., 16.,  4.,  4.]), array([4., 4.]), array([100., 100.,  25.,  25.]))
    """
    values = {
        "position_noise_std": position_noise_std,
        "velocity_noise_std": velocity_noise_std,
        "measurement_noise_std": measurement_noise_std,
        "initial_position_std": initial_position_std,
        "initial_velocity_std": initial_velocity_std,
        "dt": dt,
    }
    for name, value in values.items():
        check_positive(name, value)
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    H = np.eye(2, 4)
    Q = np.diag([position_noise_std**2] * 2 + [velocity_noise_std**2] * 2)
    R = np.eye(2) * measurement_noise_std**2
    P0 = np.diag([initial_position_std**2] * 2 + [initial_velocity_std**2] * 2)
    return LinearGaussianModel(F=F, H=H, Q=Q, R=R, P0=P0)


def initial_state(positions_first: object, positions_next: object) -> np.ndarray:
    """Two-frame initial states s0 = [x₁, y₁, x₁ - x₀, y₁ - y₀] for many points.

    Parameters
    ----------
    positions_first : (P, 2) positions (x, y) in frame i.
    positions_next : (P, 2) positions of the same points in frame i + 1.

    Returns
    -------
    (P, 4) states placed at frame i + 1.

    Examples
    --------
    >>> initial_state([[118, 78], [117, 89]], [[115, 78], [114, 89]])
    array([[115.,  78.,  -3.,   0.],
           [114.,  89.,  -3.,   0.]])
    """
    first = as_float_array("positions_first", positions_first)
    nxt = as_float_array("positions_next", positions_next)
    check_shape("positions_first", first, (None, 2), "(points, 2) as (x, y)")
    check_shape("positions_next", nxt, (first.shape[0], 2), "(points, 2), same points as positions_first")
    return np.concatenate([nxt, nxt - first], axis=1)
