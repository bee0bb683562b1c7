"""The report's view of unknown motion: relative orientation of consecutive frames, recursive structure fusion.

Thomas & Oliensis (``004_cd423c68da9c9743.txt``, section 8) close with the next
step: replace the motion oracle of Task 7 by a relative-orientation algorithm
whose error covariance "will model the noise in the transition of the
underlying process".  This module does exactly that:

1. **Relative orientation** of every consecutive pair (k-1, k): essential
   matrix and pose from the shared tracks (:func:`.incremental.relative_pose`),
   refined by a two-view bundle adjustment; its covariance is that of camera k
   with camera k-1 and the baseline length held fixed (the two-view reduced
   camera matrix, pseudo-inverted along the baseline): rotation (3) and
   baseline direction (2 degrees of freedom).
2. **Scale.**  A pair fixes the baseline direction, not its length s_k; s_k is
   the inverse-variance weighted ratio of the depths of the points already in
   the filter to the pair's own triangulation of them (after a median-based
   outlier screen); its variance is carried with the motion's.
3. **Recursive fusion** in the current camera frame, one Kalman step per frame:
   the prediction moves every point by the estimated motion (the report's
   eq. 23 with C = R_k, b = s_k R_k Ĉ_k),

       x_k = R_k (x_{k-1} - s_k Ĉ_k),   P_k = R_k P_{k-1} R_kᵀ + J Σ_motion Jᵀ,

   the process noise J Σ_motion Jᵀ being the motion's covariance pushed through
   (J = ∂x_k / ∂(ω, Ĉ, s)); the update is a gated iterated EKF update with the
   point's observation in frame k (:mod:`~kalmansfm.structure.fusion`'s update, the same as in
   known-camera fusion).  A track first seen in a pair enters the filter with
   the pair's triangulation and a covariance that includes the pair's image
   noise and the motion's and scale's uncertainty (implicit-function theorem).

The filter treats points as independent, as the report does; the motion
errors they share are a common-mode error, which the similarity alignment of
the free-network gauge largely removes.  Camera poses are the chained relative
motions; their covariances are propagated along the chain and are given in the
gauge of the first camera and the first baseline.  The pixel noise σ is
pooled from the two-view adjustments (degrees of freedom counted).  The chain
needs parallax between consecutive frames: where a pair has none, or too few
shared points carry the scale, the chain stops and the later frames are
reported unregistered.
"""

from __future__ import annotations

import numpy as np

from ...errors import NotEnoughDataError
from .bundle import (
    ObservationList,
    camera_frame_projections,
    residuals_and_jacobians,
    bundle_adjust,
    reduced_camera_matrix,
    reprojection_residuals,
    similarity_free_covariances,
)
from .settings import (
    FrameStatus,
    PerspectiveSettings,
    frame_runs,
    perspective_reconstruction,
)
from ..reconstruction import Reconstruction
from .incremental import relative_pose
from ..fusion import iterated_update
from ..points import PointStatus
from ..geometry.pinhole import CameraSet, project_points, triangulate_points
from ..geometry.rotation import cross_matrix

__all__ = ["reconstruct_recursive"]

# A scale ratio further than this many standard deviations from the median ratio is not used.
_SCALE_SCREEN = 3.0
# A consecutive pair is degenerate (plane or pure rotation) when a homography explains this share of the
# essential inliers (a piecewise-planar object such as the Oxford house reaches 0.85 with real parallax).
_DEGENERATE_HOMOGRAPHY_SHARE = 0.95
# Fewest points shared by the filter and a pair to carry the scale over.
_MIN_SCALE_POINTS = 5


class _Motion:
    """Relative orientation of frames (a, b): x_b = R (x_a - s Ĉ), |Ĉ| = 1, with covariance."""

    def __init__(self, rotation, direction, covariance, tracks, points, point_info, sensitivity, squares, dof):
        self.rotation = rotation  # (3, 3)
        self.direction = direction  # (3,) Ĉ, camera b's centre in frame a, unit length
        self.covariance = covariance  # (6, 6) of (δω, δĈ), rank 5, unit σ
        self.tracks = tracks  # (k,) track indices of the pair's inliers
        self.points = points  # (k, 3) in frame a at unit baseline
        self.point_info = point_info  # (k, 3, 3) JᵀJ of each point given the two cameras (unit σ)
        self.sensitivity = sensitivity  # (k, 3, 6) d point / d(δω, δĈ)
        self.squares = squares  # Σ |r|² of the two-view fit
        self.dof = dof


