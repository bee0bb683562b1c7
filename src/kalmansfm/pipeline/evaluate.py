"""What a run measured: tracking statistics, a reconstruction's figures, and the comparison with ground truth.

Each function returns the frozen record that :class:`~kalmansfm.io.summary.RunSummary`
holds; nothing here writes files.  Every number the summary and the report show is computed
here, once.
"""

from __future__ import annotations

import warnings

import numpy as np
from tqdm import tqdm

from ..io.ground_truth import GroundTruth
from ..io.summary import ReconstructionMetrics, Similarity, TrackingMetrics, TrackMetrics, TruthComparison
from ..structure import PointStatus, Reconstruction, align_similarity, factorize, rms_std
from ..structure.affine.factorization import DEFAULT_MAX_ITERATIONS
from ..structure.geometry.orthographic import camera_rotation_matrices, rotation_angle_deg
from ..tracking.tracks import LOST, PREDICTED, Tracks
from .stage import bar_progress

__all__ = ["compare_with_truth", "factorize_tracks", "reconstruction_metrics", "tracking_metrics"]


def _optional(values: np.ndarray, present: np.ndarray) -> tuple[float | None, ...]:
    return tuple(float(v) if ok else None for v, ok in zip(values, present))


def tracking_metrics(tracks: Tracks) -> TrackingMetrics:
    """Per-run and per-track statistics of tracks (no ground truth needed).

    Examples
    --------
    >>> t = Tracks.empty(3, 1); t.status[:] = [[1], [2], [1]]; t.covariances[:] = np.eye(4)
    >>> m = tracking_metrics(t)
    >>> round(m.measured_fraction, 3), m.per_track[0].frames_predicted
    (0.667, 1)
    """
    alive = tracks.alive
    measured = tracks.measured
    std = tracks.position_std
    mean_std = np.full(tracks.n_tracks, np.nan)
    filtered = tracks.filtered  # not the start-up prior of the initialising frames
    if std is not None and filtered.any():
        rms_std = np.sqrt(np.mean(std**2, axis=-1))  # RMS of the x and y standard deviations
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a track that never got past its start: NaN
            mean_std = np.nanmean(np.where(filtered, rms_std, np.nan), axis=0)
    lost = tracks.status == LOST
    lost_at = np.where(lost.any(axis=0), np.argmax(lost, axis=0), -1)
    per_track = tuple(
        TrackMetrics(
            track_id=int(tid),
            frames_measured=int(m),
            frames_predicted=int(p),
            lost_at=int(at) if at >= 0 else None,
            mean_std_px=float(s) if np.isfinite(s) else None,
        )
        for tid, m, p, at, s in zip(tracks.track_ids, measured.sum(axis=0), (tracks.status == PREDICTED).sum(axis=0),
                                    lost_at, mean_std)
    )
    trace = tracks.mean_covariance_trace()
    return TrackingMetrics(
        frames=tracks.n_frames,
        tracks=tracks.n_tracks,
        measured_fraction=float(measured.sum() / max(alive.sum(), 1)),
        alive_in_last_frame=int(alive[-1].sum()) if tracks.n_frames else 0,
        survival_of_first_frame_tracks=float(tracks.survival()[-1]) if tracks.n_frames else 0.0,
        lost=int(lost.sum()),
        mean_covariance_trace=_optional(trace, np.isfinite(trace)),
        per_track=per_track,
    )


def factorize_tracks(tracks: Tracks, *, weighted: bool = True, max_iterations: int = DEFAULT_MAX_ITERATIONS,
                     progress: bool = False) -> Reconstruction:
    """Factorize the measured positions of ``tracks`` (a coasting prediction is no observation).

    With ``weighted`` (and covariances in the tracks) each observation has the least-squares
    weight 1 / σ², σ the tracker's posterior standard deviation.  The reconstruction carries
    the tracks' frame numbers and ids.  ``progress`` shows a bar over the fit's iterations on
    stderr (the closed form of complete unweighted tracks has none).
    """
    weights = tracks.observation_weights() if weighted else None
    with tqdm(total=max_iterations, desc="factorization", unit="it", disable=not progress, leave=False) as bar:
        rec = factorize(tracks.observations(), weights=weights, max_iterations=max_iterations,
                        progress=bar_progress(bar) if progress else None)
    return rec.with_ids(tracks.frames, tracks.track_ids)


