"""Is the reported uncertainty honest?  Monte Carlo consistency of fused estimates.

For N independent runs of an experiment with known truth, each estimate x̂ with
covariance P gives the normalised estimation error squared

    NEES = (x̂ - x)ᵀ P⁻¹ (x̂ - x),

which is χ²(d) distributed for a consistent d-dimensional Gaussian estimate.  At
each iteration the mean over N runs, times N, is then χ²(N d), so its 95 %
interval is [χ²_{0.025}(N d), χ²_{0.975}(N d)] / N (Bar-Shalom, Li & Kirubarajan,
*Estimation with Applications to Tracking and Navigation*, sec. 5.4).  Per axis,
a consistent estimate's error lies within 1σ about 68.3 % and within 3σ about
99.7 % of the time.

The verdict ``passed`` is: the mean NEES at the *final* iteration lies inside its
95 % interval.  The result also gives the mean NEES of every iteration, the
first iteration from which every later one is inside its interval
(``consistent_from``), and the mean over all iterations and runs.

Experiments: Task 2 (one distance, truth 40 m, Table 2's measurement standard
deviations, Kalman fusion) and Task 7 (a landmark from a moving camera, methods
``pairs`` and ``batch``, see :mod:`kalmansfm.structure.fusion.landmark`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from ..errors import InvalidInputError
from .._validation import check_choice, check_count
from ..estimation.fusion import fuse_recursive
from ..structure.fusion.landmark import TASK7_DEFAULT_METHOD, check_method, estimate_landmarks
from ..structure.geometry.triangulation import check_focal
from .fusion_tasks import load_task
from .moving_camera import report_path
from .task7 import DEFAULT_FOCAL, DEFAULT_PIXEL_NOISE_STD, N_IMAGES, check_pixel_noise, simulate_observations

__all__ = [
    "ConsistencyResult",
    "consistency_from_errors",
    "nees_interval",
    "run_consistency",
    "task2_consistency",
    "task7_consistency",
]

Progress = Callable[[int], None]
#: What Task 7's consistency judges: the point (x, y, z) in the current camera frame, or the
#: recursive filter's state (inverse depth in the first camera frame).
SPACES = ("point", "inverse_depth")
_CHUNK = 100  # runs simulated together (vectorised), between progress reports
#: The most Monte Carlo runs one call accepts: 10⁵ runs take about 7 minutes and 0.9 GB with Task 7's
#: slowest estimator; far more is a typo, which would run for days before anyone noticed.
MAX_RUNS = 100_000
#: Seconds per run, for the estimate in the refusal (measured with ``kalmansfm consistency --runs 1000``,
#: 2-core machine at load 4.5; Task 2 with ``--runs 100000``).
_SECONDS_PER_RUN = {"kalman": 2e-5, "recursive": 1.4e-3, "batch": 4.4e-3, "pairs": 4e-4}


@dataclass(frozen=True)
class ConsistencyResult:
    """Monte Carlo consistency of one estimator over N runs and K iterations.

    Attributes
    ----------
    task : 2 or 7.
    method : the estimator ("kalman" for Task 2, "pairs" or "batch" for Task 7).
    runs : N.
    dimension : d.
    mean_nees : (K,) — mean NEES over the runs with a usable estimate at iteration k.
    nees_low, nees_high : (K,) — its 95 % chi-square interval.
    valid_runs : (K,) int — runs with a usable estimate (converged, finite, positive definite).
    within_1sigma, within_3sigma : (K, d) — per iteration and axis, the fraction of
        |error| <= 1σ (resp. 3σ), σ the square root of the covariance diagonal.
    parameters : dict — the experiment's settings (seed, focal, noise).
    """

    task: int
    method: str
    runs: int
    dimension: int
    mean_nees: np.ndarray
    nees_low: np.ndarray
    nees_high: np.ndarray
    valid_runs: np.ndarray
    within_1sigma: np.ndarray
    within_3sigma: np.ndarray
    parameters: dict = field(default_factory=dict)

    @property
    def iterations(self) -> int:
        """K."""
        return int(self.mean_nees.shape[0])

    @property
    def inside(self) -> np.ndarray:
        """(K,) bool — the iteration's mean NEES lies inside its 95 % interval."""
        return (self.mean_nees >= self.nees_low) & (self.mean_nees <= self.nees_high)

    @property
    def final_mean_nees(self) -> float:
        """Mean NEES at the last iteration."""
        return float(self.mean_nees[-1])

    @property
    def pooled_mean_nees(self) -> float:
        """Mean NEES over all iterations and runs (weighted by the valid runs)."""
        w = self.valid_runs
        ok = w > 0
        return float(np.sum(self.mean_nees[ok] * w[ok]) / np.sum(w[ok]))

    @property
    def pooled_within_1sigma(self) -> np.ndarray:
        """(d,) fraction of axis errors within 1σ over all iterations and runs."""
        return self._pooled(self.within_1sigma)

    @property
    def pooled_within_3sigma(self) -> np.ndarray:
        """(d,) fraction of axis errors within 3σ over all iterations and runs."""
        return self._pooled(self.within_3sigma)

    def _pooled(self, fractions: np.ndarray) -> np.ndarray:
        w = self.valid_runs[:, None]
        ok = self.valid_runs > 0
        return np.sum(fractions[ok] * w[ok], axis=0) / np.sum(w[ok])

    @property
    def consistent_from(self) -> int | None:
        """First iteration (1-based) from which every mean NEES is inside its interval; None if the last is not."""
        inside = self.inside
        if not inside[-1]:
            return None
        outside = np.flatnonzero(~inside)
        return int(outside[-1]) + 2 if outside.size else 1

    @property
    def passed(self) -> bool:
        """The final iteration's mean NEES lies inside its 95 % interval."""
        return bool(self.inside[-1])

    @property
    def verdict(self) -> str:
        """"consistent", "over-confident" (NEES too large) or "under-confident" (too small)."""
        if self.passed:
            return "consistent"
        return "over-confident" if self.final_mean_nees > self.nees_high[-1] else "under-confident"


