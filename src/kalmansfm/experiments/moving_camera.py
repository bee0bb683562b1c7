"""The ground-truth path of the report's Tasks 6 and 7: a robot on a flat road.

Thomas & Oliensis (``004_cd423c68da9c9743.txt``) move a sensor past one landmark;
the landmark's coordinates in the sensor frame change as
x_{k+1} = C_k x_k - b_k (eq. 23), with rotations about the vertical
(camera Y) axis and translations on the ground plane.  The report prints only the
resulting coordinates; the motion below reproduces every ground-truth row of
Table 6.1 (24 rows) and Table 7.1 (24 rows) to their printed precision
(``tests/unit/scenes/test_moving_camera.py``); it is Task 6's motion of
:mod:`kalmansfm.experiments.fusion_tasks`, continued for one more step:

* the landmark starts at (40, 40, 60) m in the first sensor frame;
* C_k = R_y(+1°) for even k (0, 2, 4, ...) and R_y(-1°) for odd k, with
  R_y(θ) = [[cos θ, 0, sin θ], [0, 1, 0], [-sin θ, 0, cos θ]];
* b_k = (0, 0, 1) m: one metre forward along the optical axis each step.

Task 6 measures the landmark in sensor frames 0..23; Task 7 triangulates it
from image pairs (k-1, k) for k = 1..24, so its truth column is Task 6's
shifted by one step and needs 25 images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import check_count

__all__ = ["CameraPath", "report_path", "rotation_about_y", "yaw_and_forward_motion"]

#: The landmark in the first sensor frame (Table 6.1, row 1), metres.
REPORT_LANDMARK = (40.0, 40.0, 60.0)


def rotation_about_y(angle_rad: float) -> np.ndarray:
    """The 3×3 rotation by ``angle_rad`` about the y axis, [[c, 0, s], [0, 1, 0], [-s, 0, c]].

    Examples
    --------
    >>> rotation_about_y(np.pi / 2).round(12) @ [1.0, 0.0, 0.0]
    array([ 0.,  0., -1.])
    """
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])



def yaw_and_forward_motion(steps: int) -> tuple[np.ndarray, np.ndarray]:
    """The report's sensor motion for ``steps`` steps: C_k = R_y(±1°) alternating from +1°, b_k = (0, 0, 1) m.

    This is Task 6's motion (and, continued, Task 7's): one definition serves both.

    Examples
    --------
    >>> C, b = yaw_and_forward_motion(3)
    >>> np.degrees(np.arcsin(C[:, 0, 2])).round(6).tolist(), b[0].tolist()
    ([1.0, -1.0, 1.0], [0.0, 0.0, 1.0])
    """
    angles = np.where(np.arange(steps) % 2 == 0, 1.0, -1.0)
    C = np.stack([rotation_about_y(np.radians(a)) for a in angles]) if steps else np.zeros((0, 3, 3))
    return C, np.tile([0.0, 0.0, 1.0], (steps, 1))


@dataclass(frozen=True)
class CameraPath:
    """A landmark seen from a moving sensor with known motion.

    Attributes
    ----------
    landmark : (K, 3) — the landmark in sensor frame k, metres.
    rotations : (K-1, 3, 3) — C_k with x_{k+1} = C_k x_k - b_k.
    translations : (K-1, 3) — b_k, metres.
    """

    landmark: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray


def report_path(n_frames: int = 25) -> CameraPath:
    """The report's path (Tables 6.1 and 7.1) over ``n_frames`` sensor frames.

    Parameters
    ----------
    n_frames : int
        Number of sensor frames (images) K >= 2; 25 gives Task 7's 24 pairs.

    Returns
    -------
    CameraPath

    Examples
    --------
    >>> path = report_path()
    >>> path.landmark[[1, 2, 24]].round(3)
    array([[41.041, 40.   , 58.293],
           [40.017, 40.   , 58.   ],
           [40.209, 40.   , 36.002]])
    """
    n_frames = check_count("n_frames", n_frames, 2)
    steps = n_frames - 1
    C, b = yaw_and_forward_motion(steps)
    x = np.empty((n_frames, 3))
    x[0] = REPORT_LANDMARK
    for k in range(steps):
        # eq. 23: x_{k+1} = C_k x_k - b_k
        x[k + 1] = C[k] @ x[k] - b[k]
    return CameraPath(x, C, b)
