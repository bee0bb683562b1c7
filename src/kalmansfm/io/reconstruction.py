"""The one reconstruction record in files: its own ``reconstruction.npz``, and COLMAP sparse models both ways.

* :func:`write_reconstruction` / :func:`read_reconstruction`: every array of a
  :class:`~kalmansfm.structure.Reconstruction` (cameras, points, covariances, the observations with
  their used/rejected flags and residuals, the noise estimate, warnings) in one compressed NPZ, which
  every run that reconstructs writes, so that a run folder can be exported or compared without its
  inputs.  A fusion's per-view history is not kept (``history.csv`` has it).
* :func:`colmap_of` / :func:`reconstruction_of_colmap`: a pinhole reconstruction as a COLMAP model
  (:mod:`kalmansfm.io.colmap`) and back.  COLMAP's cameras have no skew: a K with skew is written
  as the same K without it, and each 2-D point is mapped to that camera (x₀ = K₀ K⁻¹ x, exact for
  the 3-D points); the skew of every image goes into the side-car ``cameras_skew.txt`` so that
  kalmansfm reads back the original K and pixels.  Other tools see a consistent PINHOLE model whose
  2-D points differ from the image by at most the skew's shear.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from ..structure.reconstruction import (
    AffineDetails,
    FusionDetails,
    NoiseEstimate,
    Observations,
    PerspectiveDetails,
    Reconstruction,
)
from ._csv import where
from .atomic import atomic_write
from .colmap import SKEW_FILE, ColmapModel, build_colmap_model
from .npz import load_npz, save_npz

__all__ = [
    "RECONSTRUCTION_FILE",
    "ColmapExport",
    "colmap_of",
    "images_of",
    "read_reconstruction",
    "reconstruction_of_colmap",
    "write_reconstruction",
]

#: The file a run keeps its reconstruction in.
RECONSTRUCTION_FILE = "reconstruction.npz"
#: Version of the NPZ layout; a reader refuses others.
_FORMAT = 1
_DETAILS = {"affine": AffineDetails, "fusion": FusionDetails, "perspective": PerspectiveDetails}
_ARRAYS = ("projections", "rotations", "frame_status", "points", "point_covariances", "point_status", "views",
           "point_reprojection_rms", "frame_ids", "track_ids")
_OPTIONAL = ("intrinsics", "translations", "pose_covariances")


def _details_json(details: object) -> dict:
    out = {}
    for f in fields(details):  # type: ignore[arg-type]
        value = getattr(details, f.name)
        if f.name == "history":
            continue
        out[f.name] = value.tolist() if isinstance(value, np.ndarray) else value
    return out


def write_reconstruction(rec: Reconstruction, path: str | os.PathLike[str], *, image_names: list[str] | None = None,
                         image_size: tuple[int, int] | None = None) -> Path:
    """Write ``rec`` (and, when known, each frame's image file name and the image size) to one NPZ, atomically.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.structure import factorize
    >>> rng = np.random.default_rng(0)
    >>> rows = [np.linalg.qr(rng.normal(size=(3, 3)))[0][:2] for _ in range(4)]
    >>> rec = factorize(np.stack([rng.normal(size=(6, 3)) @ m.T for m in rows]))
    >>> back = read_reconstruction(write_reconstruction(rec, pathlib.Path(tempfile.mkdtemp()) / "r.npz"))
    >>> bool(np.array_equal(back.points, rec.points)), back.details.iterations == rec.details.iterations
    (True, True)
    """
    obs = rec.observations
    arrays = {name: np.asarray(getattr(rec, name)) for name in _ARRAYS}
    arrays.update({name: np.asarray(getattr(rec, name)) for name in _OPTIONAL if getattr(rec, name) is not None})
    arrays.update(obs_shape=np.asarray(obs.shape), obs_frame=obs.frame.astype(np.int32),
                  obs_point=obs.point.astype(np.int32), obs_xy=obs.xy, obs_used=obs.used, obs_rejected=obs.rejected,
                  obs_residual=obs.residual.astype(np.float32))
    meta = {"format": _FORMAT, "kind": rec.kind, "method": rec.method, "camera_model": rec.camera_model,
            "covariance_gauge": rec.covariance_gauge, "reprojection_rms": rec.reprojection_rms,
            "warnings": list(rec.warnings), "noise": {k: v for k, v in asdict(rec.noise).items() if k != "observation_std"},
            "details": _details_json(rec.details),
            "image_names": image_names, "image_size": None if image_size is None else [int(v) for v in image_size]}
    if rec.noise.observation_std is not None:  # each observation's own σ, stored per observation
        arrays["obs_std"] = np.asarray(rec.noise.observation_std)
    arrays["meta"] = np.frombuffer(json.dumps(meta, allow_nan=True).encode("utf-8"), dtype=np.uint8)
    buffer = io.BytesIO()
    save_npz(buffer, arrays)
    path = Path(path)
    data = buffer.getvalue()
    atomic_write(path, lambda tmp: tmp.write_bytes(data))
    return path


def read_reconstruction(path: str | os.PathLike[str]) -> Reconstruction:
    """The :class:`~kalmansfm.structure.Reconstruction` of a file :func:`write_reconstruction` wrote.

    The image names, when the file holds them, are in ``image_names_of(path)``.
    """
    data = load_npz(path)
    meta = _meta(data, path)
    try:
        kind = meta["kind"]
        details_type = _DETAILS[kind]
        details = details_type(**{k: (np.asarray(v) if k in ("singular_values", "metric_matrix") else
                                      tuple(v) if k == "initial_pair" else v) for k, v in meta["details"].items()})
        noise = meta["noise"]
        shape = tuple(int(v) for v in data["obs_shape"])
        per_observation = np.asarray(data["obs_std"], dtype=np.float64) if "obs_std" in data else None
        if per_observation is not None and per_observation.shape != np.shape(data["obs_frame"]):
            raise ValueError(f"obs_std holds {per_observation.size} values for {np.size(data['obs_frame'])} "
                             "observations")
        noise = NoiseEstimate(**{**noise, "parameters": tuple(tuple(p) for p in noise.get("parameters", ()))},
                              observation_std=per_observation)
        observations = Observations.from_sparse(shape, data["obs_frame"], data["obs_point"], data["obs_xy"],
                                                used=data["obs_used"], residual=data["obs_residual"],
                                                rejected=data["obs_rejected"])
        return Reconstruction(
            kind=kind, method=meta["method"], camera_model=meta["camera_model"],
            **{name: data[name] for name in _ARRAYS}, **{name: data.get(name) for name in _OPTIONAL},
            covariance_gauge=meta["covariance_gauge"], observations=observations, noise=noise,
            reprojection_rms=float(meta["reprojection_rms"]), details=details, warnings=tuple(meta["warnings"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise InvalidInputError(f"{where(Path(path))}: not a reconstruction kalmansfm wrote ({exc})") from None


def images_of(path: str | os.PathLike[str]) -> tuple[list[str] | None, tuple[int, int] | None]:
    """The image file names and the image size (width, height) a reconstruction file records, or None."""
    meta = _meta(load_npz(path), path)
    names, size = meta.get("image_names"), meta.get("image_size")
    return (None if names is None else [str(n) for n in names]), (None if size is None else (int(size[0]), int(size[1])))


def _meta(data: dict[str, np.ndarray], path: str | os.PathLike[str]) -> dict:
    try:
        meta = json.loads(data["meta"].tobytes().decode("utf-8"))
    except (KeyError, UnicodeDecodeError, ValueError):
        raise InvalidInputError(f"{where(Path(path))}: not a reconstruction kalmansfm wrote (no meta)") from None
    if meta.get("format") != _FORMAT:
        raise InvalidInputError(f"{where(Path(path))}: reconstruction format {meta.get('format')!r} is not {_FORMAT} "
                                "(written by another kalmansfm version; rerun the command)")
    return meta


@dataclass(frozen=True)
class ColmapExport:
    """A COLMAP model made from a reconstruction, and what had to change on the way.

    Attributes
    ----------
    model : the COLMAP model.
    skew : (F,) the skew of each frame's K that the model's cameras leave out (0 where none).
    notes : what the user should know (skew mapped out, frames or points left out).
    """

    model: ColmapModel
    skew: np.ndarray
    notes: tuple[str, ...]


def colmap_of(rec: Reconstruction, image_names: list[str], image_sizes: np.ndarray,
              colours: np.ndarray | None = None) -> ColmapExport:
    """A COLMAP model of a pinhole reconstruction: its registered frames, its ``ok`` points and their tracks.

    Parameters
    ----------
    rec : a reconstruction with pinhole cameras (an affine one is refused).
    image_names : one file name per frame (unique).
    image_sizes : (F, 2) or (2,) width, height.
    colours : (P, 3) uint8 or None.

    Only the observations the estimate used form the tracks; each point's ERROR is its reprojection
    RMS (pixels); its covariance goes to the side-car with the reconstruction's gauge.
    """
    if rec.camera_model != "pinhole" or rec.intrinsics is None or rec.translations is None:
        raise InvalidInputError("an affine reconstruction has no camera centres and no focal length: COLMAP's "
                                "models are pinhole cameras; export a perspective or fusion run")
    K = np.array(rec.intrinsics, dtype=np.float64)
    reg = rec.registered
    # a skew below 1e-9 of the focal length is the rounding of a decomposition, not a skew
    skew = np.where(reg & (np.abs(K[:, 0, 1]) > 1e-9 * np.abs(K[:, 0, 0])), K[:, 0, 1], 0.0)
    obs = rec.observations
    pick = obs.used
    frame, point, xy = obs.frame[pick], obs.point[pick], obs.xy[pick]
    notes = []
    K[:, 0, 1] = np.where(skew == 0.0, 0.0, K[:, 0, 1])
    if np.any(skew != 0.0):
        # COLMAP has no skew: the same camera without it sees x0 = K0 K⁻¹ x (exact for the 3-D points)
        K0 = K.copy()
        K0[:, 0, 1] = 0.0
        to_zero = K0 @ np.linalg.inv(np.where(reg[:, None, None], K, np.eye(3)))
        h = np.einsum("nij,nj->ni", to_zero[frame], np.column_stack([xy, np.ones(len(xy))]))
        xy = h[:, :2] / h[:, 2:]
        K = K0
        notes.append(f"COLMAP has no skew: the skew of {int(np.count_nonzero(skew))} image(s) (largest "
                     f"{np.abs(skew).max():.3g} px) is mapped out of their 2-D points and kept in {SKEW_FILE}")
    rotations = np.where(reg[:, None, None], rec.rotations, np.nan)
    translations = np.where(reg[:, None], rec.translations, np.nan)
    model = build_colmap_model(K, rotations, translations, image_sizes, image_names, frame, point, xy, rec.points,
                               colours=colours, errors=rec.point_reprojection_rms, keep=rec.reconstructed,
                               point_ids=rec.track_ids + 1 if rec.track_ids.min(initial=0) >= 0 else None,
                               covariances=rec.point_covariances, covariance_gauge=rec.covariance_gauge)
    return ColmapExport(model, skew, tuple(notes))


def reconstruction_of_colmap(model: ColmapModel, skew: dict[str, float] | None = None) -> Reconstruction:
    """A COLMAP model as a :class:`~kalmansfm.structure.Reconstruction` (``kind="perspective"``, ``method="colmap"``).

    Frames are the model's images in the order of their ids (frame = image id − 1); points get track
    id = point id − 1 (the ids :func:`colmap_of` writes are track id + 1);
    the observations are the images' 2-D points that belong to a point (in kalmansfm pixels).  With
    ``skew`` (image name → skew, from :data:`SKEW_FILE`) the original K and pixels come back.
    """
    from ..structure.reconstruction import FREE_NETWORK_GAUGE, FrameStatus

    images = model.images
    F, P = len(images.ids), len(model.points.ids)
    K = np.array(model.intrinsics(), dtype=np.float64)
    R = np.array(images.rotations(), dtype=np.float64)
    t = np.array(images.translations, dtype=np.float64)
    image_row, point_row, xy = model.observations()
    if skew:
        s = np.array([skew.get(name, 0.0) for name in images.names])
        K_skew = K.copy()
        K_skew[:, 0, 1] = s
        back = K_skew @ np.linalg.inv(K)
        h = np.einsum("nij,nj->ni", back[image_row], np.column_stack([xy, np.ones(len(xy))]))
        xy, K = h[:, :2] / h[:, 2:], K_skew
    projections = K @ np.concatenate([R, t[:, :, None]], axis=2)
    X = np.array(model.points.xyz, dtype=np.float64)
    cov = model.covariances if model.covariances is not None else np.full((P, 3, 3), np.nan)
    views = np.bincount(point_row, minlength=P).astype(np.int64)
    errors = np.array(model.points.errors, dtype=np.float64)
    return Reconstruction(
        kind="perspective", method="colmap", camera_model="pinhole", projections=projections, rotations=R,
        frame_status=np.full(F, FrameStatus.REGISTERED, dtype=np.int8), points=X, point_covariances=np.asarray(cov),
        point_status=np.zeros(P, dtype=np.int8), views=views,
        point_reprojection_rms=np.where(errors >= 0, errors, np.nan),
        covariance_gauge=model.covariance_gauge or FREE_NETWORK_GAUGE,
        observations=Observations.from_sparse((F, P), image_row, point_row, xy),
        noise=NoiseEstimate(std=float("nan"), estimated=False, degrees_of_freedom=0),
        reprojection_rms=float(np.sqrt(np.mean(np.square(errors[errors >= 0])))) if (errors >= 0).any() else float("nan"),
        details=PerspectiveDetails(initial_pair=(0, min(1, F - 1)), outlier_threshold_px=float("nan"),
                                   outlier_probability=float("nan")),
        intrinsics=K, translations=t, frame_ids=np.asarray(images.ids, dtype=np.int64) - 1,
        track_ids=np.asarray(model.points.ids, dtype=np.int64) - 1,
    )
