"""Batched Kalman filtering at the memory floor: kalmansfm vs the floor pass, simdkalman and FilterPy, in one run.

Constant-velocity model (state 4, measurement 2), random whole-row missing measurements so
that the per-track covariances really differ.  A track-step is one ``predict()`` plus one
``update(z)`` of one track, through the public class, as a user's loop writes it.

The **floor pass** is one in-place NumPy ``a += b`` over an (N, 10) array: it reads and
writes 10 numbers per track (a track's state and covariance, 4 + 3 unique ones, and its
measurement, rounded up), so it is what any filter costs that touches a track's numbers
once per step.  It is timed in the same run, alternating with the filter, and every
filter row is also given as a multiple of it (same dtype).

Printed, each with the load average:

* the main table at ``--tracks`` (default 10⁶) × ``--steps`` (30): kalmansfm with 1 and 2
  threads (numba), float64 and float32, per-track and shared covariances, the general dense
  model (compiled kernel vs the NumPy reference functions), simdkalman and FilterPy;
* the size sweep ``--sizes`` (default 10⁵, 10⁶, 4·10⁶): floor pass and kalmansfm, 1 and 2
  threads, float64 and float32;
* agreement with the dense NumPy reference (``kalman_predict`` + ``kalman_update`` on (N, 4, 4)
  covariances) at ``--tracks``, as the largest relative difference of a track's state and
  covariance, and with FilterPy and simdkalman;
* the first call's cost in a fresh process: import, compilation with an empty numba cache,
  and loading from the cache (``cache=True``) the second time, below the engine's threshold
  (NumPy twins: nothing to compile) and above it;
* peak traced memory of the per-track run;
* with ``--tracker``: the share of ``kalmansfm.track``'s time spent in the filter on the
  built-in scene with 500 detected features (this alone, then exit);
* with ``--twins``: ms per step on the compiled kernels and on their NumPy twins (which the
  filter runs below ``engine.COMPILED_MIN_TRACKS`` tracks) from 10 to 4096 tracks (alone, then exit).

Run:

    python benchmarks/bench_kalman.py                  # the whole set, ~12 min on 2 cores
    python benchmarks/bench_kalman.py --quick          # 10⁵ tracks, no sweep, no first-call or memory pass
    python benchmarks/bench_kalman.py --tracker
    python benchmarks/bench_kalman.py --twins          # the NumPy twins' extra cost per step, small sizes

Peers that cannot hold the full size in memory (simdkalman stores every step's covariance) or
are too slow (FilterPy, one Python object per track) are timed on a subsample and reported
per track-step, which is how their cost scales (linear in the number of tracks).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"  # NumPy's BLAS on one thread; numba's threads are set per row below

import argparse  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from pathlib import Path  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402

from kalmansfm import KalmanFilter  # noqa: E402
from kalmansfm.estimation import constant_velocity_2d  # noqa: E402
from kalmansfm.estimation.kalman import kalman_predict, kalman_update  # noqa: E402


def make_problem(N: int, T: int, p_missing: float, seed: int = 0, dtype=np.float64):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0, 640, size=(N, 2))
    vel = rng.normal(scale=2.0, size=(N, 2))
    x0 = np.concatenate([pos, vel], axis=1).astype(dtype)
    zs = np.empty((T, N, 2), dtype=dtype)
    for t in range(T):  # step by step: no (T, N, 2) float64 temporaries at 4·10⁶ tracks
        zs[t] = pos + (t + 1) * vel + rng.normal(scale=2.0, size=(N, 2))
        zs[t][rng.random(N) < p_missing] = np.nan
    return x0, zs


def load() -> str:
    return f"{os.getloadavg()[0]:.1f}"


class Clock:
    """Wall-clock and CPU seconds of a block (on a shared machine the CPU time shows our own work)."""

    def __enter__(self):
        self.wall, self.cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self.wall
        self.cpu = time.process_time() - self.cpu

    @property
    def seconds(self) -> np.ndarray:
        return np.array([self.wall, self.cpu])


def floor_pass(N: int, dtype) -> callable:
    """One in-place a += b over (N, 10) (the memory floor of a step); returns a function timing T of them."""
    a = np.ones((N, 10), dtype=dtype)
    b = np.full((N, 10), 1e-9, dtype=dtype)

    def run(T: int) -> np.ndarray:
        with Clock() as c:
            for _ in range(T):
                np.add(a, b, out=a)  # a += b
        return c.seconds
    return run


def filter_loop(x0, zs, model, T, **options) -> callable:
    """A user's loop: T predict + update steps; the measurements cycle through zs."""
    def run(_: int) -> np.ndarray:
        kf = KalmanFilter(x0, model.P0, model.F, model.H, model.Q, model.R, **options)
        with Clock() as c:
            for t in range(T):
                kf.predict()
                kf.update(zs[t % len(zs)])
        run.last = kf
        return c.seconds
    return run


