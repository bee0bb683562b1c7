"""Structure fusion with known cameras: speed against OpenCV's two-view triangulation, memory, Dask scaling.

Usage::

    python benchmarks/bench_fuse.py                         # everything (10⁶ points on Dask: several minutes)
    python benchmarks/bench_fuse.py --dask-points 0         # speed and memory only
    python benchmarks/bench_fuse.py --points 20000 --dask-points 100000 --repeat 2   # quick look

1. Speed (one core).  A seeded scene of ``--points`` points seen by 12 cameras (every point in every
   view, 0.5 px noise).  ``kalmansfm.fuse`` fuses every point over the 12 views with covariances
   (recursive: the two-view start + 10 gated iterated EKF updates per point; σ given) against
   ``cv2.triangulatePoints`` on the 11 consecutive view pairs (linear, no covariance, no outlier
   test).  Both run in this process, interleaved, best of ``--repeat``; the ratio is ours / OpenCV.
   batch, pairs and σ = auto (which needs extra passes over the data) are timed once for reference.
2. Memory.  Peak of NumPy's allocations (tracemalloc) during one fusion without and with the
   history, against the size of the observations.
3. Dask.  ``--dask-points`` points × 12 views fused chunk-parallel on a ``dask.distributed``
   LocalCluster of 1 and 2 single-threaded worker processes (the set-up of ``kalmansfm batch``,
   :func:`kalmansfm.pipeline.cluster.dask_client`; chunks scattered to the workers as
   ``kalmansfm fuse --workers`` does), for a few chunk sizes; the in-process run is the reference.
   Cluster start-up is not timed; sending the chunks and fetching the results are, and are shown.

The machine is shared during development: the load average is printed with every table.
"""

from __future__ import annotations

import argparse
import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import platform  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from kalmansfm.pipeline.cluster import ScatteringExecutor, dask_client  # noqa: E402
from kalmansfm.scenes.known_cameras import known_camera_scene  # noqa: E402
from kalmansfm.structure.fusion import fuse  # noqa: E402


def load() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min), {os.cpu_count()} cores"