def nees_interval(runs: int | np.ndarray, dimension: int, confidence: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided interval of the mean NEES of ``runs`` consistent d-dimensional estimates.

    N × mean NEES ~ χ²(N d), so the interval is χ²_{(1∓c)/2}(N d) / N.

    Examples
    --------
    >>> lo, hi = nees_interval(100, 3)
    >>> float(lo.round(3)), float(hi.round(3))
    (2.539, 3.499)
    """
    n = np.asarray(runs, dtype=float)
    alpha = 1.0 - confidence
    with np.errstate(invalid="ignore", divide="ignore"):
        lo = stats.chi2.ppf(alpha / 2, n * dimension) / n
        hi = stats.chi2.ppf(1 - alpha / 2, n * dimension) / n
    return np.where(n > 0, lo, np.nan), np.where(n > 0, hi, np.nan)


def consistency_from_errors(
    errors: np.ndarray,
    covariances: np.ndarray,
    valid: np.ndarray | None = None,
    *,
    task: int = 0,
    method: str = "",
    parameters: dict | None = None,
) -> ConsistencyResult:
    """Consistency statistics from estimation errors and covariances of N runs.

    Parameters
    ----------
    errors : (K, N, d) — estimate minus truth.
    covariances : (K, N, d, d) — the estimator's covariances.
    valid : (K, N) bool, optional — runs to use at each iteration (default: every
        finite error with a positive-definite covariance).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> r = consistency_from_errors(rng.normal(size=(1, 2000, 2)), np.broadcast_to(np.eye(2), (1, 2000, 2, 2)))
    >>> r.passed, r.within_1sigma.round(2)
    (True, array([[0.68, 0.67]]))
    """
    e = np.asarray(errors, dtype=float)
    P = np.asarray(covariances, dtype=float)
    if e.ndim != 3 or P.shape != e.shape + (e.shape[-1],):
        raise InvalidInputError(f"errors (K, N, d) and covariances (K, N, d, d) do not match: {e.shape}, {P.shape}")
    K, N, d = e.shape
    finite = np.isfinite(e).all(-1) & np.isfinite(P).all((-2, -1))
    P_safe = np.where(finite[..., None, None], P, np.eye(d))
    e_safe = np.where(finite[..., None], e, 0.0)
    pd = np.linalg.eigvalsh(P_safe)[..., 0] > 0
    use = finite & pd
    if valid is not None:
        use &= np.asarray(valid, dtype=bool)
    P_safe = np.where(use[..., None, None], P_safe, np.eye(d))
    nees = np.einsum("kni,kni->kn", e_safe, np.linalg.solve(P_safe, e_safe[..., None])[..., 0])
    sigma = np.sqrt(np.diagonal(P_safe, axis1=-2, axis2=-1))
    z = np.abs(e_safe) / sigma
    count = use.sum(axis=1)
    denom = np.maximum(count, 1)
    mean_nees = np.where(count > 0, np.sum(np.where(use, nees, 0.0), axis=1) / denom, np.nan)
    within1 = np.sum(use[..., None] & (z <= 1.0), axis=1) / denom[:, None]
    within3 = np.sum(use[..., None] & (z <= 3.0), axis=1) / denom[:, None]
    within1[count == 0] = np.nan
    within3[count == 0] = np.nan
    lo, hi = nees_interval(count, d)
    return ConsistencyResult(task, method, N, d, mean_nees, lo, hi, count, within1, within3, dict(parameters or {}))


def _duration(seconds: float) -> str:
    """A rough duration in words.

    Examples
    --------
    >>> _duration(40), _duration(4e3), _duration(4e6), _duration(4e9)
    ('40 seconds', '67 minutes', '46 days', '127 years')
    """
    for unit, size in (("years", 365.25 * 86400), ("days", 86400), ("hours", 3600 * 3), ("minutes", 60)):
        if seconds >= 2 * size:
            divisor = 3600 if unit == "hours" else size
            return f"{seconds / divisor:.0f} {unit}"
    return f"{seconds:.0f} seconds"


def _check_runs_seed(runs: object, seed: object, method: str) -> tuple[int, int]:
    count = check_count("runs", runs, 2)
    if count > MAX_RUNS:
        per_run = _SECONDS_PER_RUN[method]
        raise InvalidInputError(
            f"runs must be an integer in 2 … {MAX_RUNS}; got {count} (about {_duration(count * per_run)} at "
            f"{per_run * 1e3:.2g} ms per run)"
        )
    return count, check_count("seed", seed, 0)


def _chunks(runs: int) -> list[int]:
    return [min(_CHUNK, runs - start) for start in range(0, runs, _CHUNK)]


def task2_consistency(runs: int = 300, seed: int = 0, progress: Progress | None = None) -> ConsistencyResult:
    """Task 2: Kalman fusion of one distance (truth 40 m) measured with Table 2's standard deviations.

    Each run draws z_k = 40 + σ_k ε_k (σ_k from Table 2) and fuses them with
    :func:`~kalmansfm.fuse_recursive`; a linear Gaussian problem, so consistent.

    Examples
    --------
    >>> task2_consistency(runs=200, seed=1).passed
    True
    """
    runs, seed = _check_runs_seed(runs, seed, "kalman")
    task = load_task(2)
    truth = float(task.truth[0, 0])
    std = task.measurement_std[:, 0]  # (K,)
    rng = np.random.default_rng(seed)
    errors, covs = [], []
    for n in _chunks(runs):
        z = truth + std[:, None] * rng.normal(size=(std.size, n))
        fused = fuse_recursive(z[..., None], np.broadcast_to((std**2)[:, None, None, None], (std.size, n, 1, 1)))
        errors.append(fused.estimates - truth)
        covs.append(fused.covariances)
        if progress is not None:
            progress(n)
    return consistency_from_errors(
        np.concatenate(errors, axis=1), np.concatenate(covs, axis=1), task=2, method="kalman",
        parameters={"seed": seed, "truth": truth},
    )


def task7_consistency(
    method: str = TASK7_DEFAULT_METHOD,
    runs: int = 300,
    seed: int = 0,
    focal: float = DEFAULT_FOCAL,
    pixel_noise_std: float = DEFAULT_PIXEL_NOISE_STD,
    progress: Progress | None = None,
    space: str = "point",
) -> ConsistencyResult:
    """Task 7: the report's landmark from a moving camera, N independent noise draws.

    Iterations 1..24 are the estimates after images 1..24.  A run whose estimate
    is flagged (not converged, no estimate) is left out of that iteration and
    counted in ``valid_runs``.  ``space="inverse_depth"`` (method ``recursive``)
    judges the filter's own state, (x/z, y/z, 1/z) of the landmark in the first
    camera frame, which exists in every run from the first pair on, also while the
    depth is not determined and the point has no finite (x, y, z).

    Examples
    --------
    >>> r = task7_consistency("batch", runs=50, seed=0, pixel_noise_std=1.0)
    >>> r.passed, r.iterations
    (True, 24)
    """
    check_method(method)
    check_choice("space", space, SPACES)
    if space == "inverse_depth" and method != "recursive":
        raise InvalidInputError(f"space 'inverse_depth' is the recursive filter's state; method is {method!r}")
    runs, seed = _check_runs_seed(runs, seed, method)
    f = check_focal(focal)
    sigma = check_pixel_noise(pixel_noise_std)
    path = report_path(N_IMAGES)
    rng = np.random.default_rng(seed)
    errors, covs, valid = [], [], []
    for n in _chunks(runs):
        truth, obs = simulate_observations(n, rng, f, sigma)
        est = estimate_landmarks(obs, path.rotations, path.translations, f, sigma, method=method)
        if space == "point":
            errors.append(est.estimates[1:] - truth[1:, None, :])
            covs.append(est.covariances[1:])
            valid.append(est.converged[1:])
        else:
            # every run starts at images (0, 1): the state is the landmark's inverse depth in frame 0
            x, y, z = truth[0]
            errors.append(est.inverse_depth[1:] - np.array([x / z, y / z, 1.0 / z]))
            covs.append(est.inverse_depth_covariances[1:])
            valid.append(np.isfinite(est.inverse_depth[1:]).all(axis=2))
        if progress is not None:
            progress(n)
    return consistency_from_errors(
        np.concatenate(errors, axis=1), np.concatenate(covs, axis=1), np.concatenate(valid, axis=1),
        task=7, method=method,
        parameters={"seed": seed, "focal": f, "pixel_noise_std": sigma, "noise_over_focal": sigma / f,
                    "space": space},
    )


def run_consistency(
    task: int,
    method: str | None = None,
    runs: int = 300,
    seed: int = 0,
    focal: float = DEFAULT_FOCAL,
    pixel_noise_std: float = DEFAULT_PIXEL_NOISE_STD,
    progress: Progress | None = None,
    space: str = "point",
) -> ConsistencyResult:
    """Dispatch to :func:`task2_consistency` or :func:`task7_consistency`.

    ``method`` None is Task 2's Kalman filter, and for Task 7
    :data:`~kalmansfm.structure.fusion.landmark.TASK7_DEFAULT_METHOD` (``pairs``, the report's scheme).
    """
    if task == 2:
        if method not in (None, "kalman"):
            raise InvalidInputError(f"method applies to task 7 only (task 2 is the Kalman filter); got {method!r}")
        if space != "point":
            raise InvalidInputError(f"space applies to task 7 only; got {space!r}")
        return task2_consistency(runs, seed, progress)
    if task == 7:
        return task7_consistency(TASK7_DEFAULT_METHOD if method is None else method, runs, seed, focal, pixel_noise_std, progress, space)
    raise InvalidInputError(f"task must be 2 or 7; got {task!r}")
