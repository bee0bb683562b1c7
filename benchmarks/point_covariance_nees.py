"""Is the covariance of a factorized point honest?  NEES on data with truth; prints the figures in docs/factorization.md.

Usage::

    python benchmarks/point_covariance_nees.py

1. Synthetic affine scenes (seeded): 150 points, 20 orthographic frames turning 20° about a
   random axis, 0.5 px Gaussian noise, 30 % of the points seen only in a window of 2–6
   frames.  Each point's covariance (:func:`kalmansfm.structure.affine.uncertainty.point_uncertainty`) is
   judged against its true position after the best affine map onto the truth (the gauge
   the covariance lives in: the motion's own error moves all points by one common affine
   map, which Σ_p leaves out) and after the best similarity (what a user comparing shapes
   sees).  NEES should average 3 (3 coordinates); 68.3 % / 99.7 % within the 1σ / 3σ
   ellipsoids.
2. cmu_hotel's 30 hand-labelled landmarks over frames 0–50 (real images, real labelling
   noise): the reference is the factorization of all 51 frames; then the landmarks are cut,
   five at a time, to a random window of L frames, the data factorized again, and each cut
   point compared with its reference position (covariance: the cut point's plus the
   reference's), after the best affine map on the uncut points.
3. cmu_hotel tracked by our tracker (200 detected corners, 51 frames, smoothed, weighted),
   as ``kalmansfm demo --input ../shared/data/cmu_hotel/images`` does: the points far from
   the rest, their views and their standard deviations, and what is marked unreliable.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import scipy.io
from scipy.spatial.transform import Rotation

from kalmansfm.io.frames import read_frames
from kalmansfm.structure import align_affine, align_similarity
from kalmansfm.structure.affine.factorization import factor_affine as factorize
from kalmansfm.structure.affine.uncertainty import point_uncertainty
from kalmansfm.tracking import smooth_tracks, track

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
CHI2_3_1SIGMA, CHI2_3_3SIGMA = 3.5267, 14.156  # χ²₃ quantiles of 0.6827 and 0.9973


def synthetic_scene(rng: np.random.Generator, frames: int = 20, points: int = 150, noise: float = 0.5,
                    short: float = 0.3, turn_deg: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    shape = rng.normal(size=(points, 3)) * [80.0, 60.0, 40.0]
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    rotations = Rotation.from_rotvec(np.linspace(0, np.radians(turn_deg), frames)[:, None] * axis).as_matrix()
    x = np.einsum("fij,pj->fpi", rotations[:, :2], shape) + rng.normal(size=(frames, 1, 2)) * 20 + 300
    x += rng.normal(scale=noise, size=x.shape)
    for p in range(int(short * points)):
        length = rng.integers(2, 7)
        start = rng.integers(0, frames - length + 1)
        hidden = np.ones(frames, bool)
        hidden[start:start + length] = False
        x[hidden, p] = np.nan
    return shape, x


def nees(estimate: np.ndarray, covariance: np.ndarray, truth: np.ndarray, anchors: np.ndarray, gauge: str) -> np.ndarray:
    """NEES of every point after the best ``gauge`` map (affine or similarity) fitted on ``anchors``."""
    if gauge == "affine":
        fit = align_affine(estimate[anchors], truth[anchors])
        linear = fit.rotation
    else:
        fit = align_similarity(estimate[anchors], truth[anchors], allow_reflection=True)
        linear = fit.scale * fit.rotation
    error = estimate @ linear.T + fit.translation - truth
    mapped = linear @ covariance @ linear.T
    return np.einsum("pi,pij,pj->p", error, np.linalg.inv(mapped), error)


def describe(values: list[float]) -> str:
    a = np.asarray(values)
    return (f"n {len(a):5d}  mean {a.mean():6.2f}  median {np.median(a):5.2f}  within 1σ {np.mean(a <= CHI2_3_1SIGMA):.3f}"
            f"  3σ {np.mean(a <= CHI2_3_3SIGMA):.3f}")


def synthetic(trials: int = 30) -> None:
    print("== synthetic affine scenes:", trials, "scenes × 150 points, 20 frames, 20° turn, σ = 0.5 px")
    rng = np.random.default_rng(1)
    groups: dict[tuple[str, str], list[float]] = {}
    sigma = []
    for _ in range(trials):
        shape, x = synthetic_scene(rng)
        reconstruction = factorize(x)
        u = point_uncertainty(reconstruction, x)
        sigma.append(u.noise_std)
        for gauge in ("affine", "similarity"):
            values = nees(reconstruction.points, u.covariances, shape, u.views == x.shape[0], gauge)
            for name, chosen in (("2-3 views", u.views <= 3), ("4-6 views", (u.views >= 4) & (u.views <= 6)),
                                 ("all 20 views", u.views == x.shape[0])):
                groups.setdefault((gauge, name), []).extend(values[chosen].tolist())
    print(f"σ̂ (true 0.5): mean {np.mean(sigma):.3f}")
    for (gauge, name), values in groups.items():
        print(f"{gauge:10s} {name:13s} {describe(values)}")


def hotel_landmarks() -> None:
    print("== cmu_hotel, 30 hand-labelled landmarks × 51 frames, cut to windows of L frames")
    mat = scipy.io.loadmat(DATA / "cmu_hotel" / "tracks" / "cmum.mat", squeeze_me=True, struct_as_record=False)
    x = np.stack([np.asarray(mat["CMUM"].hotel.XTs[k], float).T for k in range(51)]) - 1.0
    reference = factorize(x)
    u_reference = point_uncertainty(reference, x)
    print(f"reference: residual {reference.residual_rms:.3f} px RMS, σ̂ {u_reference.noise_std:.3f} px, "
          f"largest 1σ of a point {np.nanmax(u_reference.largest_std):.2f} px")
    rng = np.random.default_rng(0)
    for length in (2, 3, 5, 8, 15):
        values: list[float] = []
        stds: list[float] = []
        for _ in range(6):
            for chunk in np.array_split(rng.permutation(30), 6):
                cut = x.copy()
                for p in chunk:
                    start = rng.integers(0, 51 - length + 1)
                    hidden = np.ones(51, bool)
                    hidden[start:start + length] = False
                    cut[hidden, p] = np.nan
                reconstruction = factorize(cut)
                u = point_uncertainty(reconstruction, cut)
                kept = np.setdiff1d(np.arange(30), chunk)
                fit = align_affine(reconstruction.points[kept], reference.points[kept])
                error = reconstruction.points[chunk] @ fit.rotation.T + fit.translation - reference.points[chunk]
                covariance = fit.rotation @ u.covariances[chunk] @ fit.rotation.T + u_reference.covariances[chunk]
                values += np.einsum("pi,pij,pj->p", error, np.linalg.inv(covariance), error).tolist()
                stds += u.largest_std[chunk].tolist()
        print(f"L = {length:2d} frames: {describe(values)}  median largest 1σ {np.median(stds):6.1f} px")


def hotel_tracked() -> None:
    print("== cmu_hotel tracked: 200 detected corners, 51 frames, smoothed, weighted (as kalmansfm demo --input)")
    frames = [np.asarray(f) for f in read_frames(DATA / "cmu_hotel" / "images")]
    tracks = smooth_tracks(track(frames))
    weights = tracks.observation_weights()
    reconstruction = factorize(tracks.observations(), weights=weights)
    u = point_uncertainty(reconstruction, tracks.observations(), weights=weights)
    z = reconstruction.points[:, 2]
    far = np.abs(z) > 1000
    print(f"residual {reconstruction.residual_rms:.3f} px, σ̂ (unit weight) {u.noise_std:.3f}, shape radius "
          f"{u.radius_px:.1f} px, bound {u.bound_px:.1f} px; unreliable {int((~u.reliable).sum())} of {len(z)}")
    print(f"{int(far.sum())} points with |Z| > 1000 px:")
    for p in np.flatnonzero(far)[np.argsort(-np.abs(z[far]))]:
        std = np.sqrt(np.diag(u.covariances[p]))
        print(f"  track {tracks.track_ids[p]:3d}: Z {z[p]:8.0f} px, views {u.views[p]}, std X/Y/Z "
              f"{std[0]:.1f}/{std[1]:.1f}/{std[2]:.1f} px, {'reliable' if u.reliable[p] else 'unreliable'}")
    kept = u.reliable
    print(f"reliable points: |Z| median {np.median(np.abs(z[kept])):.0f} px, max {np.abs(z[kept]).max():.0f} px; "
          f"largest 1σ median {np.median(u.largest_std[kept]):.2f} px, max {u.largest_std[kept].max():.1f} px")


if __name__ == "__main__":
    print("load average:", " ".join(f"{v:.2f}" for v in os.getloadavg()))
    synthetic()
    hotel_landmarks()
    hotel_tracked()
