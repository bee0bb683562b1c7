"""Task 7 of the report as a simulation: a landmark triangulated from a moving camera.

The camera follows the report's path (:func:`kalmansfm.experiments.moving_camera.report_path`,
25 images, 24 pairs); the landmark is projected into every image with focal
length ``focal`` and Gaussian noise of ``pixel_noise_std`` pixels is added to
each image coordinate.  Each image is used by two consecutive pairs.

The defaults, f = 500 px and σ = 10 px (σ/f = 0.02), reproduce the report's
magnitudes (Tables 7.1-7.3): single-pair first-order standard deviations of
tens of metres, and (with ``method="batch"``) a fused error and standard
deviation of about a metre by iteration 24.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from .._validation import check_positive
from ..structure.fusion.landmark import TASK7_DEFAULT_METHOD, check_method, estimate_landmarks, project
from ..structure.geometry.triangulation import check_focal
from .fusion_tasks import FusionTable
from .moving_camera import report_path

__all__ = ["DEFAULT_FOCAL", "DEFAULT_PIXEL_NOISE_STD", "Task7Result", "simulate_task7", "simulate_observations", "task7_table"]

DEFAULT_FOCAL = 500.0
DEFAULT_PIXEL_NOISE_STD = 10.0
N_IMAGES = 25
_METHOD_NAMES = {
    "pairs": "Kalman fusion of pair triangulations (report)",
    "batch": "Gauss-Newton ML, all images",
    "recursive": "Kalman fusion of the images, inverse depth (iterated EKF)",
}


@dataclass(frozen=True)
class Task7Result:
    """One simulated run of Task 7, iteration k = 1..24 uses images k-1 and k.

    Attributes
    ----------
    task : 7.
    title : a one-line description with the method and noise.
    method, focal, pixel_noise_std, seed : the parameters of the run.
    truth : (24, 3) — the landmark in the camera frame of image k (Table 7.1's truth column).
    measured, measured_std : (24, 3) — the single-pair triangulation (images k-1, k)
        and its first-order standard deviation (eq. 34).
    estimate, estimate_std : (24, 3) — the method's estimate after image k and its
        standard deviation.
    estimate_covariance : (24, 3, 3).
    converged : (24,) bool — the estimate exists and its iteration converged.
    measurement_status : (24,) int8 — the pair triangulation's ``PointStatus``.
    """

    task: int
    title: str
    method: str
    focal: float
    pixel_noise_std: float
    seed: int
    truth: np.ndarray
    measured: np.ndarray
    measured_std: np.ndarray
    estimate: np.ndarray
    estimate_std: np.ndarray
    estimate_covariance: np.ndarray
    converged: np.ndarray
    measurement_status: np.ndarray


def check_pixel_noise(pixel_noise_std: object) -> float:
    """Return ``pixel_noise_std`` as a float or raise unless it is finite and > 0 (pixels)."""
    return check_positive("pixel_noise_std", pixel_noise_std, "pixels")


def simulate_observations(
    runs: int, rng: np.random.Generator, focal: float, pixel_noise_std: float
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy images of the report's landmark for ``runs`` independent runs: (truth (25, 3), observations (25, runs, 2))."""
    path = report_path(N_IMAGES)
    clean = project(path.landmark, focal)
    noise = rng.normal(scale=pixel_noise_std, size=(N_IMAGES, runs, 2))
    return path.landmark, clean[:, None, :] + noise


def simulate_task7(
    method: str = TASK7_DEFAULT_METHOD,
    seed: int = 0,
    focal: float = DEFAULT_FOCAL,
    pixel_noise_std: float = DEFAULT_PIXEL_NOISE_STD,
) -> Task7Result:
    """Simulate the report's Task 7 experiment once.

    Parameters
    ----------
    method : {"pairs", "batch", "recursive"}
        ``"pairs"``: the report's Kalman fusion of consecutive pair triangulations;
        ``"batch"``: Gauss-Newton maximum likelihood on all images so far;
        ``"recursive"``: Kalman fusion of the images themselves (inverse depth, iterated EKF).
    seed : int
        Seed of the image noise (``np.random.default_rng(seed)``).
    focal : float
        Focal length in pixels (> 0).
    pixel_noise_std : float
        Standard deviation of the image noise in pixels (> 0).

    Returns
    -------
    Task7Result

    Examples
    --------
    >>> r = simulate_task7("batch", seed=1)
    >>> r.truth.shape, r.estimate.shape
    ((24, 3), (24, 3))
    >>> bool(np.all(np.abs(r.estimate[-1] - r.truth[-1]) < 4 * r.estimate_std[-1]))
    True
    """
    check_method(method)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidInputError(f"seed must be a non-negative integer; got {seed!r}")
    f = check_focal(focal)
    sigma = check_pixel_noise(pixel_noise_std)
    path = report_path(N_IMAGES)
    truth, obs = simulate_observations(1, np.random.default_rng(seed), f, sigma)
    est = estimate_landmarks(obs, path.rotations, path.translations, f, sigma, method=method)
    name = _METHOD_NAMES[method]
    title = f"Task 7: structure from a moving camera, {name}; f = {f:g} px, image noise {sigma:g} px, seed {seed}"
    return Task7Result(
        task=7,
        title=title,
        method=method,
        focal=f,
        pixel_noise_std=sigma,
        seed=int(seed),
        truth=truth[1:],
        measured=est.measurements[1:, 0],
        measured_std=est.measurement_standard_deviations[1:, 0],
        estimate=est.estimates[1:, 0],
        estimate_std=est.standard_deviations[1:, 0],
        estimate_covariance=est.covariances[1:, 0],
        converged=est.converged[1:, 0],
        measurement_status=est.measurement_status[1:, 0],
    )


def task7_table(
    method: str = TASK7_DEFAULT_METHOD,
    seed: int = 0,
    focal: float = DEFAULT_FOCAL,
    pixel_noise_std: float = DEFAULT_PIXEL_NOISE_STD,
) -> FusionTable:
    """Task 7 simulated once, as the report's table: the single-pair triangulation as the
    measurement, the method's estimate as the Kalman columns.

    Examples
    --------
    >>> task7_table("batch", seed=1).estimate.shape
    (24, 3)
    """
    r = simulate_task7(method, seed, focal, pixel_noise_std)
    return FusionTable(r.task, r.title, r.truth, r.measured, r.measured_std, r.estimate, r.estimate_std)