def alternate(named: dict, T: int, repeats: int) -> dict:
    """Best-of-``repeats`` (wall, CPU) seconds of each timing function, alternating in every round."""
    best = {name: np.array([np.inf, np.inf]) for name in named}
    for _ in range(repeats):
        for name, (fn, threads) in named.items():
            numba.set_num_threads(threads)
            best[name] = np.minimum(best[name], fn(T))
    return best


def warm_up(x0, zs, model, dtype) -> None:
    """Compile (or load from the cache) every kernel the timed loops use, outside the timings."""
    small = min(2 * 8192 + 1, x0.shape[0])
    partial = zs[:, :small].copy()
    partial[:, ::20, 1] = np.nan
    for options in ({}, {"joseph": False}):
        filter_loop(x0[:small], zs[:, :small], model, 2, dtype=dtype, **options)(0)
    filter_loop(x0[:small], partial, model, 2, dtype=dtype)(0)
    filter_loop(x0[:small], np.nan_to_num(zs[:, :small]), model, 2, dtype=dtype)(0)


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
    return c.seconds, np.array([f.x for f in filters]), np.array([f.P for f in filters])


def run_simdkalman(x0, zs, model):
    import simdkalman

    kf = simdkalman.KalmanFilter(state_transition=model.F, process_noise=model.Q,
                                 observation_model=model.H, observation_noise=model.R)
    # simdkalman updates before it predicts: start it from our first prior.
    m0 = x0 @ model.F.T
    P0 = model.F @ model.P0 @ model.F.T + model.Q
    data = np.ascontiguousarray(np.moveaxis(zs, 0, 1))  # (tracks, steps, 2)
    with Clock() as c:
        result = kf.compute(data, 0, initial_value=m0[..., None], initial_covariance=P0, smoothed=False,
                            filtered=True, observations=False)
    return c.seconds, result.filtered.states.mean[:, -1], result.filtered.states.cov[:, -1]


def run_numpy_reference(x0, zs, model):
    """The pure NumPy reference functions, (N, 4, 4) covariances: what the tests compare the kernels with."""
    x, P = x0.copy(), np.broadcast_to(model.P0, (x0.shape[0], 4, 4)).copy()
    with Clock() as c:
        for z in zs:
            x, P = kalman_predict(x, P, model.F, model.Q)
            result = kalman_update(x, P, z, model.H, model.R)
            x, P = result.x, np.broadcast_to(result.P, P.shape)
    return c.seconds, x, P


def run_decoupled_reference(x0, zs, model):
    """The NumPy decoupled constant-velocity path (chunked elementwise passes), which the filter ran
    before the compiled kernels and which the tests now compare the kernels with (tests/reference)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from reference import decoupled as reference

    from kalmansfm.estimation import _decoupled

    q = _decoupled.axis_blocks(model.Q)[:1]
    r = _decoupled.diagonal_noise(model.R)
    X = np.ascontiguousarray(x0.T)
    C = np.ascontiguousarray(np.broadcast_to(_decoupled.axis_blocks(model.P0)[:1, :, None], (1, 3, x0.shape[0])))
    with Clock() as c:
        for z in zs:
            X, C = reference.predict(X, C, 1.0, q, None)
            X, C, _ = reference.update(X, C, z, r, True, np.isnan(z))
    return c.seconds, X.T


def coupled_model(seed: int = 1):
    """A general dense model (x and y coupled): no structure to exploit."""
    rng = np.random.default_rng(seed)
    base = constant_velocity_2d()
    F = base.F + 0.01 * rng.normal(size=(4, 4))
    A = rng.normal(size=(4, 4))
    Q = base.Q + 0.5 * A @ A.T
    R = np.array([[4.0, 1.0], [1.0, 4.0]])
    return base.__class__(F=F, H=base.H, Q=Q, R=R, P0=base.P0)


def relative_difference(a: np.ndarray, ref: np.ndarray) -> float:
    """Largest over tracks of max |a - ref| / max |ref| within the track."""
    axes = tuple(range(1, ref.ndim))
    return float((np.abs(a - ref).max(axis=axes) / np.abs(ref).max(axis=axes)).max())


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


FIRST_CALL = """
import time
t0 = time.perf_counter()
import numpy as np
from kalmansfm import KalmanFilter
from kalmansfm.estimation import constant_velocity_2d
t1 = time.perf_counter()
m = constant_velocity_2d()
F, Q, N = ({F}, {Q}, {N})
zs = np.random.default_rng(0).normal(size=(2, N, 2))
zs[0, ::10] = np.nan
kf = KalmanFilter(np.zeros((N, 4)), m.P0, F, m.H, Q, m.R)
for z in zs:
    kf.predict()
    kf.update(z)
