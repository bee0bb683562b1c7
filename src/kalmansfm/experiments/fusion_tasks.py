"""The fusion experiments (Tasks 1-6) of Thomas & Oliensis, *Fusing Structure by Kalman Filtering*.

The measurement columns of the report's Tables 1-6 (ground truth, measurement,
standard deviation of its noise) ship as package data in
``kalmansfm/data/fusion_tasks/task{N}.csv``, each with a header naming its source,
units and motion.  :func:`load_task` reads one; :func:`run_task` fuses its
measurements with :func:`~kalmansfm.fuse_recursive` and returns the table with
the Kalman columns computed by this library (the report's printed Kalman values
are used only by the tests).

The motions x_k = C_{k-1} x_{k-1} - b_{k-1} between iterations:

* Tasks 1, 2, 4: static, C = I, b = 0.
* Task 3: the observer walks 1 m towards the pole, C = 1, b = 1 m.
* Task 5 (recovered from the ground truth): C = 2 n nᵀ - I, the rotation by π
  about n = (2, 3, 1)/√14, every step; b = 0.
* Task 6 (recovered from the ground truth): C alternates R_y(+1°), R_y(-1°)
  (starting with +1°), b = (0, 0, 1) m every step.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Callable
from dataclasses import dataclass, fields
from importlib import resources

import numpy as np

from ..errors import InvalidInputError
from ..estimation import fuse_recursive
from .moving_camera import rotation_about_y, yaw_and_forward_motion

__all__ = ["FusionTable", "FusionTask", "available_tasks", "load_task", "run_task", "rotation_about_y"]


@dataclass(frozen=True)
class FusionTable:
    """One fusion experiment, row k = after measurement k.

    Attributes
    ----------
    task : int
        The task number of the report.
    title : str
        A one-line title.
    truth, measured, measured_std, estimate, estimate_std : (K, d) float64
        Ground truth, measurement, standard deviation of the measurement noise,
        fused estimate and the square roots of the diagonal of its covariance,
        all in the sensor frame of iteration k. d = 1 for a scalar quantity.

    Examples
    --------
    >>> t = FusionTable(1, "two readings", np.array([[10.0], [10.0]]), np.array([[10.2], [9.9]]),
    ...                 np.ones((2, 1)), np.array([[10.2], [10.05]]), np.array([[1.0], [0.7071]]))
    >>> t.iterations, t.dimension
    (2, 1)
    """

    task: int
    title: str
    truth: np.ndarray
    measured: np.ndarray
    measured_std: np.ndarray
    estimate: np.ndarray
    estimate_std: np.ndarray

    def __post_init__(self) -> None:
        shape = None
        for f in fields(self)[2:]:
            value = np.asarray(getattr(self, f.name), dtype=np.float64)
            if value.ndim != 2:
                raise InvalidInputError(f"FusionTable.{f.name} must have shape (K, d); got {value.shape}")
            shape = shape or (f.name, value.shape)
            if value.shape != shape[1]:
                raise InvalidInputError(
                    f"FusionTable.{f.name} must have the shape of {shape[0]}, {shape[1]}; got {value.shape}"
                )
            object.__setattr__(self, f.name, value)

    @property
    def iterations(self) -> int:
        """Number of rows K."""
        return self.truth.shape[0]

    @property
    def dimension(self) -> int:
        """Dimension d of the fused quantity."""
        return self.truth.shape[1]


@dataclass(frozen=True)
class FusionTask:
    """The measurement side of one fusion experiment.

    Attributes
    ----------
    number : int
        Task number in the report.
    title : str
        One-line title.
    truth, measurements, measurement_std : (K, d) float64
        Ground truth, measurement and standard deviation of each coordinate's
        noise (the measurement covariance is diagonal), in the sensor frame of
        iteration k; d = 1 for Tasks 1-3, d = 3 for Tasks 4-6.
    rotations : (K-1, d, d) float64
        C_k of the motion x_{k+1} = C_k x_k - b_k.
    translations : (K-1, d) float64
        b_k of the motion.
    description : str
        Source, columns, units and motion, as given in the data file's header.
    """

    number: int
    title: str
    truth: np.ndarray
    measurements: np.ndarray
    measurement_std: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    description: str

    @property
    def measurement_covariances(self) -> np.ndarray:
        """(K, d, d) diagonal covariances diag(measurement_std²)."""
        K, d = self.measurements.shape
        cov = np.zeros((K, d, d))
        idx = np.arange(d)
        cov[:, idx, idx] = self.measurement_std**2
        return cov


Motion = Callable[[int], tuple[np.ndarray, np.ndarray]]


def _static(d: int) -> Motion:
    return lambda steps: (np.broadcast_to(np.eye(d), (steps, d, d)).copy(), np.zeros((steps, d)))


def _walking_observer(steps: int) -> tuple[np.ndarray, np.ndarray]:
    # x_k = x_{k-1} - 1 m
    return np.ones((steps, 1, 1)), np.ones((steps, 1))


def _half_turn_about_fixed_axis(steps: int) -> tuple[np.ndarray, np.ndarray]:
    # Rotation by π about the unit axis n: C = 2 n nᵀ - I.
    n = np.array([2.0, 3.0, 1.0]) / np.sqrt(14.0)
    C = 2.0 * np.outer(n, n) - np.eye(3)
    return np.broadcast_to(C, (steps, 3, 3)).copy(), np.zeros((steps, 3))


_MOTIONS: dict[int, tuple[int, Motion]] = {
    1: (1, _static(1)),
    2: (1, _static(1)),
    3: (1, _walking_observer),
    4: (3, _static(3)),
    5: (3, _half_turn_about_fixed_axis),
    6: (3, yaw_and_forward_motion),
}


def available_tasks() -> list[int]:
    """The task numbers :func:`load_task` knows.

    Examples
    --------
    >>> available_tasks()
    [1, 2, 3, 4, 5, 6]
    """
    return sorted(_MOTIONS)


def _check_number(number: object) -> int:
    tasks = available_tasks()
    if isinstance(number, bool) or not isinstance(number, (int, np.integer)) or int(number) not in tasks:
        raise InvalidInputError(f"unknown task {number}; tasks {tasks[0]}–{tasks[-1]} are available")
    return int(number)


def _read_csv(number: int, d: int) -> tuple[list[str], np.ndarray]:
    name = f"task{number}.csv"
    text = resources.files("kalmansfm").joinpath("data", "fusion_tasks", name).read_text(encoding="utf-8")
    lines = text.splitlines()
    comments = [line[1:].strip() for line in lines if line.startswith("#")]
    rows = list(csv.reader(io.StringIO("\n".join(line for line in lines if line and not line.startswith("#")))))
    axes = [""] if d == 1 else ["_x", "_y", "_z"]
    expected = ["iter"] + [f"{col}{a}" for col in ("truth", "meas", "meas_std") for a in axes]
    if rows[0] != expected:
        raise InvalidInputError(f"{name}: header must be {','.join(expected)}; got {','.join(rows[0])}")
    values = np.array(rows[1:], dtype=np.float64)
    if not np.array_equal(values[:, 0], np.arange(1, len(values) + 1)):
        raise InvalidInputError(f"{name}: the iter column must count 1, 2, 3, ...")
    return comments, values[:, 1:]


def load_task(number: int) -> FusionTask:
    """Load the measurement columns and the known motion of Task ``number`` (1-6).

    Raises
    ------
    InvalidInputError
        If there is no such task.

    Examples
    --------
    >>> task = load_task(6)
    >>> task.measurements.shape, task.rotations.shape, task.translations[0]
    ((24, 3), (23, 3, 3), array([0., 0., 1.]))
    >>> load_task(3).truth[:3, 0]
    array([1000.,  999.,  998.])
    """
    number = _check_number(number)
    d, motion = _MOTIONS[number]
    comments, values = _read_csv(number, d)
    truth, measurements, std = values[:, :d], values[:, d : 2 * d], values[:, 2 * d :]
    rotations, translations = motion(len(values) - 1)
    return FusionTask(
        number=number,
        title=comments[0],
        truth=truth,
        measurements=measurements,
        measurement_std=std,
        rotations=rotations,
        translations=translations,
        description="\n".join(comments[1:]),
    )


def run_task(number: int) -> FusionTable:
    """Fuse the measurements of Task ``number`` recursively and return the report's table.

    The Kalman columns are computed by :func:`~kalmansfm.fuse_recursive` from the
    measurement columns and the known motion; nothing is read from the report's
    printed Kalman output.

    Examples
    --------
    >>> table = run_task(2)
    >>> table.estimate[:3, 0].round(3), table.estimate_std[:3, 0].round(4)
    (array([39.602, 39.568, 37.673]), array([1.6247, 1.1792, 0.8095]))
    """
    task = load_task(number)
    fused = fuse_recursive(task.measurements, task.measurement_covariances, task.rotations, task.translations)
    return FusionTable(
        task=task.number,
        title=task.title,
        truth=task.truth,
        measured=task.measurements,
        measured_std=task.measurement_std,
        estimate=fused.estimates,
        estimate_std=fused.standard_deviations,
    )
