"""Factorization of a large track array: ``kalmansfm.factorize`` end to end vs scipy ``svds(k=3)`` on
the centred W it implies, then the rank-3 solvers side by side, then the missing-data path — on two
scenes in one run: a camera turning smoothly about an axis (video-like) and random orientations.

Usage::

    python benchmarks/bench_factorization.py            # both scenes, 1000 frames x 100000 points (~9 GB)
    python benchmarks/bench_factorization.py --scene smooth --frames 200 --points 20000
    python benchmarks/bench_factorization.py --layout c # the smooth scene C-ordered instead of (F, 2, P)
    python benchmarks/bench_factorization.py --profile  # also a cProfile of one factorize call
    python benchmarks/bench_factorization.py --steps 4  # CPU time and page faults of each step, 4 calls

The same script runs on older code (the table's factorize row, and ``--steps`` with that version's
step names), e.g. the code before issue 29::

    git archive fc44746 src | tar -x -C /tmp/before
    PYTHONPATH=/tmp/before/src python benchmarks/bench_factorization.py --missing-fraction 0

One core: the script sets the BLAS/OpenMP/numba thread variables to 1 before NumPy is imported, so
our code and scipy's ARPACK run single-threaded in the same process. ``factorize`` gets the
(F, P, 2) track array, as a user calls it (validation, centring, rank-3 SVD, metric upgrade, gauge,
residuals); svds and the other solvers get the centred W (2F x P) built beforehand, untimed. The
timed calls alternate (factorize, svds, ...) for ``--repeat`` rounds and the best of each is kept,
so that both see the same load; the load average is printed. The reference subspace is the top-3
eigenvectors of the 2F x 2F Gram matrix W Wᵀ (its eigenvector error is about eps·σ1²/(σ3² − σ4²)
≈ 1e-15 rad here); the angle column is the largest principal angle between a method's left rank-3
subspace and that reference.
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_variable] = "1"

import argparse  # noqa: E402
import cProfile  # noqa: E402
import platform  # noqa: E402
import pstats  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402

import numpy as np  # noqa: E402
import scipy  # noqa: E402
from scipy.sparse.linalg import svds  # noqa: E402

from kalmansfm.structure import align_similarity, factorize, subspace_angle, truncated_svd  # noqa: E402

GB = 1e9


def random_scene(frames: int, points: int, noise_px: float, rng: np.random.Generator) -> np.ndarray:
    """(F, P, 2) orthographic tracks of a random rigid object seen in random orientations (pixels), C order."""
    shape = rng.normal(size=(points, 3)) * np.array([60.0, 40.0, 25.0])
    q, _ = np.linalg.qr(rng.normal(size=(frames, 3, 3)))
    positions = shape @ q[:, :2].transpose(0, 2, 1)  # (F, P, 2) = S M_fᵀ
    positions += rng.uniform(100, 400, size=(frames, 1, 2))
    positions += noise_px * rng.normal(size=positions.shape)
    return positions


def rotations_about(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations by ``angles`` (radians) about the unit vector along ``axis`` (Rodrigues)."""
    k = np.cross(np.eye(3), axis / np.linalg.norm(axis))  # k @ v = axis × v
    a = np.asarray(angles)[:, None, None]
    return np.eye(3) + np.sin(a) * k + (1.0 - np.cos(a)) * (k @ k)


def smooth_scene(frames: int, points: int, noise_px: float, rng: np.random.Generator, turn_deg: float = 45.0,
                 jitter_deg: float = 0.1) -> np.ndarray:
    """(F, P, 2) tracks of a video-like shot: the camera turns smoothly by ``turn_deg`` about a fixed,
    slightly tilted axis over the frames, with a hand-held jitter of ``jitter_deg`` (std, degrees) in
    the angle and about the horizontal axis, and pans slowly; ``noise_px`` image noise.

    Rendered the way such a scene is naturally written, camera rows times points, so the array is
    (F, 2, P) in memory and seen as (F, P, 2) (not C-ordered; ``--layout c`` gives a C-ordered copy).
    """
    shape = rng.normal(size=(points, 3)) * np.array([60.0, 40.0, 25.0])
    angles = np.radians(np.linspace(0.0, turn_deg, frames) + jitter_deg * rng.normal(size=frames))
    shake = rotations_about(np.array([1.0, 0.0, 0.0]), np.radians(jitter_deg * rng.normal(size=frames)))
    cameras = shake @ rotations_about(np.array([0.1, 1.0, 0.2]), angles)
    pan = 250.0 + np.cumsum(rng.normal(scale=0.3, size=(frames, 2)), axis=0)
    image = cameras[:, :2] @ shape.T + pan[:, :, None]  # (F, 2, P)
    image += noise_px * rng.normal(size=image.shape)
    return image.transpose(0, 2, 1)