t2 = time.perf_counter()
print(t1 - t0, t2 - t1)
"""


def first_call_costs() -> list[str]:
    """Import time and first predict+update (per-track covariances) in fresh processes: below the engine's
    threshold (NumPy twins, nothing compiled) and above it (compiled kernels: compiled, then loaded from the cache)."""
    from kalmansfm.estimation.engine import COMPILED_MIN_TRACKS

    lines = []
    cv, coupled = ("m.F", "m.Q"), ("m.F + 0.01", "m.Q + 0.1")
    for N in (COMPILED_MIN_TRACKS // 2, 100 * COMPILED_MIN_TRACKS):
        with tempfile.TemporaryDirectory() as cache:
            env = {**os.environ, "NUMBA_CACHE_DIR": cache}
            for label, (F, Q) in (("constant-velocity model (decoupled kernels)", cv), ("general dense model", coupled)):
                for state in ("empty cache", "second process, same cache"):
                    out = subprocess.run([sys.executable, "-c", FIRST_CALL.format(F=F, Q=Q, N=N)], env=env, check=True,
                                         capture_output=True, text=True).stdout.split()
                    lines.append(f"| {label} | {N:,} | {state} | {float(out[0]):.2f} | {float(out[1]):.2f} |")
    return lines


def twin_costs(sizes=(10, 100, 500, 1000, 2000, 4096), steps: int = 40, repeats: int = 3) -> list[str]:
    """ms per predict + update step on the compiled kernels and on their NumPy twins, both forced, for the
    constant-velocity form (shared R) and the tracker's pattern (prior read first, a per-track 2×2 R: general form)."""
    from kalmansfm.estimation import engine

    cv = constant_velocity_2d()
    before = engine.COMPILED_MIN_TRACKS

    def per_step(N, form, threshold):
        engine.COMPILED_MIN_TRACKS = threshold
        rng = np.random.default_rng(0)
        kf = KalmanFilter(rng.normal(scale=10, size=(N, 4)), cv.P0, cv.F, cv.H, cv.Q, cv.R)
        zs = rng.normal(size=(steps, N, 2))
        zs[:, ::10] = np.nan
        R = np.broadcast_to(np.array([[0.3, 0.05], [0.05, 0.2]]), (N, 2, 2)).copy()
        best = np.inf
        for _ in range(repeats):
            with Clock() as c:
                for z in zs:
                    kf.predict()
                    if form == "tracker":
                        kf.x_prior, kf.P_prior
                        kf.update(z, R=R)
                    else:
                        kf.update(z)
            best = min(best, c.wall / steps)
        return best * 1e3

    lines = ["| form | tracks | compiled kernel ms/step | NumPy twin ms/step | twin − kernel |", "|---|---:|---:|---:|---:|"]
    try:
        for form in ("constant-velocity", "tracker"):
            for N in sizes:
                per_step(N, form, 0)  # compiled or loaded outside the timing
                kernel, twin = per_step(N, form, 0), per_step(N, form, 2**62)
                lines.append(f"| {form} | {N:,} | {kernel:.3f} | {twin:.3f} | {twin - kernel:+.3f} |")
    finally:
        engine.COMPILED_MIN_TRACKS = before
    lines.append(f"(load {load()})")
    return lines


