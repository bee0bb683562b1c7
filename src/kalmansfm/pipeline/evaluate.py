"""What a run measured: tracking statistics, the factorization's figures, and the comparison with ground truth.

Each function returns the frozen record that :class:`~kalmansfm.io.summary.RunSummary`
holds; nothing here writes files.
"""

from __future__ import annotations

import warnings

import numpy as np

from ..io.ground_truth import GroundTruth
from ..io.summary import Similarity, StructureMetrics, TrackingMetrics, TrackMetrics, TruthComparison
from ..structure import PointUncertainty, Reconstruction, align_similarity, factorize, point_uncertainty
from ..structure.geometry.orthographic import camera_rotation_matrices, rotation_angle_deg
from ..structure.affine.factorization import DEFAULT_MAX_ITERATIONS
from ..tracking.tracks import LOST, PREDICTED, Tracks

__all__ = ["compare_with_truth", "factorize_tracks", "structure_metrics", "structure_uncertainty", "tracking_metrics"]


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


def factorize_tracks(tracks: Tracks, *, weighted: bool = True, max_iterations: int = DEFAULT_MAX_ITERATIONS) -> Reconstruction:
    """Factorize the measured positions of ``tracks`` (a coasting prediction is no observation).

    With ``weighted`` (and covariances in the tracks) each observation has the least-squares
    weight 1 / σ², σ the tracker's posterior standard deviation.
    """
    weights = tracks.observation_weights() if weighted else None
    return factorize(tracks.observations(), weights=weights, max_iterations=max_iterations)


def structure_uncertainty(tracks: Tracks, reconstruction: Reconstruction, *, weighted: bool = True) -> PointUncertainty:
    """Each point's covariance and status for a reconstruction made by :func:`factorize_tracks` (same ``weighted``)."""
    weights = tracks.observation_weights() if weighted else None
    return point_uncertainty(reconstruction, tracks.observations(), weights=weights)


def structure_metrics(
    reconstruction: Reconstruction,
    *,
    weighted: bool,
    smoothed: bool | int,
    uncertainty: PointUncertainty | None = None,
) -> StructureMetrics:
    """The figures of a factorization (and of its points' uncertainty, when given) for the run summary."""
    unreliable = 0
    if uncertainty is not None:
        unreliable = int((np.isfinite(reconstruction.points).all(axis=1) & ~uncertainty.reliable).sum())
    return StructureMetrics(
        method=reconstruction.method,
        frames=int(reconstruction.motion.shape[0]),
        points=int(reconstruction.points.shape[0]),
        reconstructed_frames=int(np.isfinite(reconstruction.motion).all(axis=(1, 2)).sum()),
        reconstructed_points=int(np.isfinite(reconstruction.points).all(axis=1).sum()),
        iterations=int(reconstruction.iterations),
        singular_values=tuple(float(v) for v in reconstruction.singular_values[:10]),
        residual_rms_px=float(reconstruction.residual_rms),
        weighted=weighted,
        smoothed=smoothed,
        warnings=tuple(reconstruction.warnings),
        noise_std=None if uncertainty is None or not np.isfinite(uncertainty.noise_std) else uncertainty.noise_std,
        unreliable_points=unreliable,
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