SCENES = {"smooth": smooth_scene, "random": random_scene}


def layout_name(positions: np.ndarray) -> str:
    if positions.flags.c_contiguous:
        return "C-ordered (F, P, 2)"
    if positions.transpose(0, 2, 1).flags.c_contiguous:
        return "(F, 2, P) in memory"
    return f"strides {positions.strides}"


def range_finder_one_power_iteration(w: np.ndarray, k: int = 3, oversampling: int = 10, seed: int = 0):
    """The textbook randomized SVD (Halko, Martinsson & Tropp 2011, alg. 4.4 + 5.1) with q = 1.

    Q = orth(W Ω); Q = orth(W orth(Wᵀ Q)); B = Qᵀ W; SVD of B — four products with W.
    """
    omega = np.random.default_rng(seed).standard_normal((w.shape[1], k + oversampling))
    q, _ = np.linalg.qr(w @ omega)
    q, _ = np.linalg.qr(w @ np.linalg.qr(w.T @ q)[0])
    u_b, s, vt = np.linalg.svd(q.T @ w, full_matrices=False)
    return q @ u_b[:, :k], s[:k], vt[:k]


def interleaved(contenders: dict, repeat: int) -> tuple[dict, dict, dict]:
    """Best wall time and best CPU time (user + system, this process) of each contender over
    ``repeat`` rounds in which they run in turn; and the last results."""
    wall, cpu, results = dict.fromkeys(contenders, np.inf), dict.fromkeys(contenders, np.inf), {}
    for _ in range(repeat):
        for name, fn in contenders.items():
            results.pop(name, None)  # the previous result is freed outside the timed call
            start, start_cpu = time.perf_counter(), time.process_time()
            results[name] = fn()
            cpu[name] = min(cpu[name], time.process_time() - start_cpu)
            wall[name] = min(wall[name], time.perf_counter() - start)
    return wall, cpu, results


def peak_memory(fn) -> tuple[float, float | None]:
    """(tracemalloc peak of NumPy + Python allocations, rise of the process's peak RSS) in bytes.

    The RSS figure resets the kernel's high-water mark first (``/proc/self/clear_refs``); None
    where that is not available.
    """
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")
        baseline = _status_kb("VmRSS")
    except OSError:
        baseline = None
    tracemalloc.start()
    try:
        fn()
        traced = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    rss = None if baseline is None else (_status_kb("VmHWM") - baseline) * 1024.0
    return traced, rss


def _status_kb(field: str) -> float:
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith(field + ":"):
                return float(line.split()[1])
    raise OSError(field)


# The steps of ``factorize`` timed by ``--steps``: whichever of these the installed version has
# (the names of commit f7ed7b8 first, then those of the streamed path), so that the same command
# measures the code before and after issue 17.
STEPS = {
    "kalmansfm.structure.affine.factorization": ("_validate", "_centred_measurement_matrix", "truncated_svd",
                                          "metric_upgrade", "_reprojection_residuals"),
    "kalmansfm.structure.affine._measurement": ("_start", "_first_pass", "_round_trip", "_projection_pass"),
}