def opencv_pairs(P: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """cv2.triangulatePoints on each consecutive pair of views: (V-1, N, 3)."""
    out = []
    for v in range(P.shape[0] - 1):
        h = cv2.triangulatePoints(P[v], P[v + 1], np.ascontiguousarray(obs[v].T), np.ascontiguousarray(obs[v + 1].T))
        out.append((h[:3] / h[3]).T)
    return np.stack(out)


def timed(fn):
    start = time.perf_counter()
    result = fn()
    return time.perf_counter() - start, result


def speed(points: int, repeat: int) -> None:
    s = known_camera_scene(points=points, views=12, pixel_std=0.5, seed=0)
    P = s.cameras.matrices
    fuse(s.observations[:, :100], s.cameras, pixel_std=0.5)  # compile (or load) the numba kernel
    cv2.setNumThreads(1)
    ours, theirs = [], []
    for _ in range(repeat):
        t, cv_points = timed(lambda: opencv_pairs(P, s.observations))
        theirs.append(t)
        t, fused = timed(lambda: fuse(s.observations, s.cameras, pixel_std=0.5))
        ours.append(t)
    best_ours, best_cv = min(ours), min(theirs)
    pairs = points * 11
    print(f"\n## Speed: {points} points x 12 views, one core ({load()})")
    print("| method | seconds (best of %d) | µs per point | µs per point-pair | ratio to OpenCV |" % repeat)
    print("|---|---|---|---|---|")
    print(f"| OpenCV triangulatePoints, 11 consecutive pairs (no covariance) | {best_cv:.3f} | "
          f"{1e6 * best_cv / points:.2f} | {1e6 * best_cv / pairs:.3f} | 1 |")
    print(f"| kalmansfm recursive, 12 views, covariances, σ given | {best_ours:.3f} | {1e6 * best_ours / points:.2f} "
          f"| {1e6 * best_ours / pairs:.3f} | {best_ours / best_cv:.2f} |")
    for label, kwargs in (("recursive, σ = auto", dict(pixel_std="auto")),
                          ("batch (Gauss-Newton per point), σ given", dict(method="batch", pixel_std=0.5)),
                          ("pairs (the report's scheme), σ given", dict(method="pairs", pixel_std=0.5))):
        t, other = timed(lambda: fuse(s.observations, s.cameras, **kwargs))
        extra = f" ({other.details.passes} passes, σ = {other.noise.std:.3f})" if kwargs.get("pixel_std") == "auto" else ""
        print(f"| kalmansfm {label}{extra} | {t:.3f} | {1e6 * t / points:.2f} | {1e6 * t / pairs:.3f} | "
              f"{t / best_cv:.2f} |")
    err_ours = np.sqrt(np.mean(np.sum((fused.points - s.points) ** 2, axis=1)))
    err_cv = np.sqrt(np.mean(np.sum((cv_points[-1] - s.points) ** 2, axis=1)))
    print(f"\nRMS 3-D error: fused over 12 views {err_ours:.2e}; OpenCV's last pair {err_cv:.2e} (world units)")
    print(f"all timings ours: {np.round(ours, 3).tolist()}  OpenCV: {np.round(theirs, 3).tolist()}")


def memory(points: int) -> None:
    s = known_camera_scene(points=points, views=12, pixel_std=0.5, seed=1)
    size = s.observations.nbytes
    print(f"\n## Memory: {points} points x 12 views; observations {size / 1e6:.1f} MB ({load()})")
    print("| run | peak NumPy allocations during fuse (MB) | / observations |")
    print("|---|---|---|")
    for label, kwargs in (("recursive, no history", {}), ("recursive, history", {"history": True}),
                          ("recursive, no history, chunks of 10 000", {"chunk_points": 10_000}),
                          ("batch, no history", {"method": "batch"})):
        tracemalloc.start()
        fuse(s.observations, s.cameras, pixel_std=0.5, **kwargs)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        print(f"| {label} | {peak / 1e6:.1f} | {peak / size:.1f} |")


class TimedExecutor(ScatteringExecutor):
    """ScatteringExecutor that records how long sending, computing and fetching the chunks took."""

    def map(self, fn, items):
        from dask.distributed import wait

        client = self._client
        start = time.perf_counter()
        data = client.scatter(list(items))
        sent = time.perf_counter()
        futures = client.map(fn, data, pure=False)
        wait(futures)
        computed = time.perf_counter()
        results = client.gather(futures)
        self.phases = (sent - start, computed - sent, time.perf_counter() - computed)
        return iter(results)


def dask_scaling(points: int, chunks: list[int]) -> None:
    s = known_camera_scene(points=points, views=12, pixel_std=0.5, seed=2)
    print(f"\n## Dask: {points} points x 12 views, recursive, σ given ({load()})")
    t, reference = timed(lambda: fuse(s.observations, s.cameras, pixel_std=0.5))
    print("| where | chunk (points) | seconds | of which: send chunks, compute, fetch results | speed-up vs in-process |")
    print("|---|---|---|---|---|")
    print(f"| in this process | {reference_chunk(points)} | {t:.2f} | – | 1 |")
    for workers in (1, 2):
        with dask_client(None, workers) as client:
            executor = TimedExecutor(client)
            fuse(s.observations[:, :1000], s.cameras, pixel_std=0.5, executor=executor)  # warm the workers
            for chunk in chunks:
                tt, result = timed(lambda: fuse(s.observations, s.cameras, pixel_std=0.5, chunk_points=chunk,
                                                executor=executor))
                same = np.allclose(result.points, reference.points, rtol=1e-9, equal_nan=True)
                phases = ", ".join(f"{x:.2f}" for x in executor.phases)
                print(f"| LocalCluster, {workers} worker{'s' if workers > 1 else ''} | {chunk} | {tt:.2f} | {phases} | "
                      f"{t / tt:.2f} |{'' if same else ' (results differ!)'}")
    print(f"({load()})")


def reference_chunk(points: int) -> int:
    from kalmansfm.structure.fusion import DEFAULT_CHUNK_POINTS

    return min(points, DEFAULT_CHUNK_POINTS)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--memory-points", type=int, default=100_000)
    parser.add_argument("--dask-points", type=int, default=1_000_000)
    parser.add_argument("--chunks", type=int, nargs="+", default=[50_000, 250_000])
    args = parser.parse_args()
    print(f"# bench_fuse: {platform.processor() or platform.machine()}, Python {platform.python_version()}, "
          f"NumPy {np.__version__}, OpenCV {cv2.__version__}")
    speed(args.points, args.repeat)
    if args.memory_points:
        memory(args.memory_points)
    if args.dask_points:
        dask_scaling(args.dask_points, args.chunks)


if __name__ == "__main__":
    main()
