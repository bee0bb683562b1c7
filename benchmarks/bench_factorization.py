"""Rank-3 decomposition of a large measurement matrix: ours vs scipy svds(k=3) vs numpy's full SVD.

Usage::

    PYTHONPATH=src python benchmarks/bench_factorization.py            # W 2000 x 100000 (needs ~8 GB)
    PYTHONPATH=src python benchmarks/bench_factorization.py --frames 200 --points 20000

Prints, per implementation: size, seconds, ratio to ours, and the largest principal angle
between its left rank-3 subspace and the exact one (eigenvectors of the 2F x 2F Gram
matrix W Wᵀ, accurate to ~1e-15 rad when σ₁/σ₃ is moderate). Then the timings of the
parts of ``factorize``: the metric upgrade, and the missing-data refinement (ALS).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import scipy
from scipy.sparse.linalg import svds

from kalmansfm.structure import factorize, metric_upgrade, subspace_angle, truncated_svd


def scene(frames: int, points: int, noise_px: float, rng: np.random.Generator) -> np.ndarray:
    """(F, P, 2) orthographic tracks of a random rigid object (pixels)."""
    shape = rng.normal(size=(points, 3)) * np.array([60.0, 40.0, 25.0])
    q, _ = np.linalg.qr(rng.normal(size=(frames, 3, 3)))
    positions = np.einsum("fij,pj->fpi", q[:, :2], shape) + rng.uniform(100, 400, size=(frames, 1, 2))
    positions += noise_px * rng.normal(size=positions.shape)
    return positions


def timed(fn, repeat: int = 1):
    best, out = np.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=1000, help="F; W has 2F rows")
    parser.add_argument("--points", type=int, default=100_000, help="P; W has P columns")
    parser.add_argument("--noise", type=float, default=1.0, help="pixel noise std")
    parser.add_argument("--full-svd-points", type=int, default=5000, help="numpy full SVD on the first columns only")
    parser.add_argument("--missing-frames", type=int, default=200)
    parser.add_argument("--missing-points", type=int, default=20_000)
    parser.add_argument("--missing-fraction", type=float, default=0.2)
    parser.add_argument("--skip-svds", action="store_true")
    args = parser.parse_args()
    rng = np.random.default_rng(0)

    positions = scene(args.frames, args.points, args.noise, rng)
    w = np.ascontiguousarray(positions.transpose(0, 2, 1)).reshape(2 * args.frames, args.points)
    del positions
    offsets = w.mean(axis=1)
    size = f"{w.shape[0]} x {w.shape[1]}"
    print(f"machine: {platform.processor() or platform.machine()}, numpy {np.__version__}, scipy {scipy.__version__}"
          " (2 cores shared with other jobs)")

    t_ref, gram = timed(lambda: (w @ w.T - np.outer(offsets, w.sum(axis=1)) - np.outer(w.sum(axis=1), offsets)
                                 + w.shape[1] * np.outer(offsets, offsets)))
    eigenvalues, eigenvectors = np.linalg.eigh(gram)
    exact = eigenvectors[:, ::-1][:, :3]
    sigma = np.sqrt(np.maximum(eigenvalues[::-1][:5], 0))
    print(f"W {size}: singular values {np.array2string(sigma, precision=1)}; reference from W Wᵀ in {t_ref:.1f} s")

    rows = []
    t_ours, ours = timed(lambda: truncated_svd(w, 3, row_offsets=offsets, method="randomized"), repeat=3)
    rows.append(("kalmansfm truncated_svd (randomized, certified)", size, t_ours, subspace_angle(ours.u, exact)))
    print(f"  ours: {ours.passes} passes over W, certified angle bound {ours.angle_bound:.2e} rad")
    t_one, one = timed(lambda: truncated_svd(w, 3, row_offsets=offsets, method="randomized", max_passes=3), repeat=3)
    rows.append(("kalmansfm, stopped after 3 passes (1 power iteration)", size, t_one, subspace_angle(one.u, exact)))
    t_four, four = timed(lambda: truncated_svd(w, 3, row_offsets=offsets, method="randomized", max_passes=4), repeat=3)
    rows.append(("kalmansfm, stopped after 4 passes (uncertified)", size, t_four, subspace_angle(four.u, exact)))
    if not args.skip_svds:
        centred = w - offsets[:, None]
        t_svds, (u, s, vt) = timed(lambda: svds(centred, k=3, random_state=0))
        rows.append(("scipy.sparse.linalg.svds(k=3), ARPACK", size, t_svds, subspace_angle(u, exact)))
        del centred
    small = w[:, : args.full_svd_points]
    t_full, (u_full, _, _) = timed(lambda: np.linalg.svd(small - small.mean(axis=1, keepdims=True), full_matrices=False))
    scale = w.shape[1] / small.shape[1]
    rows.append((f"numpy.linalg.svd (full) on {small.shape[1]} columns; x{scale:.0f} = {t_full * scale:.1f} s est.",
                 f"{small.shape[0]} x {small.shape[1]}", t_full, float("nan")))

    print()
    print(f"| implementation | size | seconds | ratio to ours | max principal angle to exact (rad) |")
    print("|---|---|---|---|---|")
    for name, sz, t, angle in rows:
        print(f"| {name} | {sz} | {t:.3f} | {t / t_ours:.1f} | {angle:.1e} |")

    # The other parts of factorize at the same size.
    frames = args.frames
    affine_rows = ours.u * np.sqrt(ours.s)
    t_metric, _ = timed(lambda: metric_upgrade(affine_rows), repeat=3)
    positions = w.reshape(frames, 2, -1).transpose(0, 2, 1)
    del w
    t_fact, rec = timed(lambda: factorize(positions))
    print()
    print("| step | size | seconds |")
    print("|---|---|---|")
    print(f"| metric upgrade (A by least squares, Cholesky) | {frames} frames | {t_metric:.4f} |")
    print(f"| factorize, complete data, end to end (incl. W layout copy, residuals) | {size} | {t_fact:.2f} |")
    del positions, rec

    mf, mp = args.missing_frames, args.missing_points
    holes = scene(mf, mp, args.noise, np.random.default_rng(1))
    complete = factorize(holes)
    holes[np.random.default_rng(2).random((mf, mp)) < args.missing_fraction] = np.nan
    t_als, rec = timed(lambda: factorize(holes))
    print(f"| factorize, {args.missing_fraction:.0%} missing (block init + ALS, {rec.iterations} iterations) "
          f"| {2 * mf} x {mp} | {t_als:.2f} |")
    print(f"| (same, complete data, closed form) | {2 * mf} x {mp} | {timed(lambda: factorize(scene(mf, mp, args.noise, np.random.default_rng(1))))[0]:.2f} |")
    from kalmansfm.structure import align_similarity

    fit = align_similarity(rec.points, complete.points, allow_reflection=True)
    radius = np.sqrt(np.mean(np.sum(complete.points**2, axis=1)))
    print(f"missing-data shape vs complete-data shape: {fit.rms / radius:.2e} of the RMS radius; "
          f"residual {rec.residual_rms:.3f} px vs {complete.residual_rms:.3f} px")


if __name__ == "__main__":
    main()
