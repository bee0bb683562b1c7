"""Batched Kalman filtering: kalmansfm vs simdkalman vs a FilterPy loop, side by side in one run.

Constant-velocity model (state 4, measurement 2), random whole-row missing measurements so
that the per-track covariances really differ.  Prints a Markdown table of ns per track-step
(one predict + one update of one track) and the ratios to the peers measured in this run, the
agreement with FilterPy on a subsample, and the peak traced memory of the large run.

Run on one core:

    python benchmarks/bench_kalman.py            # 1 000 000 tracks
    python benchmarks/bench_kalman.py --tracks 100000 --quick

Peers that cannot hold the full size in memory (simdkalman stores every step's covariance) or
are too slow (FilterPy, one Python object per track) are timed on a subsample and reported
per track-step, which is how their cost scales (linear in the number of tracks).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402

import numpy as np  # noqa: E402

from kalmansfm import KalmanFilter  # noqa: E402
from kalmansfm.estimation import constant_velocity_2d  # noqa: E402


def make_problem(N: int, T: int, p_missing: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 640, size=(N, 2))
    vel = rng.normal(scale=2.0, size=(N, 2))
    x0 = np.concatenate([pos, vel], axis=1)
    steps = np.arange(1, T + 1)[:, None, None]
    zs = pos[None] + steps * vel[None] + rng.normal(scale=2.0, size=(T, N, 2))
    zs[rng.random((T, N)) < p_missing] = np.nan
    return x0, zs


class Clock:
    """Wall-clock and CPU time of a block (the machine is shared: CPU time shows our own work)."""

    def __enter__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.wall
        self.cpu = time.process_time() - self.cpu


def best_of(clocks):
    return min(c.wall for c in clocks), min(c.cpu for c in clocks)


def run_kalmansfm(x0, zs, model, repeats=2, **options):
    """Best-of-``repeats`` (wall, CPU) seconds for T predict+update steps; returns (times, final filter)."""
    clocks, kf = [], None
    for _ in range(repeats):
        kf = KalmanFilter(x0, model.P0, model.F, model.H, model.Q, model.R, **options)
        with Clock() as c:
            for z in zs:
                kf.predict()
                kf.update(z)
        clocks.append(c)
    return best_of(clocks), kf


def run_filterpy(x0, zs, model):
    from filterpy.kalman import KalmanFilter as FilterPyKF

    N = x0.shape[0]
    filters = []
    for i in range(N):
        f = FilterPyKF(dim_x=4, dim_z=2)
        f.x = x0[i].copy()
        f.P = model.P0.copy()
        f.F, f.H, f.Q, f.R = model.F, model.H, model.Q, model.R
        filters.append(f)
    with Clock() as c:
        for z in zs:
            for i, f in enumerate(filters):
                f.predict()
                f.update(None if np.isnan(z[i]).any() else z[i])
    return (c.wall, c.cpu), np.array([f.x for f in filters]), np.array([f.P for f in filters])


def run_simdkalman(x0, zs, model, repeats=1):
    import simdkalman

    kf = simdkalman.KalmanFilter(state_transition=model.F, process_noise=model.Q,
                                 observation_model=model.H, observation_noise=model.R)
    # simdkalman updates before it predicts: start it from our first prior.
    m0 = x0 @ model.F.T
    P0 = model.F @ model.P0 @ model.F.T + model.Q
    data = np.ascontiguousarray(np.moveaxis(zs, 0, 1))  # (tracks, steps, 2)
    clocks, result = [], None
    for _ in range(repeats):
        with Clock() as c:
            result = kf.compute(data, 0, initial_value=m0[..., None], initial_covariance=P0, smoothed=False,
                                filtered=True, observations=False)
        clocks.append(c)
    return best_of(clocks), result.filtered.states.mean[:, -1], result.filtered.states.cov[:, -1]


def coupled_model(seed: int = 1):
    """A general dense model (x and y coupled): no structure to exploit."""
    rng = np.random.default_rng(seed)
    base = constant_velocity_2d()
    F = base.F + 0.01 * rng.normal(size=(4, 4))
    A = rng.normal(size=(4, 4))
    Q = base.Q + 0.5 * A @ A.T
    R = np.array([[4.0, 1.0], [1.0, 4.0]])
    return base.__class__(F=F, H=base.H, Q=Q, R=R, P0=base.P0)


def peak_memory(x0, zs, model):
    tracemalloc.start()
    tracemalloc.reset_peak()
    base, _ = tracemalloc.get_traced_memory()
    kf = KalmanFilter(x0, model.P0, model.F, model.H, model.Q, model.R)
    for z in zs:
        kf.predict()
        kf.update(z)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak - base


def machine() -> str:
    cpu = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(line.split(":", 1)[1].strip() for line in fh if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, NumPy {np.__version__}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tracks", type=int, default=1_000_000)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--missing", type=float, default=0.1, help="probability a measurement row is missing")
    ap.add_argument("--filterpy-tracks", type=int, default=500)
    ap.add_argument("--simdkalman-tracks", type=int, default=100_000)
    ap.add_argument("--dense-tracks", type=int, default=100_000, help="size of the general dense comparison")
    ap.add_argument("--quick", action="store_true", help="one repeat, skip the memory pass")
    args = ap.parse_args()
    N, T = args.tracks, args.steps
    reps = 1 if args.quick else 2
    cv = constant_velocity_2d()
    rows = []  # (implementation, tracks, wall ns, CPU ns per track-step)

    def add(name, tracks, times):
        wall, cpu = (t / (tracks * T) * 1e9 for t in times)
        rows.append((name, tracks, wall, cpu))
        print(f"  {name:<58s} {tracks:>9d} tracks  {wall:9.1f} ns wall  {cpu:9.1f} ns CPU per track-step",
              flush=True)
        return np.array([wall, cpu])

    print(f"# bench_kalman: {N} tracks x {T} steps, {args.missing:.0%} rows missing; {machine()}; "
          f"load average at start {os.getloadavg()[0]:.1f}")
    x0, zs = make_problem(N, T, args.missing)
    sec, kf = run_kalmansfm(x0, zs, cv, reps)
    ours = add("kalmansfm, per-track covariance (decoupled, Joseph)", N, sec)
    assert kf.decoupled and not kf.shared_covariance
    sec, _ = run_kalmansfm(x0, zs, cv, reps, joseph=False)
    add("kalmansfm, per-track covariance, joseph=False", N, sec)
    sec, _ = run_kalmansfm(x0, zs, cv, reps, dtype=np.float32)
    add("kalmansfm, per-track covariance, float32", N, sec)
    x_full, zs_full = make_problem(N, T, 0.0)
    sec, kf_shared = run_kalmansfm(x_full, zs_full, cv, reps)
    assert kf_shared.shared_covariance
    shared = add("kalmansfm, shared covariance (every track measured)", N, sec)
    del zs_full, x_full, kf_shared

    n_fp = min(args.filterpy_tracks, N)
    sec, fp_x, fp_P = run_filterpy(x0[:n_fp], zs[:, :n_fp], cv)
    filterpy = add("FilterPy KalmanFilter, one object per track (loop)", n_fp, sec)
    dx = np.abs(kf.x[:n_fp] - fp_x).max()
    dP = np.abs(kf.P[:n_fp] - fp_P).max()

    n_sk = min(args.simdkalman_tracks, N)
    sec, sk_x, sk_P = run_simdkalman(x0[:n_sk], zs[:, :n_sk], cv)
    simd = add("simdkalman (filtered=True), CV model", n_sk, sec)
    dx_sk = np.abs(kf.x[:n_sk] - sk_x).max()

    dm = coupled_model()
    n_d = min(args.dense_tracks, N)
    sec, kf_dense = run_kalmansfm(x0[:n_d], zs[:, :n_d], dm, 1)
    assert not kf_dense.decoupled
    dense = add("kalmansfm, general dense model (coupled F, Q, R)", n_d, sec)
    sec, _ = run_kalmansfm(x0[:n_d], zs[:, :n_d], dm, 1, joseph=False)
    add("kalmansfm, general dense model, joseph=False", n_d, sec)
    sec, skd_x, _ = run_simdkalman(x0[:n_d], zs[:, :n_d], dm)
    simd_dense = add("simdkalman, same general dense model", n_d, sec)
    dx_dense = np.abs(kf_dense.x - skd_x).max()

    print()
    print("| implementation | tracks | ns / track-step (wall) | (CPU) | vs FilterPy loop (wall / CPU) "
          "| vs simdkalman CV (wall / CPU) |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, tracks, wall, cpu in rows:
        print(f"| {name} | {tracks:,} | {wall:.1f} | {cpu:.1f} | {filterpy[0] / wall:.0f}x / {filterpy[1] / cpu:.0f}x "
              f"| {simd[0] / wall:.1f}x / {simd[1] / cpu:.1f}x |")
    print()
    print(f"per-track path: {filterpy[0] / ours[0]:.0f}x (wall) / {filterpy[1] / ours[1]:.0f}x (CPU) faster than "
          f"FilterPy, {simd[0] / ours[0]:.1f}x / {simd[1] / ours[1]:.1f}x faster than simdkalman")
    print(f"shared path: {shared[0]:.1f} ns (wall) / {shared[1]:.1f} ns (CPU) per track-step")
    print(f"general dense model: kalmansfm time / simdkalman time = {dense[0] / simd_dense[0]:.2f} (wall), "
          f"{dense[1] / simd_dense[1]:.2f} (CPU)")
    print(f"max |x - x_FilterPy| = {dx:.2e}, max |P - P_FilterPy| = {dP:.2e} (after {T} steps, {n_fp} tracks)")
    print(f"max |x - x_simdkalman| = {dx_sk:.2e} (CV), {dx_dense:.2e} (dense model)")
    if not args.quick:
        del kf
        peak = peak_memory(x0, zs, cv)
        visible = N * (4 + 16) * 8
        compact = N * (4 + 3) * 8
        print(f"peak traced memory during the per-track run: {peak / 1e6:.0f} MB = {peak / visible:.2f}x the "
              f"(N,4)+(N,4,4) state + covariance arrays ({visible / 1e6:.0f} MB), {peak / compact:.2f}x the compact "
              f"storage ({compact / 1e6:.0f} MB); the {zs.nbytes / 1e6:.0f} MB of measurements are input")


if __name__ == "__main__":
    main()
