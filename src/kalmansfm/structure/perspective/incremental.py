"""The batch method of :func:`~.perspective.reconstruct_perspective`: incremental reconstruction and bundle adjustment.

See :mod:`.perspective` for the pipeline.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from ...errors import NotEnoughDataError
from .bundle import (
    ObservationList,
    bundle_adjust,
    camera_frame_projections,
    free_network_covariances,
    reprojection_residuals,
    residuals_and_jacobians,
)
from .settings import (
    FrameStatus,
    PerspectiveSettings,
    frame_runs,
    perspective_reconstruction,
)
from ..reconstruction import Reconstruction
from ..geometry.batched import inverse3
from ..geometry.pinhole import CameraSet, camera_centres, triangulate_points
from ..fusion import UNRELIABLE_RELATIVE_DEPTH, FusionSettings, fuse
from ..points import PointStatus

__all__ = ["RelativePose", "reconstruct_incremental", "relative_pose"]

# A frame that failed to register is tried again once its shared points have grown by this factor.
_RETRY_GROWTH = 1.2
# A global bundle adjustment runs during growth when the registered frames have grown by this factor.
_GLOBAL_BUNDLE_GROWTH = 1.25
# During growth a bundle adjustment stops when a step lowers the cost by less than this fraction (Ceres' default;
# the refinement adjusts again, to bundle_adjust's own tighter default).
_GROWTH_TOLERANCE = 1e-6
# Initial pair: the triangulation angle counts up to this many degrees in the pair's score.
_ANGLE_CAP_DEG = 20.0
# Initial pair: a pair is degenerate when a homography explains at least this share of the essential inliers.
_MAX_HOMOGRAPHY_SHARE = 0.8


@dataclass
class _PairCandidate:
    first: int
    second: int
    inliers: np.ndarray  # track indices
    rotation: np.ndarray
    translation: np.ndarray
    essential_inliers: int
    homography_inliers: int | None  # None until fitted (only for the pairs that could be chosen)
    median_angle_deg: float

    @property
    def score(self) -> float:
        return len(self.inliers) * min(self.median_angle_deg, _ANGLE_CAP_DEG) ** 2


def _ray_angles_deg(centres: np.ndarray, points: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(N,) largest angle between any used ray and the mean ray of each point, doubled (≈ the spread), degrees."""
    d = points[None] - centres[:, None]
    length = np.linalg.norm(d, axis=2, keepdims=True)
    d = np.where(seen[..., None] & (length > 0), d / np.where(length > 0, length, 1.0), 0.0)
    mean = d.sum(axis=0)
    norm = np.linalg.norm(mean, axis=1, keepdims=True)
    mean = mean / np.where(norm > 0, norm, 1.0)
    cos = np.where(seen, np.einsum("fnk,nk->fn", d, mean), 1.0)
    return 2.0 * np.degrees(np.arccos(np.clip(cos.min(axis=0), -1.0, 1.0)))


@dataclass(frozen=True)
class RelativePose:
    """Relative pose of two calibrated views from their matches (unit baseline).

    Attributes
    ----------
    rotation, translation : the second view's pose, x₂ = R x₁ + t, |t| = 1.
    inliers : (k,) indices into the matches given: cheirality-consistent essential
        inliers that triangulate.
    points : (k, 3) their linear triangulation in the first view's frame.
    angles_deg : (k,) their triangulation angles.
    essential_inliers, homography_inliers : RANSAC inlier counts of the two models (the homography's
        None when it was not fitted).
    """

    rotation: np.ndarray
    translation: np.ndarray
    inliers: np.ndarray
    points: np.ndarray
    angles_deg: np.ndarray
    essential_inliers: int
    homography_inliers: int | None