def tracker_share(features: int = 500, repeats: int = 5) -> str:
    """Share of kalmansfm.track's wall time spent in KalmanFilter (built-in scene, detected features)."""
    import kalmansfm
    from kalmansfm.scenes import render_scene
    from kalmansfm.tracking.detect import detect_corners

    spent = [0.0]
    depth = [0]

    def timed(fn):
        def inner(*args, **kwargs):
            depth[0] += 1
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                depth[0] -= 1
                if depth[0] == 0:
                    spent[0] += time.perf_counter() - start
        return inner

    for name in ("__init__", "predict", "update"):
        setattr(KalmanFilter, name, timed(getattr(KalmanFilter, name)))
    for name in ("x", "P", "x_prior", "P_prior"):
        prop = getattr(KalmanFilter, name)
        setattr(KalmanFilter, name, property(timed(prop.fget), prop.fset))
    frames = list(render_scene(seed=0).frames)
    points = detect_corners(frames[0], features, 0.01, 5.0)
    kalmansfm.track(frames[:3], points)  # warm-up: kernels compiled or loaded
    runs = []
    for _ in range(repeats):
        spent[0] = 0.0
        start = time.perf_counter()
        kalmansfm.track(frames, points)
        runs.append((time.perf_counter() - start, spent[0]))
    total, filt = min(runs)
    shares = sorted(f / t for t, f in runs)
    return (f"kalmansfm.track, built-in scene, {len(points)} features, {len(frames)} frames (best of {repeats}): "
            f"{total * 1e3:.0f} ms, of which KalmanFilter {filt * 1e3:.1f} ms = {filt / len(frames) * 1e3:.3f} ms/frame "
            f"= {100 * filt / total:.1f} % (median share over the runs {100 * shares[len(shares) // 2]:.1f} %); "
            f"load {load()}")