def time_steps(positions: np.ndarray, calls: int) -> None:
    """CPU time (user, system) and page faults of each step of ``factorize``, per call."""
    import importlib
    import resource

    def usage() -> np.ndarray:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return np.array([time.perf_counter(), r.ru_utime, r.ru_stime, r.ru_minflt])

    totals: dict[str, list[np.ndarray]] = {}
    patched = []
    for module_name, names in STEPS.items():
        try:
            module = importlib.import_module(module_name)
        except ImportError:
            continue
        for name in names:
            if not hasattr(module, name):
                continue
            original = getattr(module, name)

            def wrapper(*args, _original=original, _name=name, **kwargs):
                before = usage()
                out = _original(*args, **kwargs)
                totals.setdefault(_name, []).append(usage() - before)
                return out

            setattr(module, name, wrapper)
            patched.append((module, name, original))
    try:
        for _ in range(calls):
            before = usage()
            factorize(positions)
            totals.setdefault("factorize (whole call)", []).append(usage() - before)
    finally:
        for module, name, original in patched:
            setattr(module, name, original)
    print(f"\nsteps of factorize, {calls} calls (load average {os.getloadavg()[0]:.1f}); per call: wall, user, system "
          "seconds and page faults, min–max over the calls\n")
    print("| step | wall (s) | user (s) | system (s) | page faults |")
    print("|---|---:|---:|---:|---:|")
    for name, rows in totals.items():
        per_call = np.array(rows).reshape(calls, -1, 4).sum(axis=1)
        low, high = per_call.min(axis=0), per_call.max(axis=0)
        print(f"| {name} | {low[0]:.2f}–{high[0]:.2f} | {low[1]:.2f}–{high[1]:.2f} | {low[2]:.2f}–{high[2]:.2f} "
              f"| {low[3]:.0f}–{high[3]:.0f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=1000, help="F; W has 2F rows")
    parser.add_argument("--points", type=int, default=100_000, help="P; W has P columns")
    parser.add_argument("--scene", choices=("smooth", "random", "both"), default="both",
                        help="smooth: a camera turning 45 degrees about an axis (video-like); random: a random "
                             "orientation per frame; both: one after the other in one run (default)")
    parser.add_argument("--layout", choices=("natural", "c"), default="natural",
                        help="natural: the array as the scene makes it (smooth: (F, 2, P) in memory); c: a "
                             "C-ordered copy")
    parser.add_argument("--noise", type=float, default=1.0, help="pixel noise std")
    parser.add_argument("--repeat", type=int, default=2, help="timed rounds (best of)")
    parser.add_argument("--full-svd-points", type=int, default=2000, help="numpy full SVD on the first columns only")
    parser.add_argument("--missing-fraction", type=float, default=0.3, help="holes for the missing-data run (0: skip)")
    parser.add_argument("--profile", action="store_true", help="print a cProfile of one factorize call")
    parser.add_argument("--steps", type=int, default=0, metavar="CALLS",
                        help="time the steps of factorize (CPU, page faults) over CALLS calls")
    args = parser.parse_args()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores shared with other jobs; one thread; "
          f"load average {os.getloadavg()[0]:.1f} at start; numpy {np.__version__}, scipy {scipy.__version__}")
    names = ("smooth", "random") if args.scene == "both" else (args.scene,)
    summary = [run_scene(name, args) for name in names]
    print("\n| scene | layout | factorize (s) | svds (s) | **factorize / svds** | CPU ratio | peak memory / input "
          "(tracemalloc, RSS rise) | load around the rounds |")
    print("|---|---|---:|---:|---:|---:|---|---|")
    for row in summary:
        print(row)
    print(f"\nload average at end: {os.getloadavg()[0]:.1f}")