def relative_pose(first: np.ndarray, second: np.ndarray, threshold: float, homography: bool = True
                  ) -> RelativePose | None:
    """Essential matrix (RANSAC), homography (RANSAC) and pose by cheirality from normalised matches (k, 2).

    ``threshold`` is the RANSAC inlier distance in normalised units.  None when no
    essential matrix is found; otherwise the pose with however many inliers
    triangulate in front of both views (few when the views have no parallax).
    ``homography=False`` skips the homography (the caller fits it later if needed).
    """
    a, b = np.ascontiguousarray(first), np.ascontiguousarray(second)
    if len(a) < 5:
        return None
    # OpenCV's USAC with local optimisation: plain RANSAC at a 4 px threshold picked a wrong essential matrix
    # (baseline direction > 10° off) in 25 of 90 consecutive pairs of the synthetic walk-around, USAC in none
    E, mask_e = cv2.findEssentialMat(a, b, np.eye(3), method=cv2.USAC_ACCURATE, prob=0.999, threshold=threshold)
    if E is None or E.shape != (3, 3) or mask_e is None:
        return None
    n_h = _homography_inliers(a, b, threshold) if homography else None
    _, R, t, mask_pose = cv2.recoverPose(E, a, b, np.eye(3), mask=mask_e.copy())
    keep = np.flatnonzero(mask_pose.ravel() > 0)
    cams = CameraSet.from_pose(np.eye(3), np.stack([np.eye(3), R]), np.stack([np.zeros(3), t.ravel()]))
    tri = triangulate_points(cams, np.stack([a[keep], b[keep]]), orientation=1)
    good = tri.status == PointStatus.OK
    angles = _ray_angles_deg(cams.centers, tri.points[good], np.ones((2, int(good.sum())), bool))
    return RelativePose(R, t.ravel(), keep[good], tri.points[good], angles, int(mask_e.sum()), n_h)


def _homography_inliers(first: np.ndarray, second: np.ndarray, threshold: float) -> int:
    """Inliers of a homography (USAC) between normalised matches: many when the views have no parallax."""
    _, mask = cv2.findHomography(np.ascontiguousarray(first), np.ascontiguousarray(second), cv2.USAC_ACCURATE,
                                 threshold)
    return 0 if mask is None else int(mask.sum())


