"""One batched KalmanFilter run for 10⁶ consecutive steps: every covariance stays symmetric and positive definite.

The unit test (tests/unit/estimation/test_numerical_health.py) covers 10⁶ filter-steps as
1000 filters × 1000 steps, which fits in CI.  This script runs the literal version: a
batch of filters stepped 10⁶ times in a row (about 2 minutes per path on one core), with
the same hard regime as the test — small process noise (σ = 10⁻³), 30 % of the rows
missing, 5 % with only x, and outages of 100 steps.  Every step checks that each P is
exactly symmetric and that its smallest eigenvalue is positive; the run reports the
smallest λ_min / λ_max met.

Run::

    python benchmarks/long_run_health.py [--steps 1000000] [--filters 16]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from kalmansfm.estimation.kalman import KalmanFilter
from kalmansfm.estimation import constant_velocity_2d

MODEL = constant_velocity_2d(position_noise_std=1e-3, velocity_noise_std=1e-3, measurement_noise_std=1.0)
BLOCK = 10_000  # measurements are drawn in blocks of steps to keep memory flat


def process_noise(path: str) -> np.ndarray:
    Q = MODEL.Q.copy()
    if path == "general":
        Q[0, 1] = Q[1, 0] = 0.5 * np.sqrt(Q[0, 0] * Q[1, 1])  # couples x and y: no fast path
    return Q


def run(path: str, steps: int, filters: int, seed: int = 0) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    truth = np.zeros((filters, 4))
    truth[:, 2:] = rng.normal(0.0, 2.0, (filters, 2))
    kf = KalmanFilter(np.zeros((filters, 4)), MODEL.P0, MODEL.F, MODEL.H, process_noise(path), MODEL.R)
    worst_ratio, worst_asymmetry = np.inf, 0.0
    started = time.perf_counter()
    for first in range(0, steps, BLOCK):
        n = min(BLOCK, steps - first)
        zs = np.empty((n, filters, 2))
        for t in range(n):
            truth = truth @ MODEL.F.T
            zs[t] = truth[:, :2] + rng.normal(0.0, 1.0, (filters, 2))
        zs[rng.random((n, filters)) < 0.30] = np.nan
        zs[rng.random((n, filters)) < 0.05, 1] = np.nan
        for f in rng.choice(filters, max(1, filters // 8), replace=False):
            start = rng.integers(0, n - 100)
            zs[start : start + 100, f] = np.nan
        for t in range(n):
            kf.predict()
            kf.update(zs[t])
            P = np.broadcast_to(kf.P, (filters, 4, 4))
            worst_asymmetry = max(worst_asymmetry, float(np.abs(P - np.swapaxes(P, -1, -2)).max()))
            eig = np.linalg.eigvalsh(P)
            if not eig[:, 0].min() > 0:
                raise SystemExit(f"{path}: P not positive definite at step {first + t}")
            worst_ratio = min(worst_ratio, float((eig[:, 0] / eig[:, -1]).min()))
    if not np.isfinite(kf.x).all():
        raise SystemExit(f"{path}: non-finite state after {steps} steps")
    return {"seconds": time.perf_counter() - started, "worst_ratio": worst_ratio, "worst_asymmetry": worst_asymmetry,
            "decoupled": float(kf.decoupled)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--filters", type=int, default=16)
    args = parser.parse_args()
    print(f"{args.steps} consecutive steps, {args.filters} filters in the batch")
    for path in ("general", "decoupled"):
        r = run(path, args.steps, args.filters)
        print(f"{path:<10} fast path {bool(r['decoupled'])!s:<5} largest |P - Pᵀ| {r['worst_asymmetry']:.1e}  "
              f"smallest λmin/λmax {r['worst_ratio']:.2e}  every P positive definite  {r['seconds']:.0f} s")


if __name__ == "__main__":
    main()