def _from_guess(na: np.ndarray, nb: np.ndarray, guess: tuple[np.ndarray, np.ndarray], threshold: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pose (R, t) of the guess, the matches that triangulate in front of both views within ``threshold``, their points."""
    R, direction = guess
    t = -R @ direction
    cams = CameraSet.from_pose(np.eye(3), np.stack([np.eye(3), R]), np.stack([np.zeros(3), t]))
    tri = triangulate_points(cams, np.stack([na, nb]), orientation=1)
    good = tri.status == PointStatus.OK
    pix = project_points(cams, np.where(good[:, None], tri.points, 0.0)).pixels
    err = np.linalg.norm(pix - np.stack([na, nb]), axis=2).max(axis=0)
    keep = np.flatnonzero(good & (err < threshold))
    return R, t, keep, tri.points[keep]


def _relative_orientation(obs: np.ndarray, K: np.ndarray, normalised: np.ndarray, a: int, b: int,
                          settings: PerspectiveSettings, guess: tuple[np.ndarray, np.ndarray] | None = None
                          ) -> tuple[_Motion | None, str]:
    """The pair's relative orientation, or None and why not.

    The essential matrix of a narrow view of a small object is ambiguous: one that explains
    every match may put none of them in front of both cameras.  Then ``guess`` — the
    previous pair's motion (rotation, unit baseline direction), a good start along a smooth
    path such as a turntable — is tried as the start of the two-view adjustment instead.
    """
    seen = np.isfinite(obs[a, :, 0]) & np.isfinite(obs[b, :, 0])
    tracks = np.flatnonzero(seen)
    focal = np.sqrt(K[[a, b], 0, 0] * K[[a, b], 1, 1])
    need = 2 * settings.min_registration_points
    if len(tracks) < need:
        return None, f"frames {a} and {b} share {len(tracks)} tracks (at least {need} needed)"
    threshold = settings.outlier_threshold_px / np.sqrt(focal.prod())
    pose = relative_pose(normalised[a, tracks], normalised[b, tracks], threshold)
    if pose is not None and pose.homography_inliers >= _DEGENERATE_HOMOGRAPHY_SHARE * pose.essential_inliers:
        return None, (f"no parallax between frames {a} and {b}: a homography explains {pose.homography_inliers} of "
                      f"the {pose.essential_inliers} matches (a plane or a pure rotation)")
    if pose is not None and len(pose.inliers) >= need:
        R0_b, t0_b, inliers, X = pose.rotation, pose.translation, pose.inliers, pose.points
    else:
        why = ("no essential matrix" if pose is None else
               f"the essential matrix is ambiguous ({pose.essential_inliers} matches fit it, {len(pose.inliers)} lie "
               "in front of both cameras)")
        if guess is None:
            return None, f"frames {a} and {b}: {why}"
        R0_b, t0_b, inliers, X = _from_guess(normalised[a, tracks], normalised[b, tracks], guess, threshold)
        if len(inliers) < need:
            return None, (f"frames {a} and {b}: {why}, and the previous pair's motion places only {len(inliers)} "
                          f"matches in front within the outlier threshold (at least {need} needed)")
    tracks = tracks[inliers]
    R0 = np.stack([np.eye(3), R0_b])
    C0 = np.stack([np.zeros(3), -R0_b.T @ t0_b])
    pix = obs[[a, b]][:, tracks]
    observations = ObservationList.from_dense(pix)
    Kab = K[[a, b]]
    fit = bundle_adjust(R0, C0, X, observations, Kab, loss="huber", loss_scale=settings.outlier_threshold_px)
    r, depth = reprojection_residuals(fit.rotations, fit.centres, fit.points, observations, Kab)
    bad = np.zeros(len(tracks), bool)
    np.logical_or.at(bad, observations.points, (np.linalg.norm(r, axis=1) > settings.outlier_threshold_px)
                     | (depth <= 0))
    keep = ~bad
    if keep.sum() < need:
        return None, (f"frames {a} and {b}: only {int(keep.sum())} matches are within the outlier threshold after "
                      f"the two-view adjustment (at least {need} needed)")
    tracks, pix = tracks[keep], pix[:, keep]
    observations = ObservationList.from_dense(pix)
    fit = bundle_adjust(fit.rotations, fit.centres, fit.points[keep], observations, Kab)
    # gauge of the pair: camera a at the origin with R = I, |C_b| = 1
    Ra, Ca = fit.rotations[0], fit.centres[0]
    scale = 1.0 / np.linalg.norm(fit.centres[1] - Ca)
    R = fit.rotations @ Ra.T
    C = scale * (fit.centres - Ca) @ Ra.T
    X = scale * (fit.points - Ca) @ Ra.T
    r, _ = reprojection_residuals(R, C, X, observations, Kab)
    S, V = reduced_camera_matrix(R, C, X, observations, Kab)
    # camera b given camera a: its 6 × 6 block; the baseline length (δC ∥ Ĉ) is the remaining gauge freedom
    S_b = S[6:, 6:]
    u = np.concatenate([np.zeros(3), C[1]])
    big = np.trace(S_b)
    covariance = np.linalg.inv(S_b + big * np.outer(u, u)) - np.outer(u, u) / big
    # d point / d(camera b) at the least-squares solution: -V⁻¹ J_pᵀ J_c over the point's view in b
    _, _, J_c, J_p = residuals_and_jacobians(R, C, X, observations, camera_frame_projections(Kab))
    in_b = observations.cameras == 1
    sensitivity = np.zeros((len(tracks), 3, 6))
    sensitivity[observations.points[in_b]] = -np.linalg.solve(
        V[observations.points[in_b]], np.einsum("nki,nkj->nij", J_p[in_b], J_c[in_b]))
    dof = 2 * len(observations) - 3 * len(tracks) - 5
    return _Motion(R[1], C[1], covariance, tracks, X, V, sensitivity, float(np.sum(r**2)), dof), ""


def _scale(x: np.ndarray, P: np.ndarray, motion: _Motion, sigma: float) -> tuple[float, np.ndarray] | None:
    """Baseline length s from the depths of the filter's points vs the pair's (frame a), and the (7, 7)
    covariance of (δω, δĈ, δs), scale included.

    z_filter ≈ s z_pair.  Each ratio has an independent part (the points' own noise) and
    parts shared by all points: the pair's motion error moves every pair depth at once
    (δz_pair = ∂z/∂(ω, Ĉ) δm), and the filter's points carry the common error of the
    earlier motions, which a per-point filter does not record; that part is taken as
    fully shared (the mean relative depth variance, not divided by the number of points).
    """
    z_filter, var_filter = x[:, 2], P[:, 2, 2]
    z_pair = motion.points[:, 2]
    var_pair = sigma**2 * np.linalg.inv(motion.point_info)[:, 2, 2]
    usable = np.isfinite(z_filter) & (z_filter > 0) & (z_pair > 0)
    if usable.sum() < _MIN_SCALE_POINTS:
        return None
    zf, vf, zp, vp = z_filter[usable], var_filter[usable], z_pair[usable], var_pair[usable]
    s = float(np.median(zf / zp))
    for _ in range(3):
        # z_filter = s z_pair + noise, noise variance var_filter + s² var_pair
        w = 1.0 / (vf + s**2 * vp)
        keep = np.abs(zf - s * zp) * np.sqrt(w) < _SCALE_SCREEN
        if keep.sum() < _MIN_SCALE_POINTS:
            return None
        s = float(np.sum(w[keep] * zf[keep] * zp[keep]) / np.sum(w[keep] * zp[keep] ** 2))
    w, zf, zp = w[keep], zf[keep], zp[keep]
    norm = np.sum(w * zp**2)
    # ∂s/∂z_pair,i = w_i (z_f,i - 2 s z_p,i) / Σ w z_p²; through the pair's motion: Σ_i ∂s/∂z_p,i ∂z_p,i/∂m
    ds_dz = w * (zf - 2.0 * s * zp) / norm
    ds_dm = ds_dz @ motion.sensitivity[usable][keep][:, 2, :]
    motion_cov = sigma**2 * motion.covariance
    cov = np.zeros((7, 7))
    cov[:6, :6] = motion_cov
    cov[6, :6] = cov[:6, 6] = ds_dm @ motion_cov
    shared_filter = s**2 * float(np.mean(vf[keep] / zf**2))
    cov[6, 6] = 1.0 / norm + ds_dm @ motion_cov @ ds_dm + shared_filter
    return s, cov


def reconstruct_recursive(observations: np.ndarray, intrinsics: np.ndarray,
                          settings: PerspectiveSettings) -> Reconstruction:
    """Relative orientations of consecutive frames, then recursive fusion with them as process noise.

    Parameters are validated (F, P, 2) tracks and (F, 3, 3) intrinsics (see
    :func:`~.perspective.reconstruct_perspective`, ``method="recursive"``).
    """
    obs, K = observations, intrinsics
    F, P = obs.shape[:2]
    homogeneous = np.concatenate([np.nan_to_num(obs), np.ones((F, P, 1))], axis=2)
    xn = np.einsum("fij,fpj->fpi", np.linalg.inv(K), homogeneous)
    normalised = xn[..., :2] / xn[..., 2:3]
    # the chain starts at the first consecutive pair with a relative orientation and runs until one fails;
    # one relative orientation per frame pair (not per point)
    reasons: list[str] = []
    first, m = None, None
    for k in range(1, F):
        m, why = _relative_orientation(obs, K, normalised, k - 1, k, settings)
        if m is not None:
            first = k
            break
        reasons.append(why)
    if first is None:
        raise NotEnoughDataError("no two consecutive frames give a relative orientation (the recursive method needs "
                                 "parallax between consecutive frames; try method='batch'): " + "; ".join(reasons[:3]))
    # pairs before the first one found: their own essential matrix failed; start them from the next pair's motion
    while first > 1:
        earlier, why = _relative_orientation(obs, K, normalised, first - 2, first - 1, settings,
                                             guess=(m.rotation, m.direction))
        if earlier is None:
            reasons[first - 2] = why
            break
        first, m = first - 1, earlier
        del reasons[first - 1:]
    motions: dict[int, _Motion | None] = {first: m}
    stop_reason = ""
    for k in range(first + 1, F):
        previous = motions[k - 1]
        motions[k], stop_reason = _relative_orientation(obs, K, normalised, k - 1, k, settings,
                                                        guess=(previous.rotation, previous.direction))
        if motions[k] is None:
            break
    valid = [m for m in motions.values() if m is not None]
    sigma = float(np.sqrt(sum(m.squares for m in valid) / sum(m.dof for m in valid)))
    gate = settings.chi2_bound
    kz = np.concatenate([K, np.zeros((F, 3, 1))], axis=2)
    x = np.full((P, 3), np.nan)
    cov = np.full((P, 3, 3), np.nan)
    alive = np.zeros(P, bool)
    lost = np.zeros(P, bool)
    used = np.zeros((F, P), bool)
    # chained poses in the chain's first frame: x_cam_k = R_k (X - C_k); covariance of (δω, δC) with that frame
    # and the first baseline fixed
    R_chain = np.full((F, 3, 3), np.nan)
    C_chain = np.full((F, 3), np.nan)
    cam_cov = np.full((F, 6, 6), np.nan)
    R_chain[first - 1], C_chain[first - 1], cam_cov[first - 1] = np.eye(3), 0.0, 0.0
    frame_status = np.full(F, FrameStatus.NOT_CONNECTED, dtype=np.int8)
    frame_status[first - 1] = FrameStatus.REGISTERED
    warnings: list[str] = []
    for k, motion in motions.items():
        if motion is None:
            frame_status[k] = FrameStatus.POSE_FAILED
            break
        if k == first:
            s, motion_cov = 1.0, np.zeros((7, 7))
            motion_cov[:6, :6] = sigma**2 * motion.covariance
        else:
            common = alive[motion.tracks]
            found = _scale(np.where(common[:, None], x[motion.tracks], np.nan), cov[motion.tracks], motion, sigma)
            if found is None:
                frame_status[k] = FrameStatus.POSE_FAILED
                warnings.append(f"the chain of relative orientations stops at frame {k}: too few points shared "
                                f"with frame {k - 1}'s structure carry the scale over")
                break
            s, motion_cov = found
        R, C_hat = motion.rotation, motion.direction
        # -- predict: x_k = R (x_{k-1} - s Ĉ);  P_k = R P Rᵀ + J Σ_motion Jᵀ,  J = ∂x_k/∂(ω, Ĉ, s)
        idx = np.flatnonzero(alive)
        moved = (x[idx] - s * C_hat) @ R.T
        J = np.empty((len(idx), 3, 7))
        J[:, :, :3] = -cross_matrix(moved)
        J[:, :, 3:6] = -s * R
        J[:, :, 6] = -(R @ C_hat)
        cov[idx] = R @ cov[idx] @ R.T + J @ motion_cov @ np.swapaxes(J, 1, 2)
        x[idx] = moved
        # -- update with frame k's observations (gated iterated EKF on the 2-D projection)
        seen_k = idx[np.isfinite(obs[k, idx, 0])]
        # a point whose covariance stopped being positive definite (no depth: a far or nearly parallel track)
        # leaves the filter
        broken = seen_k[~(np.linalg.eigvalsh(np.nan_to_num(cov[seen_k], nan=-1.0))[:, 0] > 0)]
        if broken.size:
            alive[broken], lost[broken] = False, True
            seen_k = np.setdiff1d(seen_k, broken)
        if len(seen_k):
            Q = np.broadcast_to(kz[k], (len(seen_k), 3, 4))
            up = iterated_update(Q, x[seen_k], cov[seen_k] / sigma**2, obs[k, seen_k], sigma, gate)
            x[seen_k], cov[seen_k] = up.states, up.covariances * sigma**2
            used[k, seen_k[up.accepted]] = True
        # -- new tracks from the pair, moved into frame k
        new = ~alive[motion.tracks] & ~lost[motion.tracks]
        tracks = motion.tracks[new]
        Y = s * motion.points[new]
        x[tracks] = (Y - s * C_hat) @ R.T
        # covariance: the pair's image noise, and the motion through both the pair's triangulation
        # (implicit function: δY_unit = sensitivity δ(ω, Ĉ)) and the move into frame k, x = s R (Y_unit - Ĉ)
        J_new = np.empty((len(tracks), 3, 7))
        J_new[:, :, :6] = s * R @ motion.sensitivity[new]
        J_new[:, :, :3] -= cross_matrix(x[tracks])
        J_new[:, :, 3:6] -= s * R
        J_new[:, :, 6] = x[tracks] / s
        noise = (sigma * s) ** 2 * R @ np.linalg.inv(motion.point_info[new]) @ R.T
        cov[tracks] = noise + J_new @ motion_cov @ np.swapaxes(J_new, 1, 2)
        alive[tracks] = True
        used[k - 1, tracks] = True
        used[k, tracks] = True
        # -- chain the pose: R_0k = R R_0,k-1;  C_0k = C_0,k-1 + R_0,k-1ᵀ s Ĉ
        Rp, Cp = R_chain[k - 1], C_chain[k - 1]
        R_chain[k] = R @ Rp
        C_chain[k] = Cp + Rp.T @ (s * C_hat)
        prev = np.zeros((6, 6))
        prev[:3, :3] = R
        prev[3:, :3] = Rp.T @ cross_matrix(s * C_hat)
        prev[3:, 3:] = np.eye(3)
        step = np.zeros((6, 7))
        step[:3, :3] = np.eye(3)
        step[3:, 3:6] = s * Rp.T
        step[3:, 6] = Rp.T @ C_hat
        cam_cov[k] = prev @ cam_cov[k - 1] @ prev.T + step @ motion_cov @ step.T
        frame_status[k] = FrameStatus.REGISTERED
    last = int(np.flatnonzero(frame_status == FrameStatus.REGISTERED).max())
    # points from the last camera frame into frame 0
    X = x @ R_chain[last] + C_chain[last]
    X_cov = np.swapaxes(R_chain[last], 0, 1) @ cov @ R_chain[last]
    registered = frame_status == FrameStatus.REGISTERED
    ok = alive & np.isfinite(X).all(axis=1)
    status = np.full(P, PointStatus.TOO_FEW_VIEWS, dtype=np.int8)
    status[lost] = PointStatus.DEGENERATE
    # a point that does not fit its own observations with the chained poses (the chain's accumulated error
    # along a long path) is not trusted
    frames = np.flatnonzero(frame_status == FrameStatus.REGISTERED)
    tracks = np.flatnonzero(ok)
    o = ObservationList.from_dense(obs[np.ix_(frames, tracks)], (used & ok[None])[np.ix_(frames, tracks)])
    r, _ = reprojection_residuals(R_chain[frames], C_chain[frames], X[tracks], o, K[frames])
    with np.errstate(invalid="ignore", divide="ignore"):
        point_rms = np.sqrt(np.bincount(o.points, np.sum(r**2, axis=1), minlength=tracks.size)
                            / np.bincount(o.points, minlength=tracks.size))
    misfit = tracks[~(point_rms <= settings.outlier_threshold_px)]
    status[misfit] = PointStatus.UNRELIABLE
    ok[misfit] = False
    if misfit.size:
        warnings.append(f"{misfit.size} points do not fit their own observations with the chained poses (RMS above "
                        f"{settings.outlier_threshold_px:g} px): marked 'unreliable' — the chain of relative "
                        "orientations accumulates error along the path; method 'batch' adjusts it as a whole")
    status[ok] = PointStatus.OK
    points = np.where(ok[:, None], X, np.nan)
    point_cov = np.full((P, 3, 3), np.nan)
    point_cov[ok] = similarity_free_covariances(X[ok], X_cov[ok])
    inliers = used & registered[:, None] & ok[None]
    frames = np.flatnonzero(registered)
    tracks = np.flatnonzero(ok)
    o = ObservationList.from_dense(obs[np.ix_(frames, tracks)], inliers[np.ix_(frames, tracks)])
    r, _ = reprojection_residuals(R_chain[frames], C_chain[frames], X[tracks], o, K[frames])
    rms = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    dof = 2 * len(o) - 6 * len(frames) - 3 * len(tracks) + 7
    missing = np.flatnonzero(~registered)
    if missing.size:
        why = []
        if first > 1:
            why.append(f"frames before {first - 1} are not reached because " + "; ".join(reasons))
        if stop_reason:
            why.append(f"the chain stops at frame {last + 1}: {stop_reason}")
        warnings.append(f"{missing.size} of {F} frames could not be registered (frames {frame_runs(missing)}): "
                        "the chain of relative orientations does not reach them; they have no pose"
                        + (f" ({'; '.join(why)})" if why else ""))
    warnings.append("the recursive method fuses each point on its own and ignores how the shared motion estimates "
                    "correlate the points: its covariances are over-confident, the more so the closer consecutive "
                    "frames are (docs/perspective.md); method 'batch' gives calibrated covariances")
    t = -np.einsum("fij,fj->fi", R_chain, C_chain)
    return perspective_reconstruction(
        "recursive", obs, K, settings, points=points, point_covariances=point_cov, point_status=status,
        rotations=R_chain, translations=t, pose_covariances=cam_cov, frame_status=frame_status, inliers=inliers,
        pixel_std=sigma, reprojection_rms=rms, degrees_of_freedom=int(dof), initial_pair=(first - 1, first),
        warnings=tuple(warnings))