def machine() -> str:
    cpu = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(line.split(":", 1)[1].strip() for line in fh if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return (f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, NumPy {np.__version__}, "
            f"numba {numba.__version__}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tracks", type=int, default=1_000_000)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--missing", type=float, default=0.1, help="probability a measurement row is missing")
    ap.add_argument("--sizes", default="100000,1000000,4000000", help="track counts of the size sweep")
    ap.add_argument("--threads", default="1,2", help="numba thread counts of the kalmansfm rows")
    ap.add_argument("--repeats", type=int, default=5, help="best of this many alternating rounds")
    ap.add_argument("--filterpy-tracks", type=int, default=500)
    ap.add_argument("--simdkalman-tracks", type=int, default=100_000)
    ap.add_argument("--dense-tracks", type=int, default=100_000, help="size of the general dense model rows")
    ap.add_argument("--quick", action="store_true", help="10⁵ tracks, no sweep, no first-call or memory pass")
    ap.add_argument("--tracker", action="store_true", help="only the tracker's filter share")
    ap.add_argument("--twins", action="store_true", help="only the per-step cost of the NumPy twins against the kernels")
    args = ap.parse_args()
    if args.tracker:
        print(tracker_share())
        return
    if args.twins:
        print("\n".join(twin_costs()))
        return
    if args.quick:
        args.tracks, args.repeats, args.sizes = min(args.tracks, 100_000), 2, ""
    N, T = args.tracks, args.steps
    threads = [int(t) for t in args.threads.split(",")]
    cv = constant_velocity_2d()
    print(f"# bench_kalman: {N} tracks x {T} steps, {args.missing:.0%} rows missing; {machine()}; "
          f"load average at start {load()}", flush=True)

    rows = []  # (name, tracks, (wall, CPU) seconds, the same of the floor pass of that dtype, or None)

    def add(name, tracks, seconds, floor=None):
        rows.append((name, tracks, seconds, floor))
        ns = seconds / (tracks * T) * 1e9
        extra = f"  = {seconds[0] / floor[0]:.2f}x the floor pass" if floor is not None else ""
        print(f"  {name:<66s} {tracks:>9d} tracks {ns[0]:9.2f} ns/track-step wall, {ns[1]:9.2f} CPU{extra}  "
              f"(load {load()})", flush=True)

    # -- main table: floor pass and kalmansfm, float64 and float32, 1 and 2 threads ---------------
    results = {}
    for dtype in (np.float64, np.float32):
        x0, zs = make_problem(N, T, args.missing, dtype=dtype)
        warm_up(x0, zs, cv, dtype)
        named = {"floor": (floor_pass(N, dtype), 1)}
        for k in threads:
            named[f"per-track {k}"] = (filter_loop(x0, zs, cv, T, dtype=dtype), k)
        if dtype is np.float64:
            named["per-track joseph=False 1"] = (filter_loop(x0, zs, cv, T, joseph=False), 1)
            partial = zs[: min(T, 6)].copy()
            partial[:, ::20, 1] = np.nan  # 5 % of the rows measure x alone: x and y blocks apart
            named["per-track split 1"] = (filter_loop(x0, partial, cv, T), 1)
            full = np.nan_to_num(zs[: min(T, 2)], nan=320.0)
            for k in threads:
                named[f"shared {k}"] = (filter_loop(x0, full, cv, T), k)
        best = alternate(named, T, args.repeats)
        name = np.dtype(dtype).name
        floor = best["floor"]
        add(f"floor pass: in-place a += b over (N, 10) {name} (NumPy, 1 thread)", N, floor)
        for k in threads:
            add(f"kalmansfm, per-track covariance, {name}, {k} thread{'s' * (k > 1)}", N, best[f"per-track {k}"], floor)
        if dtype is np.float64:
            add("kalmansfm, per-track covariance, float64, joseph=False, 1 thread", N,
                best["per-track joseph=False 1"], floor)
            add("kalmansfm, per-track, x and y blocks apart (5 % rows x only), 1 thread", N,
                best["per-track split 1"], floor)
            for k in threads:
                add(f"kalmansfm, shared covariance (every track measured), {k} thread{'s' * (k > 1)}", N,
                    best[f"shared {k}"], floor)
            kf = named[f"per-track {threads[0]}"][0].last
            assert kf.decoupled and not kf.shared_covariance
            results["kf"], results["x0"], results["zs"] = kf, x0, zs
        del named, best
    kf, x0, zs = results["kf"], results["x0"], results["zs"]
    numba.set_num_threads(threads[-1])
    print(f"numba threading layer: {numba.threading_layer()}")

    # -- peers and references ----------------------------------------------------------------
    n_fp = min(args.filterpy_tracks, N)
    seconds, fp_x, fp_P = run_filterpy(x0[:n_fp], zs[:, :n_fp], cv)
    add("FilterPy KalmanFilter, one object per track (loop)", n_fp, seconds)
    n_sk = min(args.simdkalman_tracks, N)
    seconds, sk_x, _ = run_simdkalman(x0[:n_sk], zs[:, :n_sk], cv)
    add("simdkalman (filtered=True), CV model (computes in float64)", n_sk, seconds)
    seconds, dec_x = run_decoupled_reference(x0, zs, cv)
    add("NumPy decoupled path (the filter's arithmetic before the kernels)", N, seconds)
    seconds, ref_x, ref_P = run_numpy_reference(x0, zs, cv)
    add("kalmansfm NumPy reference functions, (N, 4, 4) covariances", N, seconds)
    agreement = {
        "NumPy decoupled path": (relative_difference(kf.x, dec_x), float("nan")),
        "dense NumPy reference": (relative_difference(kf.x, ref_x), relative_difference(np.array(kf.P), ref_P)),
        "FilterPy": (relative_difference(kf.x[:n_fp], fp_x), relative_difference(np.array(kf.P[:n_fp]), fp_P)),
        "simdkalman": (relative_difference(kf.x[:n_sk], sk_x), float("nan")),
    }
    del ref_x, ref_P, dec_x

    dm = coupled_model()
    n_d = min(args.dense_tracks, N)
    warm_up(x0[:n_d], zs[:, :n_d], dm, np.float64)
    named = {f"dense {k}": (filter_loop(x0[:n_d], zs[:, :n_d], dm, T), k) for k in threads}
    best = alternate(named, T, max(1, args.repeats - 1))
    for k in threads:
        add(f"kalmansfm, general dense model (coupled F, Q, R), {k} thread{'s' * (k > 1)}", n_d, best[f"dense {k}"])
    dense_kf = named[f"dense {threads[0]}"][0].last
    assert not dense_kf.decoupled
    seconds, dref_x, _ = run_numpy_reference(x0[:n_d], zs[:, :n_d], dm)
    add("NumPy reference functions, same general dense model", n_d, seconds)
    seconds, skd_x, _ = run_simdkalman(x0[:n_d], zs[:, :n_d], dm)
    add("simdkalman, same general dense model", n_d, seconds)
    agreement["dense model: NumPy reference"] = (relative_difference(dense_kf.x, dref_x), float("nan"))
    agreement["dense model: simdkalman"] = (relative_difference(dense_kf.x, skd_x), float("nan"))

    per_step = {name: s[0] / (t * T) * 1e9 for name, t, s, _ in rows}
    fp = per_step["FilterPy KalmanFilter, one object per track (loop)"]
    sk = per_step["simdkalman (filtered=True), CV model (computes in float64)"]
    print()
    print("| implementation | tracks | ns / track-step (wall) | (CPU) | × floor pass (wall) | (CPU, 1 thread) "
          "| vs FilterPy loop | vs simdkalman CV |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, tracks, seconds, floor in rows:
        ns = per_step[name]
        cpu_ns = seconds[1] / (tracks * T) * 1e9
        ratio = f"{seconds[0] / floor[0]:.2f}" if floor is not None else ""
        cpu_ratio = f"{seconds[1] / floor[1]:.2f}" if floor is not None and "2 threads" not in name else ""
        print(f"| {name} | {tracks:,} | {ns:.2f} | {cpu_ns:.2f} | {ratio} | {cpu_ratio} | {fp / ns:.0f}x "
              f"| {sk / ns:.1f}x |")
    print()
    for name, (dx, dP) in agreement.items():
        print(f"agreement with {name}: max relative difference of a track's state {dx:.1e}"
              + ("" if dP != dP else f", covariance {dP:.1e}"))

    # -- size sweep ----------------------------------------------------------------------------
    sizes = [int(s) for s in args.sizes.split(",") if s]
    if sizes:
        del kf, x0, zs, results
        print()
        print("| tracks | dtype | floor pass ns | " + " | ".join(f"kalmansfm {k} thr ns | × floor" for k in threads)
              + " | 1 thr × floor (CPU time) | load |")
        print("|---:|---|---:|" + "---:|---:|" * len(threads) + "---:|---:|")
        for size in sizes:
            for dtype in (np.float64, np.float32):
                x0, zs = make_problem(size, min(T, 6), args.missing, seed=2, dtype=dtype)
                warm_up(x0, zs, cv, dtype)
                named = {"floor": (floor_pass(size, dtype), 1)}
                named.update({k: (filter_loop(x0, zs, cv, T, dtype=dtype), k) for k in threads})
                best = alternate(named, T, args.repeats)
                ns = {k: v[0] / (size * T) * 1e9 for k, v in best.items()}
                cells = " | ".join(f"{ns[k]:.2f} | {best[k][0] / best['floor'][0]:.2f}" for k in threads)
                cpu = best[threads[0]][1] / best["floor"][1]
                print(f"| {size:,} | {np.dtype(dtype).name} | {ns['floor']:.2f} | {cells} | {cpu:.2f} | {load()} |",
                      flush=True)
                del x0, zs, named

    if not args.quick:
        print()
        print("| first predict + update, fresh process | tracks | numba cache | import kalmansfm (s) "
              "| first step (s) |")
        print("|---|---:|---|---:|---:|")
        print("\n".join(first_call_costs()))
        x0, zs = make_problem(N, T, args.missing)
        peak = peak_memory(x0, zs, cv)
        visible = N * (4 + 16) * 8
        compact = N * (4 + 3) * 8
        print(f"\npeak traced memory during the per-track run: {peak / 1e6:.0f} MB = {peak / visible:.2f}x the "
              f"(N,4)+(N,4,4) state + covariance arrays ({visible / 1e6:.0f} MB), {peak / compact:.2f}x the compact "
              f"storage ({compact / 1e6:.0f} MB); the {zs.nbytes / 1e6:.0f} MB of measurements are input")
    print(f"\nload average at the end {load()}")


if __name__ == "__main__":
    main()
