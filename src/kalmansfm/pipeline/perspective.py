"""Calibrated reconstruction in a run: intrinsics from the options, the summary record, the files.

Shared by ``kalmansfm reconstruct --camera perspective|auto`` and ``kalmansfm demo --camera perspective``.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import InvalidInputError
from ..io.atomic import OutputDirectory
from ..io.intrinsics import intrinsics_from_focal, read_intrinsics
from ..io.cameras import pose_cameras_csv
from ..io.summary import PerspectiveMetrics
from ..report.figures import camera_path_figure
from ..structure.perspective.reconstruct import (
    COVARIANCE_GAUGE,
    PerspectiveReconstruction,
    PerspectiveSettings,
)
from ..structure.points import PointStatus, rms_std
from .stage import stage_points

__all__ = ["CAMERA_MODELS", "perspective_metrics", "resolve_intrinsics", "stage_perspective"]

#: the camera models of ``reconstruct --camera``.
CAMERA_MODELS = ("affine", "perspective", "auto")


def resolve_intrinsics(frames: np.ndarray, *, intrinsics: str | os.PathLike[str] | None = None,
                       focal: float | None = None, image_size: tuple[int, int] | None = None,
                       tracks_image_size: tuple[int, int] | None = None) -> tuple[np.ndarray, str]:
    """K of every frame from a ``K.csv`` or from ``focal`` (principal point at the image centre).

    The image size for ``focal`` is ``image_size`` or else the tracks file's own; one of
    them must exist.  Returns (F, 3, 3) and a description for the summary.
    """
    if (intrinsics is None) == (focal is None):
        raise InvalidInputError("a perspective camera needs its intrinsics: give --intrinsics K.csv or --focal F "
                                "(exactly one of them)")
    if intrinsics is not None:
        return read_intrinsics(intrinsics, frames), str(intrinsics)
    size = image_size if image_size is not None else tracks_image_size
    if size is None:
        raise InvalidInputError("--focal needs the image size for the principal point: give --image-size W H "
                                "(the tracks file does not record it)")
    K = intrinsics_from_focal(float(focal), size, len(frames))  # type: ignore[arg-type]
    return K, f"focal {float(focal):g} px, principal point at the centre of the {size[0]}x{size[1]} image"


def perspective_metrics(rec: PerspectiveReconstruction, observations: np.ndarray, frames: np.ndarray,
                        intrinsics: str, settings: PerspectiveSettings,
                        camera_choice: str | None = None) -> PerspectiveMetrics:
    """The summary's record of a perspective reconstruction of the (F, P, 2) ``observations``."""
    status = rec.point_status
    ok, reg = rec.reconstructed, rec.registered
    return PerspectiveMetrics(
        method=rec.method,
        intrinsics=intrinsics,
        frames=int(len(reg)),
        registered_frames=int(reg.sum()),
        unregistered=tuple(int(f) for f in np.asarray(frames)[~reg]),
        points=int(len(status)),
        reconstructed=int(ok.sum()),
        too_few_views=int(np.sum(status == PointStatus.TOO_FEW_VIEWS)),
        degenerate=int(np.sum(status == PointStatus.DEGENERATE)),
        observations=int(np.isfinite(observations).all(axis=2).sum()),
        inliers=int(rec.inliers.sum()),
        pixel_std_px=float(rec.pixel_std),
        reprojection_rms_px=float(rec.reprojection_rms),
        degrees_of_freedom=int(rec.degrees_of_freedom),
        initial_pair=(int(np.asarray(frames)[rec.initial_pair[0]]), int(np.asarray(frames)[rec.initial_pair[1]])),
        outlier_threshold_px=float(settings.outlier_threshold_px),
        outlier_probability=float(settings.outlier_probability),
        median_point_std=float(np.median(rms_std(rec.point_covariances[ok]))) if ok.any() else None,
        median_centre_std=float(np.median(rms_std(rec.camera_covariances[reg, 3:, 3:]))) if reg.any() else None,
        covariance_gauge=COVARIANCE_GAUGE,
        camera_choice=camera_choice,
    )


def stage_perspective(out: OutputDirectory, rec: PerspectiveReconstruction, frames: np.ndarray,
                      track_ids: np.ndarray, intrinsics: np.ndarray, *, comment: str, plot: bool = True) -> list[str]:
    """Stage structure.csv (with covariances), cameras.csv, structure.ply (and reconstruction.png).

    ``cameras.csv`` is in the intrinsics + pose layout of :mod:`kalmansfm.io.cameras` (so that
    ``kalmansfm fuse --cameras`` reads it): the registered frames' K (from the (F, 3, 3)
    (or one (3, 3)) ``intrinsics`` the reconstruction used), R and t, then ``rotation_std_deg`` and ``centre_std``.
    """
    names = stage_points(out, track_ids, rec.points, rec.point_covariances, rec.views, rec.point_status,
                         rec.point_reprojection_rms, comment=f"{comment}; covariances in the {COVARIANCE_GAUGE}")
    reg = rec.registered
    K = np.broadcast_to(intrinsics, (len(reg), 3, 3))
    out.write_text("cameras.csv", pose_cameras_csv(
        np.asarray(frames)[reg], K[reg], rec.rotations[reg], rec.translations[reg],
        rotation_std_deg=np.degrees(rms_std(rec.camera_covariances[reg, :3, :3])),
        centre_std=rms_std(rec.camera_covariances[reg, 3:, 3:])))
    names.append("cameras.csv")
    ok = rec.reconstructed
    if plot and ok.any() and reg.any():
        out.write_bytes("reconstruction.png", camera_path_figure(
            rec.centres[reg], np.asarray(frames)[reg].tolist(), rec.points[ok], rms_std(rec.point_covariances[ok])))
        names.append("reconstruction.png")
    return names