def reconstruction_metrics(
    rec: Reconstruction,
    *,
    smoothed: bool | int | None = None,
    intrinsics: str | None = None,
    camera_choice: str | None = None,
    skipped_frames: tuple[int, ...] = (),
) -> ReconstructionMetrics:
    """The run summary's record of any reconstruction.

    Parameters
    ----------
    rec : the reconstruction (its ``frame_ids`` are the frame numbers reported).
    smoothed : whether the tracks it was made from were RTS-smoothed (True or the lag).
    intrinsics : where a calibrated reconstruction's K came from.
    camera_choice : with ``--camera auto``, which model was kept and why.
    skipped_frames : frames with observations but no camera (fusion).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> shape = rng.normal(size=(10, 3)) * 30
    >>> rows = [np.linalg.qr(rng.normal(size=(3, 3)))[0][:2] for _ in range(5)]
    >>> rec = factorize(np.stack([shape @ m.T + 50 for m in rows]))
    >>> m = reconstruction_metrics(rec)
    >>> m.kind, m.frames, m.reconstructed, m.observations, m.used
    ('affine', 5, 10, 50, 50)
    """
    status = rec.point_status
    ok, reg = rec.reconstructed, rec.registered
    details = rec.details
    noise = rec.noise

    def finite(value: float) -> float | None:
        return float(value) if np.isfinite(value) else None

    centre_std = None
    if rec.pose_covariances is not None and reg.any():
        centre_std = float(np.median(rms_std(rec.pose_covariances[reg, 3:, 3:])))
    initial_pair = getattr(details, "initial_pair", None)
    sv = getattr(details, "singular_values", None)
    return ReconstructionMetrics(
        kind=rec.kind,
        method=rec.method,
        camera_model=rec.camera_model,
        frames=rec.n_frames,
        registered_frames=int(reg.sum()),
        unregistered=tuple(int(f) for f in rec.frame_ids[~reg]),
        points=rec.n_points,
        reconstructed=int(ok.sum()),
        unreliable=int(np.sum(status == PointStatus.UNRELIABLE)),
        too_few_views=int(np.sum(status == PointStatus.TOO_FEW_VIEWS)),
        degenerate=int(np.sum(status == PointStatus.DEGENERATE)),
        behind_camera=int(np.sum(status == PointStatus.BEHIND_CAMERA)),
        observations=len(rec.observations),
        used=rec.observations.n_used,
        rejected=rec.observations.n_rejected,
        noise_std=finite(noise.std),
        noise_estimated=noise.estimated,
        noise_unit=noise.unit,
        noise_model=noise.model,
        degrees_of_freedom=int(noise.degrees_of_freedom),
        reprojection_rms_px=finite(rec.reprojection_rms),
        median_point_std=float(np.median(rms_std(rec.point_covariances[ok]))) if ok.any() else None,
        median_centre_std=centre_std,
        covariance_gauge=rec.covariance_gauge,
        warnings=tuple(rec.warnings),
        singular_values=() if sv is None else tuple(float(v) for v in sv[:10]),
        iterations=getattr(details, "iterations", None),
        weighted=getattr(details, "weighted", None),
        smoothed=smoothed,
        initial_pair=None if initial_pair is None else (int(rec.frame_ids[initial_pair[0]]),
                                                        int(rec.frame_ids[initial_pair[1]])),
        outlier_threshold_px=getattr(details, "outlier_threshold_px", None),
        outlier_probability=getattr(details, "outlier_probability", None),
        orientation=getattr(details, "orientation", None),
        passes=getattr(details, "passes", None),
        intrinsics=intrinsics,
        camera_choice=camera_choice,
        skipped_frames=tuple(int(f) for f in skipped_frames),
        noise_parameters=tuple((str(name), float(value)) for name, value in noise.parameters),
    )