def run_scene(name: str, args: argparse.Namespace) -> str:
    """Every measurement of one scene; returns its line of the closing summary table."""
    frames, points = args.frames, args.points
    positions = SCENES[name](frames, points, args.noise, np.random.default_rng(0))
    if args.layout == "c":
        positions = np.ascontiguousarray(positions)
    layout = layout_name(positions)
    size_in = f"{frames} x {points} x 2"
    print(f"\n## {name} scene: {size_in} float64, {positions.nbytes / GB:.2f} GB, {layout}")
    start = time.perf_counter()
    warm_up = positions[:, : max(4, 2_000_000 // (2 * frames) + 1)]  # just large enough for the streamed path
    factorize(warm_up)  # numba kernels: compile or load the cache, float64 and float32
    factorize(warm_up.astype(np.float32))
    print(f"first call (kernel compilation or cache load, small slice) {time.perf_counter() - start:.1f} s")

    traced, rss = peak_memory(lambda: factorize(positions))
    rss_text = "n/a" if rss is None else f"{rss / GB:.2f} GB ({rss / positions.nbytes:.2f}x)"
    print(f"factorize peak memory: tracemalloc {traced / GB:.2f} GB ({traced / positions.nbytes:.2f}x the input), "
          f"peak RSS rise {rss_text}")
    print(f"streamed solver: {solver_passes(positions)}")
    if args.profile:
        profile = cProfile.Profile()
        profile.enable()
        factorize(positions)
        profile.disable()
        pstats.Stats(profile).sort_stats("tottime").print_stats(12)
    if args.steps:
        time_steps(positions, args.steps)

    w = positions.transpose(0, 2, 1).reshape(2 * frames, points)  # a C-ordered copy, or a view of one
    w = w - w.mean(axis=1, keepdims=True)
    size = f"{w.shape[0]} x {w.shape[1]}"

    single = positions.astype(np.float32)  # same layout
    traced32, _ = peak_memory(lambda: factorize(single))
    contenders = {
        "factorize": lambda: factorize(positions),
        "factorize32": lambda: factorize(single),
        "svds": lambda: svds(w, k=3, random_state=0),
        "ours": lambda: truncated_svd(w, 3, method="randomized"),
        "three": lambda: truncated_svd(w, 3, method="randomized", max_passes=3),
        "finder": lambda: range_finder_one_power_iteration(w),
    }
    load_before = os.getloadavg()[0]
    best, cpu, results = interleaved(contenders, args.repeat)
    load_after = os.getloadavg()[0]

    t_gram = time.perf_counter()
    gram = w @ w.T
    t_gram = time.perf_counter() - t_gram
    t_eigh = time.perf_counter()
    eigenvalues, eigenvectors = np.linalg.eigh(gram)
    t_eigh = time.perf_counter() - t_eigh
    del gram
    best["gram"] = t_gram + t_eigh
    exact = eigenvectors[:, ::-1][:, :3]
    sigma = np.sqrt(np.maximum(eigenvalues[::-1][:5], 0))
    print(f"W {size}: singular values {np.array2string(sigma, precision=1)} (σ4/σ3 = {sigma[3] / sigma[2]:.2g})")

    rec, ours, three = results["factorize"], results["ours"], results["three"]
    rows = [  # (key, implementation, size, angle, note)
        ("factorize", "**kalmansfm `factorize`**, complete data, end to end", size_in,
         subspace_angle(rec.motion.reshape(-1, 3), exact),
         f"from the (F, P, 2) array; peak memory {traced / GB:.2f} GB = {traced / positions.nbytes:.2f}x the input "
         f"(tracemalloc); residual {rec.reprojection_rms:.6f} px"),
        ("factorize32", "kalmansfm `factorize`, the same positions as float32", size_in,
         subspace_angle(results["factorize32"].motion.reshape(-1, 3), exact),
         f"peak memory {traced32 / GB:.2f} GB = {traced32 / single.nbytes:.2f}x its input; the angle is to the "
         "float64 reference (the data differ by float32 rounding)"),
        ("svds", "scipy.sparse.linalg.svds(k=3), ARPACK", size, subspace_angle(results["svds"][0], exact),
         "on the centred W"),
        ("ours", "kalmansfm `truncated_svd` (tol 1e-9 rad, certified)", size, subspace_angle(ours.u, exact),
         f"{ours.passes} products with ℓ = {ours.s.size + ours.extra_singular_values.size} columns, "
         f"Davis–Kahan bound {ours.angle_bound:.1e} ({'rigorous' if ours.certified else 'estimate'})"),
        ("three", "kalmansfm `truncated_svd`, stopped after 3 products", size, subspace_angle(three.u, exact),
         f"bound {three.angle_bound:.1e}"),
        ("finder", "randomized range finder, 1 power iteration, ℓ = 13 (Halko et al.)", size,
         subspace_angle(results["finder"][0], exact), "4 products"),
        ("gram", "W Wᵀ (one GEMM) + numpy eigh of the 2F x 2F Gram", size, 0.0,
         f"GEMM {t_gram:.1f} s + eigh {t_eigh:.1f} s; the reference"),
    ]
    small = w[:, : args.full_svd_points]
    start = time.perf_counter()
    np.linalg.svd(small, full_matrices=False)
    t_full = time.perf_counter() - start
    scale = w.shape[1] / small.shape[1]
    best["full"] = t_full
    rows.append(("full", f"numpy.linalg.svd (full) on {small.shape[1]} columns", f"{small.shape[0]} x {small.shape[1]}",
                 float("nan"), f"x{scale:.0f} columns: ≈ {t_full * scale:.0f} s for the whole W"))
    del w, small, single

    print(f"\n{name} scene, best of {args.repeat} interleaved rounds; load average {load_before:.1f} before, "
          f"{load_after:.1f} after\n")
    print("| implementation | size | seconds (wall) | ratio to svds | CPU s (user + sys) | CPU ratio to svds "
          "| max principal angle to exact (rad) | notes |")
    print("|---|---|---:|---:|---:|---:|---:|---|")
    for key, label, shown, angle, note in rows:
        timed = f"{cpu[key]:.3f} | {cpu[key] / cpu['svds']:.2f}" if key in cpu else "– | –"
        print(f"| {label} | {shown} | {best[key]:.3f} | {best[key] / best['svds']:.2f} | {timed} | {angle:.1e} "
              f"| {note} |")

    if args.missing_fraction > 0:
        holes = np.array(positions)  # same layout
        holes[np.random.default_rng(2).random((frames, points)) < args.missing_fraction] = np.nan
        start = time.perf_counter()
        traced_als, rss_als = peak_memory(lambda: results.__setitem__("als", factorize(holes)))
        t_als = time.perf_counter() - start
        als = results["als"]
        fit = align_similarity(als.points, rec.points, allow_reflection=True)
        radius = np.sqrt(np.mean(np.sum(rec.points**2, axis=1)))
        rss_text = "n/a" if rss_als is None else f"{rss_als / GB:.2f} GB"
        print("\n| missing data | size | seconds | peak memory (tracemalloc / RSS rise) | ALS iterations | "
              "shape vs complete data (RMS radius) | residual (px) |")
        print("|---|---|---:|---|---:|---:|---:|")
        print(f"| {args.missing_fraction:.0%} of the positions NaN | {size_in} | {t_als:.1f} | "
              f"{traced_als / GB:.2f} GB ({traced_als / holes.nbytes:.2f}x) / {rss_text} | {als.details.iterations} | "
              f"{fit.rms / radius:.1e} | {als.reprojection_rms:.4f} (complete: {rec.reprojection_rms:.4f}) |")
        print("(one call, with tracemalloc running)")
        del holes, als
    rss_short = "n/a" if rss is None else f"{rss / positions.nbytes:.2f}x"
    return (f"| {name} | {layout} | {best['factorize']:.3f} | {best['svds']:.3f} | "
            f"**{best['factorize'] / best['svds']:.2f}** | {cpu['factorize'] / cpu['svds']:.2f} | "
            f"{traced / positions.nbytes:.2f}x, {rss_short} | {load_before:.1f} → {load_after:.1f} |")


def solver_passes(positions: np.ndarray) -> str:
    """Reads of the array and the certified angle of the streamed rank-3 solver, as factorize runs it."""
    from kalmansfm.structure.affine import _measurement, factorization

    fit = _measurement.streamed_rank(positions, 3, tol=factorization._SUBSPACE_TOL, max_passes=12,
                                     rng=np.random.default_rng(0))
    if fit is None:
        return "declined (NaN or infinity)"
    return (f"{fit.passes} reads of the array, Davis–Kahan bound {fit.angle_bound:.1e} rad "
            f"({'certified' if fit.certified else 'estimate'}), σ4/σ3 ≈ {fit.extra_singular_values[0] / fit.s[2]:.2g}")


if __name__ == "__main__":
    main()
