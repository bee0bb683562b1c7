"""Bundle adjustment: ours (NumPy Levenberg–Marquardt, Schur complement) vs pycolmap's (Ceres) and scipy's
``least_squares``, on the same problem from the same start; then our free-network covariances on top.

Usage::

    python benchmarks/bench_bundle.py                 # 20 views x 5000 points, and the Oxford house
    python benchmarks/bench_bundle.py --repeat 5 --no-scipy

Problems (least squares, no robust loss, fixed intrinsics):

* ``synthetic``: :func:`kalmansfm.scenes.perspective.perspective_scene` with 20 frames on a 60° arc,
  5000 points tracked over 3-20 consecutive frames, 0.7 px noise; the start is the truth with the
  rotations turned by 0.3° × s, the centres and points moved by 1 % × s of the scene size
  (s = 1 and 5, seeded).
* ``oxford_house``: the inlier observations of our reconstruction of ``../shared/data/oxford_model_house``
  (2840 observations, 672 points, 10 views); the start is the dataset's own cameras and points
  (reflected into a proper frame). The house's intrinsics have skew, which COLMAP's PINHOLE model
  lacks, so both solvers get observations mapped into the skew-free camera K₀ (x₀ = K₀ K⁻¹ x).

Every solver's result is scored by the same cost ½ Σ |r|² (pixels²). pycolmap runs with its defaults
(Ceres, all cores, gradient tolerance 1e-4, ≤ 100 iterations); ours runs with BLAS on one thread.
Times are wall-clock, interleaved rounds, best and median of ``--repeat``; the load average is printed
because the machine is shared.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from kalmansfm.io.oxford import read_oxford
from kalmansfm.scenes.perspective import perspective_scene
from kalmansfm.structure.perspective.bundle import (
    ObservationList,
    bundle_adjust,
    free_network_covariances,
    reprojection_residuals,
)
from kalmansfm.structure.perspective.reconstruct import reconstruct_perspective
from kalmansfm.structure.geometry.pinhole import decompose_projection
from kalmansfm.structure.geometry.rotation import rotation_exp

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def cost(problem, R, C, X) -> float:
    r, _ = reprojection_residuals(R, C, X, problem["obs"], problem["K"])
    return 0.5 * float(np.sum(r**2))


def synthetic(strength: float, seed: int = 0) -> dict:
    s = perspective_scene(frames=20, points=5000, pixel_std=0.7, min_track_length=3, arc_degrees=60.0, seed=seed)
    obs = ObservationList.from_dense(s.observations)
    rng = np.random.default_rng(seed + 1)
    size = np.sqrt(np.mean(np.sum((s.points - s.points.mean(0)) ** 2, axis=1)))
    start = (rotation_exp(rng.normal(0, np.radians(0.3 * strength), (20, 3))) @ s.rotations,
             s.centres + rng.normal(0, 0.01 * strength * size, s.centres.shape),
             s.points + rng.normal(0, 0.01 * strength * size, s.points.shape))
    return dict(name=f"synthetic 20 x 5000, start s={strength:g}", obs=obs, K=s.intrinsics, start=start,
                size=(1280, 960))


def oxford_house() -> dict:
    data = read_oxford(DATA / "oxford_model_house")
    pose = decompose_projection(data.cameras.matrices)
    K = pose.intrinsics
    rec = reconstruct_perspective(data.observations, K)
    obs = ObservationList.from_dense(data.observations, rec.observations.used_mask())
    # skew-free camera K0 and observations mapped into it: x0 = K0 K⁻¹ x
    K0 = K.copy()
    K0[:, 0, 1] = 0.0
    to_K0 = K0 @ np.linalg.inv(K)
    h = np.concatenate([obs.pixels, np.ones((len(obs), 1))], axis=1)
    moved = np.einsum("nij,nj->ni", to_K0[obs.cameras], h)
    obs0 = ObservationList(obs.cameras, obs.points, moved[:, :2] / moved[:, 2:])
    # the dataset's cameras live in a mirrored frame (negative scale): reflect the world, X -> -X
    flip = np.sign(pose.scales)[:, None, None]
    R = pose.rotations
    C = pose.centers
    X = data.points
    if np.all(flip < 0):
        D = np.diag([1.0, 1.0, -1.0])
        R, C, X = -R @ D, C @ D, X @ D  # -R D is a proper rotation; (-R D)(D X - D C) = -R (X - C)
    return dict(name="oxford_house (dataset's cameras as start)", obs=obs0, K=K0, start=(R, C, X), size=(768, 576))


def run_ours(problem):
    fit = bundle_adjust(*problem["start"], problem["obs"], problem["K"])
    return fit.rotations, fit.centres, fit.points, fit.iterations


def run_scipy(problem):
    import scipy.sparse
    from scipy.optimize import least_squares

    R0, C0, X0 = problem["start"]
    obs, K = problem["obs"], problem["K"]
    n, m, N = len(R0), len(X0), len(obs)
    from kalmansfm.structure.perspective.bundle import _projection_matrices, _residuals

    kz = _projection_matrices(K)

    def unpack(p):
        return rotation_exp(p[: 3 * n].reshape(n, 3)) @ R0, p[3 * n: 6 * n].reshape(n, 3), p[6 * n:].reshape(m, 3)

    def fun(p):
        return _residuals(*unpack(p), obs, kz, jacobians=False)[0].ravel()

    cols = np.concatenate([3 * obs.cameras[:, None] + np.arange(3), 3 * n + 3 * obs.cameras[:, None] + np.arange(3),
                           6 * n + 3 * obs.points[:, None] + np.arange(3)], axis=1)
    rows = np.repeat(np.arange(2 * N), 9)
    cols = np.repeat(cols[:, None, :], 2, axis=1).ravel()

    def jac(p):
        _, _, J_c, J_p = _residuals(*unpack(p), obs, kz)
        return scipy.sparse.csr_matrix((np.concatenate([J_c, J_p], axis=2).ravel(), (rows, cols)),
                                       shape=(2 * N, 6 * n + 3 * m))

    res = least_squares(fun, np.concatenate([np.zeros(3 * n), C0.ravel(), X0.ravel()]), jac=jac,
                        tr_solver="lsmr", x_scale="jac")
    return (*unpack(res.x), res.nfev)


def run_pycolmap(problem):
    import pycolmap

    (R, C, X), obs, K = problem["start"], problem["obs"], problem["K"]
    rec = pycolmap.Reconstruction()
    for c in range(len(R)):
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=problem["size"][0],
                                                        height=problem["size"][1], camera_id=c + 1,
                                                        params=[K[c, 0, 0], K[c, 1, 1], K[c, 0, 2], K[c, 1, 2]]))
    index = np.empty(len(obs), np.int64)
    for c in range(len(R)):  # one image per camera
        mine = np.flatnonzero(obs.cameras == c)
        index[mine] = np.arange(len(mine))
        image = pycolmap.Image(name=str(c), keypoints=obs.pixels[mine], camera_id=c + 1, image_id=c + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R[c]), -R[c] @ C[c]))
    order = np.argsort(obs.points, kind="stable")
    starts = np.searchsorted(obs.points[order], np.arange(len(X) + 1))
    ids = np.empty(len(X), np.int64)
    for j in range(len(X)):  # building COLMAP's own structure, not part of the timed solve
        track = pycolmap.Track()
        for k in order[starts[j]: starts[j + 1]]:
            track.add_element(int(obs.cameras[k]) + 1, int(index[k]))
        ids[j] = rec.add_point3D(X[j], track)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = options.refine_extra_params = False
    options.print_summary = False
    start = time.perf_counter()
    pycolmap.bundle_adjustment(rec, options)
    elapsed = time.perf_counter() - start
    Ro = np.stack([rec.image(c + 1).cam_from_world().rotation.matrix() for c in range(len(R))])
    to = np.stack([rec.image(c + 1).cam_from_world().translation for c in range(len(R))])
    Co = -np.einsum("nji,nj->ni", Ro, to)
    Xo = np.stack([rec.point3D(int(i)).xyz for i in ids])
    return Ro, Co, Xo, elapsed


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--no-scipy", action="store_true")
    args = parser.parse_args()
    problems = [synthetic(1.0), synthetic(5.0), oxford_house()]
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}, {os.cpu_count()} cores")
    for p in problems:
        times = {"ours": [], "pycolmap": [], "scipy": []}
        results = {}
        for _ in range(args.repeat):  # interleaved rounds
            t = time.perf_counter()
            results["ours"] = run_ours(p)
            times["ours"].append(time.perf_counter() - t)
            out = run_pycolmap(p)
            results["pycolmap"] = out
            times["pycolmap"].append(out[3])
            if not args.no_scipy:
                t = time.perf_counter()
                results["scipy"] = run_scipy(p)
                times["scipy"].append(time.perf_counter() - t)
        R, C, X, iterations = results["ours"]
        r, _ = reprojection_residuals(R, C, X, p["obs"], p["K"])
        dof = 2 * len(p["obs"]) - 6 * len(R) - 3 * len(X) + 7
        t = time.perf_counter()
        free_network_covariances(R, C, X, p["obs"], p["K"], float(np.sqrt(np.sum(r**2) / dof)))
        t_cov = time.perf_counter() - t
        print(f"\n{p['name']}: {len(p['start'][0])} cameras, {len(p['start'][2])} points, {len(p['obs'])} observations; "
              f"start cost {cost(p, *p['start']):.6g}")
        print(f"  {'solver':10s} {'best s':>8s} {'median s':>9s} {'final cost':>16s}")
        for name in ("ours", "pycolmap", "scipy"):
            if not times[name]:
                continue
            final = cost(p, *results[name][:3])
            print(f"  {name:10s} {min(times[name]):8.3f} {np.median(times[name]):9.3f} {final:16.6f}")
        print(f"  ours / pycolmap time (best): {min(times['ours']) / min(times['pycolmap']):.2f}; ours: "
              f"{iterations} LM steps; free-network covariances on top: {t_cov:.3f} s")
    print(f"\nload average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