def compare_with_truth(tracks: Tracks, reconstruction: Reconstruction | None, truth: GroundTruth) -> TruthComparison:
    """Tracking error, shape error and camera rotation error against ground truth.

    Tracking error is over the (frame, track) pairs where the point is visible and the
    tracker measured it.  Shape error is the RMS distance after the best similarity
    alignment (a mirror image allowed: the depth reversal of orthographic factorization),
    in percent of the object's RMS radius; the camera rotations are compared after the
    same alignment.
    """
    true_positions = truth.aligned_to(tracks.track_ids)  # NaN where not visible
    visible = np.isfinite(true_positions).all(axis=-1)
    measured = tracks.measured & visible
    errors = np.linalg.norm(tracks.positions - true_positions, axis=-1)
    squared = np.where(measured, errors, 0.0) ** 2
    n_frame, n_track = measured.sum(axis=1), measured.sum(axis=0)
    comparison = {
        "visible_measured_fraction": float(measured.sum() / max(visible.sum(), 1)),
        "rms_error_per_frame_px": _optional(np.sqrt(squared.sum(axis=1) / np.maximum(n_frame, 1)), n_frame > 0),
        "per_track_rms_error_px": _optional(np.sqrt(squared.sum(axis=0) / np.maximum(n_track, 1)), n_track > 0),
    }
    if measured.any():
        comparison["tracking_rms_error_px"] = float(np.sqrt(np.mean(errors[measured] ** 2)))
        comparison["within_2px"] = float(np.mean(errors[measured] <= 2.0))
        comparison["median_error_px"] = float(np.median(errors[measured]))
        comparison["max_error_px"] = float(np.max(errors[measured]))
    if reconstruction is not None and truth.points_3d is not None:
        comparison.update(_compare_shape(tracks, reconstruction, truth))
    return TruthComparison(**comparison)


def _compare_shape(tracks: Tracks, reconstruction: Reconstruction, truth: GroundTruth) -> dict[str, object]:
    index = np.searchsorted(truth.track_ids, tracks.track_ids).clip(0, max(len(truth.track_ids) - 1, 0))
    known = truth.track_ids[index] == tracks.track_ids
    ok = known & np.isfinite(reconstruction.points).all(axis=1)
    if ok.sum() < 4:
        return {}
    true_points = truth.points_3d[index[ok]]  # type: ignore[index]
    alignment = align_similarity(reconstruction.points[ok], true_points, allow_reflection=True)
    radius = float(np.sqrt(np.mean(np.sum((true_points - true_points.mean(0)) ** 2, axis=1))))
    result: dict[str, object] = {
        "shape_error_pct": 100.0 * alignment.rms / radius,
        "alignment": Similarity(
            scale=float(alignment.scale),
            rotation=tuple(tuple(float(v) for v in row) for row in alignment.rotation),  # type: ignore[misc]
            translation=tuple(float(v) for v in alignment.translation),  # type: ignore[arg-type]
        ),
    }
    if truth.rotation_rows is not None:
        # truth ≈ s A recovered ⇒ recovered camera rows ≈ (true rows) A, up to scale.  A mirror
        # image (det A = -1) is compared as the depth-reversed solution D S, R D with the
        # proper rotation A D, D = diag(1, 1, -1).
        mirrored = np.linalg.det(alignment.rotation) < 0
        candidate = reconstruction.mirrored() if mirrored else reconstruction
        rotation = alignment.rotation @ np.diag([1.0, 1.0, -1.0]) if mirrored else alignment.rotation
        finite = np.isfinite(candidate.motion).all(axis=(1, 2))
        recovered = camera_rotation_matrices(np.where(finite[:, None, None], candidate.motion, 1.0))
        expected = camera_rotation_matrices(truth.rotation_rows[tracks.frames] @ rotation)
        angles = rotation_angle_deg(recovered, expected)
        result["rotation_error_deg"] = _optional(angles, finite)
    return result