class _Incremental:
    """The state of an incremental reconstruction (cameras, points, inlier observations)."""

    def __init__(self, obs: np.ndarray, K: np.ndarray, settings: PerspectiveSettings) -> None:
        self.obs, self.K, self.settings = obs, K, settings
        self.F, self.P = obs.shape[:2]
        self.seen = np.isfinite(obs).all(axis=2)
        homogeneous = np.concatenate([np.nan_to_num(obs), np.ones((self.F, self.P, 1))], axis=2)
        xn = np.einsum("fij,fpj->fpi", np.linalg.inv(K), homogeneous)
        self.normalised = xn[..., :2] / xn[..., 2:3]
        self.focal = np.sqrt(K[:, 0, 0] * K[:, 1, 1])
        self.R = np.full((self.F, 3, 3), np.nan)
        self.C = np.full((self.F, 3), np.nan)
        self.X = np.full((self.P, 3), np.nan)
        self.inlier = self.seen.copy()
        self.frame_status = np.full(self.F, FrameStatus.NOT_CONNECTED, dtype=np.int8)
        self.failed_at = np.zeros(self.F)
        self.newest = -1  # the frame registered last
        self.last_global = 0
        self.threshold = settings.outlier_threshold_px
        self.timings: dict[str, float] = {}
        self.warnings: list[str] = []
        cv2.setRNGSeed(settings.seed)

    # -- bookkeeping -------------------------------------------------------------------------
    @property
    def registered(self) -> np.ndarray:
        return self.frame_status == FrameStatus.REGISTERED

    @property
    def has_point(self) -> np.ndarray:
        return np.isfinite(self.X[:, 0])

    def _timed(self, name: str, start: float) -> None:
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - start

    def _cameras(self, frames: np.ndarray) -> CameraSet:
        t = -np.einsum("fij,fj->fi", self.R[frames], self.C[frames])
        return CameraSet.from_pose(self.K[frames], self.R[frames], t, frames=frames)

    def _observations(self) -> tuple[ObservationList, np.ndarray, np.ndarray]:
        """Inlier observations of reconstructed points in registered frames, compacted indices."""
        frames = np.flatnonzero(self.registered)
        tracks = np.flatnonzero(self.has_point)
        use = self.inlier[np.ix_(frames, tracks)] & self.seen[np.ix_(frames, tracks)]
        cams, pts = np.nonzero(use)
        return ObservationList(cams, pts, self.obs[frames[cams], tracks[pts]]), frames, tracks

    # -- 1. initial pair -------------------------------------------------------------------------
    def _candidate_pairs(self) -> list[tuple[int, int]]:
        s = self.seen.astype(np.float64)
        shared = s @ s.T
        # mean squared displacement of the shared tracks (normalised units): a cheap parallax proxy
        x = np.where(self.seen[..., None], self.normalised, 0.0)
        sq = np.einsum("fpi,fpi->fp", x, x)
        flat = x.reshape(self.F, -1)
        moved = (sq @ s.T + s @ sq.T - 2.0 * flat @ flat.T) / np.maximum(shared, 1.0)
        a, b = np.triu_indices(self.F, 1)
        need = 2 * self.settings.min_registration_points
        ok = shared[a, b] >= need
        if not ok.any():
            raise NotEnoughDataError(f"no two frames share >= {need} tracks (most shared: {int(shared[a, b].max())}); "
                                     "the tracks are too short or the frames too different to start a reconstruction")
        a, b = a[ok], b[ok]
        proxy = shared[a, b] * np.minimum(np.sqrt(np.maximum(moved[a, b], 0.0)), np.radians(_ANGLE_CAP_DEG))
        order = np.argsort(-proxy, kind="stable")[: self.settings.max_initial_pairs]
        return list(zip(a[order].tolist(), b[order].tolist()))

    def _try_pair(self, i: int, j: int) -> _PairCandidate | None:
        tracks = np.flatnonzero(self.seen[i] & self.seen[j])
        pose = relative_pose(self.normalised[i, tracks], self.normalised[j, tracks], self._pair_threshold(i, j),
                             homography=False)
        if pose is None:
            return None
        angle = float(np.median(pose.angles_deg)) if len(pose.angles_deg) else 0.0
        return _PairCandidate(i, j, tracks[pose.inliers], pose.rotation, pose.translation, pose.essential_inliers,
                              pose.homography_inliers, angle)

    def _pair_threshold(self, i: int, j: int) -> float:
        return self.threshold / np.sqrt(self.focal[i] * self.focal[j])

    def _fit_homography(self, c: _PairCandidate) -> None:
        tracks = np.flatnonzero(self.seen[c.first] & self.seen[c.second])
        c.homography_inliers = _homography_inliers(self.normalised[c.first, tracks], self.normalised[c.second, tracks],
                                                  self._pair_threshold(c.first, c.second))

    def initialize(self) -> None:
        start = time.perf_counter()
        tried = [c for c in (self._try_pair(i, j) for i, j in self._candidate_pairs()) if c is not None]
        # the best-scoring pair that a homography does not explain; the homography (the degeneracy test) is
        # fitted best first, only until a pair passes
        best = None
        for c in sorted(tried, key=lambda c: -c.score):  # stable: among equal scores the first tried, as max()
            if len(c.inliers) < 2 * self.settings.min_registration_points \
                    or c.median_angle_deg < self.settings.min_pair_angle_deg:
                continue
            self._fit_homography(c)
            if c.homography_inliers < _MAX_HOMOGRAPHY_SHARE * c.essential_inliers:
                best = c
                break
        self._timed("initial_pair", start)
        if best is None:
            for c in tried:
                if c.homography_inliers is None:
                    self._fit_homography(c)
            raise NotEnoughDataError(self._why_no_pair(tried))
        self.initial_pair = (best.first, best.second)
        self.R[best.first], self.C[best.first] = np.eye(3), 0.0
        self.R[best.second], self.C[best.second] = best.rotation, -best.rotation.T @ best.translation
        self.frame_status[[best.first, best.second]] = FrameStatus.REGISTERED
        self._triangulate(np.flatnonzero(self.seen[best.first] & self.seen[best.second]))
        self._bundle("huber", _GROWTH_TOLERANCE)
        self.last_global = 2

    def start_from(self, rotations: np.ndarray, centres: np.ndarray, registered: np.ndarray,
                   initial_pair: tuple[int, int]) -> None:
        """Take the registered poses of an earlier reconstruction of these frames instead of an initial pair.

        Every track seen in two of those frames is triangulated and one bundle adjustment follows; growth
        and refinement then go on as after an initial pair.
        """
        self.initial_pair = initial_pair
        self.R[registered], self.C[registered] = rotations[registered], centres[registered]
        self.frame_status[registered] = FrameStatus.REGISTERED
        self._triangulate(np.flatnonzero(self.seen[registered].sum(axis=0) >= 2))
        self._bundle("huber", _GROWTH_TOLERANCE)
        self.last_global = int(registered.sum())
        self._reject(2.0 * self.threshold)

    def _why_no_pair(self, tried: list[_PairCandidate]) -> str:
        need = 2 * self.settings.min_registration_points
        if not tried:
            return "no frame pair gives an essential matrix: too few correct matches between any two frames"
        share = max(c.homography_inliers / max(c.essential_inliers, 1) for c in tried)
        if all(c.homography_inliers >= _MAX_HOMOGRAPHY_SHARE * c.essential_inliers for c in tried):
            return (f"degenerate scene: in every frame pair a homography explains the matches (up to {100 * share:.0f} "
                    "% of the essential-matrix inliers): all points on one plane, or a camera that only rotates; "
                    "depth cannot be recovered")
        if all(len(c.inliers) < need for c in tried):
            return (f"no frame pair has >= {need} matches consistent with one relative pose (most: "
                    f"{max(len(c.inliers) for c in tried)}): too few correct matches, or points at infinity")
        angle = max(c.median_angle_deg for c in tried)
        return (f"no frame pair has enough parallax: the largest median triangulation angle is {angle:.2f} degrees "
                f"(need >= {self.settings.min_pair_angle_deg}); the camera barely moved, or it only rotated")

    # -- 2. growth -------------------------------------------------------------------------------
    def register_next(self) -> bool:
        start = time.perf_counter()
        counts = (self.seen & self.has_point[None]).sum(axis=1)
        eligible = ~self.registered & (counts >= self.settings.min_registration_points) \
            & (counts >= _RETRY_GROWTH * self.failed_at)
        for f in np.flatnonzero(eligible)[np.argsort(-counts[eligible], kind="stable")]:
            tracks = np.flatnonzero(self.seen[f] & self.has_point)
            X = np.ascontiguousarray(self.X[tracks])
            x = np.ascontiguousarray(self.normalised[f, tracks])
            threshold = self.threshold / self.focal[f]
            ok, rvec, tvec, inl = cv2.solvePnPRansac(X, x, np.eye(3), None, reprojectionError=threshold,
                                                     confidence=0.9999, iterationsCount=1000,
                                                     flags=cv2.SOLVEPNP_SQPNP)
            n_in = 0 if inl is None else len(inl)
            if not ok or n_in < self.settings.min_registration_points:
                self.frame_status[f] = FrameStatus.POSE_FAILED
                self.failed_at[f] = counts[f]
                continue
            inl = inl.ravel()
            rvec, tvec = cv2.solvePnPRefineLM(X[inl], x[inl], np.eye(3), None, rvec, tvec)
            R = cv2.Rodrigues(rvec)[0]
            self.R[f], self.C[f] = R, camera_centres(R, tvec.ravel())
            self.frame_status[f] = FrameStatus.REGISTERED
            self.newest = f
            outliers = np.setdiff1d(np.arange(len(tracks)), inl)
            self.inlier[f, tracks[outliers]] = False
            self._timed("registration", start)
            return True
        self._timed("registration", start)
        return False

    def grow(self) -> None:
        while self.register_next():
            frames = np.flatnonzero(self.registered)
            # tracks the new frame sees: the others' observations have not changed since they were last tried
            # (the refinement re-estimates every track)
            waiting = ~self.has_point & self.seen[self.newest] & ((self.seen & self.inlier)[frames].sum(axis=0) >= 2)
            self._triangulate(np.flatnonzero(waiting))
            if len(frames) >= _GLOBAL_BUNDLE_GROWTH * self.last_global:
                self._bundle("huber", _GROWTH_TOLERANCE)
                self.last_global = len(frames)
                self._reject(2.0 * self.threshold)

    # -- structure and bundle steps -----------------------------------------------------------------
    def _triangulate(self, tracks: np.ndarray, gate_px: float | None = None, readmit: bool = False) -> None:
        """(Re-)estimate the given tracks from their registered observations with the fusion engine."""
        start = time.perf_counter()
        frames = np.flatnonzero(self.registered)
        if len(tracks) == 0:
            return
        # only the frames that see these tracks: a long sequence of short tracks leaves most of the others empty
        seeing = frames[self.seen[np.ix_(frames, tracks)].any(axis=1)]
        frames = seeing if len(seeing) >= 2 else frames
        use = self.seen[np.ix_(frames, tracks)]
        if not readmit:
            use &= self.inlier[np.ix_(frames, tracks)]
        obs = np.where(use[..., None], self.obs[np.ix_(frames, tracks)], np.nan)
        gate = self.threshold if gate_px is None else gate_px
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # points at a camera's plane
            fused = fuse(obs, self._cameras(frames), method="batch",
                         pixel_std=gate / np.sqrt(self.settings.chi2_bound),
                         outlier_probability=self.settings.outlier_probability)
        ok = fused.point_status == PointStatus.OK
        used = use & ~fused.observations.rejected_mask()
        angles = _ray_angles_deg(self.C[frames], np.where(ok[:, None], fused.points, 0.0), used & ok[None])
        ok &= angles >= self.settings.min_triangulation_angle_deg
        # a track that lost an observation to the outlier test is trusted only with >= 3 consistent views left:
        # two views leave one degree of freedom, and two mismatches can agree along an epipolar line
        lost = (self.seen[np.ix_(frames, tracks)] & ~used).any(axis=0)
        ok &= ~lost | (used.sum(axis=0) >= 3)
        self.X[tracks] = np.where(ok[:, None], fused.points, np.nan)
        block = self.inlier[np.ix_(frames, tracks)]
        block = np.where(use, used, block) if not readmit else np.where(self.seen[np.ix_(frames, tracks)], used, block)
        self.inlier[np.ix_(frames, tracks)] = block
        self._timed("triangulation", start)

    def _bundle(self, loss: str, function_tolerance: float | None = None) -> None:
        start = time.perf_counter()
        obs, frames, tracks = self._observations()
        fit = bundle_adjust(self.R[frames], self.C[frames], self.X[tracks], obs, self.K[frames], loss=loss,
                            loss_scale=self.threshold,
                            **({} if function_tolerance is None else {"function_tolerance": function_tolerance}))
        self.R[frames], self.C[frames], self.X[tracks] = fit.rotations, fit.centres, fit.points
        self._timed("bundle_adjustment", start)

    def _reject(self, threshold: float) -> None:
        """Drop inlier observations farther than ``threshold`` px (or behind the camera); then points with < 2."""
        obs, frames, tracks = self._observations()
        r, depth = reprojection_residuals(self.R[frames], self.C[frames], self.X[tracks], obs, self.K[frames])
        bad = (np.linalg.norm(r, axis=1) > threshold) | (depth <= 0)
        self.inlier[frames[obs.cameras[bad]], tracks[obs.points[bad]]] = False
        count = (self.inlier & self.seen)[frames].sum(axis=0)
        self.X[count < 2] = np.nan

    def _sigma(self) -> tuple[float, float, int]:
        """σ with the degrees of freedom counted, the RMS residual length, and the degrees of freedom."""
        obs, frames, tracks = self._observations()
        r, _ = reprojection_residuals(self.R[frames], self.C[frames], self.X[tracks], obs, self.K[frames])
        sq = float(np.sum(r**2))
        dof = 2 * len(obs) - 6 * len(frames) - 3 * len(tracks) + 7
        if dof <= 0:
            raise NotEnoughDataError(f"the reconstruction has no redundancy to estimate the pixel noise "
                                     f"({len(obs)} observations of {len(tracks)} points in {len(frames)} frames)")
        return float(np.sqrt(sq / dof)), float(np.sqrt(sq / max(len(obs), 1))), dof

    # -- 3. refinement -------------------------------------------------------------------------------
    def _settled(self, gate_px: float) -> np.ndarray:
        """(P,) tracks whose fusion would give back their point and inliers: nothing to re-estimate.

        A reconstructed track qualifies when every registered observation of it is an inlier (none to
        readmit), all lie in front of their cameras, and the fusion engine's tests pass at the
        bundle-adjusted point — which is already the track's least-squares point for these cameras:
        each observation's leave-one-out residual rᵀ (I - J N⁻¹ Jᵀ)⁻¹ r within the χ²(2) gate (tracks
        of ≥ 3 views), the whole cost within the χ²(1) gate (tracks of 2 views), a reliable depth and
        the triangulation angle.  Computed on the observation list, not on (views × tracks) arrays.
        """
        obs, frames, tracks = self._observations()
        r, depth, _, J = residuals_and_jacobians(self.R[frames], self.C[frames], self.X[tracks], obs,
                                                 camera_frame_projections(self.K[frames]))
        m = len(tracks)
        views = np.bincount(obs.points, minlength=m)
        JtJ = (np.swapaxes(J, 1, 2) @ J).reshape(-1, 9)
        normal = np.stack([np.bincount(obs.points, weights=JtJ[:, k], minlength=m) for k in range(9)], axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            normal_inv = inverse3(normal.reshape(m, 3, 3))
            A = np.eye(2) - J @ normal_inv[obs.points] @ np.swapaxes(J, 1, 2)
            det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
            leave_one_out = (A[:, 1, 1] * r[:, 0] ** 2 - (A[:, 0, 1] + A[:, 1, 0]) * r[:, 0] * r[:, 1]
                             + A[:, 0, 0] * r[:, 1] ** 2) / det
        # the fusion's unit is σ = gate / √χ²₂(p): its χ²(2) gate is gate² in pixels², its χ²(1) gate scales alike
        sigma2 = gate_px**2 / self.settings.chi2_bound
        gate1 = FusionSettings(outlier_probability=self.settings.outlier_probability).gate1
        bad = (depth <= 0) | ((views[obs.points] >= 3) & ~(leave_one_out <= gate_px**2))
        bad_track = np.bincount(obs.points, weights=bad, minlength=m) > 0
        cost = np.bincount(obs.points, weights=np.einsum("na,na->n", r, r), minlength=m)
        bad_track |= (views == 2) & (cost > gate1 * sigma2)
        # the fusion's status tests as well: enough parallax for a reliable depth (σ_d / d from the first camera that
        # sees the point, σ² N⁻¹ its covariance) and the triangulation angle
        first = np.full(m, len(frames))
        np.minimum.at(first, obs.points, obs.cameras)
        ray = self.X[tracks] - self.C[frames[np.minimum(first, len(frames) - 1)]]
        distance = np.linalg.norm(ray, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            relative = np.sqrt(sigma2 * np.abs(np.einsum("ni,nij,nj->n", ray, normal_inv, ray))) / distance**2
        used = np.zeros((len(frames), m), bool)
        used[obs.cameras, obs.points] = True
        angles = _ray_angles_deg(self.C[frames], self.X[tracks], used)
        bad_track |= ~(relative <= UNRELIABLE_RELATIVE_DEPTH) | (angles < self.settings.min_triangulation_angle_deg)
        settled = np.zeros(self.P, bool)
        settled[tracks] = ~bad_track & (views >= 2) & (views == self.seen[frames][:, tracks].sum(axis=0))
        return settled

    def refine(self) -> None:
        frames = np.flatnonzero(self.registered)
        candidates = np.flatnonzero(self.seen[frames].sum(axis=0) >= 2)
        self._triangulate(candidates[~self._settled(self.threshold)[candidates]], readmit=True)
        self._bundle("huber")
        adjusted = False  # by least squares, on the current inliers
        for _ in range(self.settings.refinement_rounds):
            sigma, _, _ = self._sigma()
            gate = max(self.threshold, np.sqrt(self.settings.chi2_bound) * sigma)
            inlier, reconstructed = self.inlier.copy(), self.has_point.copy()
            # only the tracks the outlier test would change (or with observations to readmit) are fused again
            self._triangulate(candidates[~self._settled(gate)[candidates]], gate_px=gate, readmit=True)
            if adjusted and np.array_equal(inlier, self.inlier) and np.array_equal(reconstructed, self.has_point):
                break  # converged: another bundle adjustment would start at its own minimum
            self._bundle("linear")
            adjusted = True

    # -- 4. result ------------------------------------------------------------------------------------
    def result(self, method: str) -> Reconstruction:
        start = time.perf_counter()
        sigma, rms, dof = self._sigma()
        obs, frames, tracks = self._observations()
        cov = free_network_covariances(self.R[frames], self.C[frames], self.X[tracks], obs, self.K[frames], sigma)
        self._timed("covariance", start)
        # output frame: the initial pair's first camera at the origin, unit baseline
        a, b = self.initial_pair
        Q = self.R[a]
        scale = 1.0 / np.linalg.norm(self.C[b] - self.C[a])
        origin = self.C[a]
        X = scale * (self.X - origin) @ Q.T
        R = self.R @ Q.T
        C = scale * (self.C - origin) @ Q.T
        point_cov = np.full((self.P, 3, 3), np.nan)
        point_cov[tracks] = scale**2 * Q @ cov.points @ Q.T
        turn = np.zeros((6, 6))
        turn[:3, :3] = np.eye(3)
        turn[3:, 3:] = scale * Q
        cam_cov = np.full((self.F, 6, 6), np.nan)
        cam_cov[frames] = turn @ cov.cameras @ turn.T
        t = -np.einsum("fij,fj->fi", R, C)
        status = np.full(self.P, PointStatus.TOO_FEW_VIEWS, dtype=np.int8)
        status[self.has_point] = PointStatus.OK
        inliers = self.inlier & self.seen & self.registered[:, None] & self.has_point[None]
        degenerate = ~self.has_point & ((self.seen & self.inlier)[frames].sum(axis=0) >= 2)
        status[degenerate] = PointStatus.DEGENERATE
        self._warn()
        return perspective_reconstruction(
            method, self.obs, self.K, self.settings, points=X, point_covariances=point_cov, point_status=status,
            rotations=R, translations=t, pose_covariances=cam_cov, frame_status=self.frame_status.copy(),
            inliers=inliers, pixel_std=sigma, reprojection_rms=rms, degrees_of_freedom=dof,
            initial_pair=self.initial_pair, warnings=tuple(self.warnings), timings=dict(self.timings))

    def _warn(self) -> None:
        missing = np.flatnonzero(~self.registered)
        if missing.size:
            self.warnings.append(f"{missing.size} of {self.F} frames could not be registered (frames "
                                 f"{frame_runs(missing)}): "
                                 "they share too few consistent tracks with the reconstruction and have no pose")
        done = int(self.has_point.sum())
        if done < 0.5 * self.P:
            self.warnings.append(f"only {done} of {self.P} tracks were reconstructed")


def reconstruct_incremental(observations: np.ndarray, intrinsics: np.ndarray, settings: PerspectiveSettings,
                            start: Reconstruction | None = None) -> Reconstruction:
    """Initial pair (or ``start``'s registered poses), growth, refinement and covariances.

    On validated (F, P, 2) tracks and (F, 3, 3) K; ``start`` is a reconstruction of the same F frames
    whose registered poses replace the initial pair (the result is then in its frame).
    """
    state = _Incremental(observations, intrinsics, settings)
    if start is None:
        state.initialize()
    else:
        registered = start.frame_status == FrameStatus.REGISTERED
        state.start_from(start.rotations, camera_centres(start.rotations, start.translations), registered,
                         start.details.initial_pair)
    state.grow()
    state.refine()
    return state.result("batch")
