"""``kalmansfm export RUN --colmap DIR``: a finished run's reconstruction as a COLMAP sparse model.

The folder is laid out as 3D Gaussian Splatting, nerfstudio and OpenMVS's importers expect it:
``DIR/sparse/0/{cameras,images,points3D}.{txt|bin}`` (with the side-cars ``points3D_covariance.txt``
and, when a K has skew, ``cameras_skew.txt``), ``DIR/images/`` when the source images are copied or
linked, and ``DIR/summary.json`` (the export's record, so that a rerun can replace it whole).
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import InvalidInputError
from ..io.atomic import check_output_directory, output_directory
from ..io.colmap import SKEW_FILE, skew_text, write_colmap_model
from ..io.reconstruction import RECONSTRUCTION_FILE, colmap_of, images_of, read_reconstruction
from ..io.run_folder import load_run
from ..io.summary import SUMMARY_FILE, RunSummary, read_summary, run_source
from ..structure import Reconstruction
from .requests import request_options
from .stage import Stopwatch, stage_summary

__all__ = ["EXPORT_IMAGES", "ExportRequest", "ExportRun", "run_export"]

log = logging.getLogger("kalmansfm")

#: what ``images`` may ask for: no images, copies of the source images, or symbolic links to them.
EXPORT_IMAGES = ("none", "copy", "link")
#: where the model goes inside the export folder (the layout 3D Gaussian Splatting reads).
MODEL_FOLDER = "sparse/0"


@dataclass(frozen=True)
class ExportRequest:
    """What to export, where, and how.

    Attributes
    ----------
    run : a run folder with a reconstruction (``reconstruct --camera perspective``, ``fuse``, or a
        ``demo`` with a perspective camera).
    out : the export folder (new, empty, or an earlier export, replaced whole).
    binary : write COLMAP's binary files instead of text.
    images : ``"none"``, ``"copy"`` or ``"link"`` the source images into ``out/images`` (needs a run
        that knows its images: a ``demo`` of a folder of images).
    """

    run: Path
    out: Path
    binary: bool = False
    images: str = "none"

    def __post_init__(self) -> None:
        object.__setattr__(self, "run", Path(self.run))
        object.__setattr__(self, "out", Path(self.out))
        if self.images not in EXPORT_IMAGES:
            raise InvalidInputError(f"images must be one of {', '.join(EXPORT_IMAGES)}; got {self.images!r}",
                                    fields=("images",))


@dataclass(frozen=True)
class ExportRun:
    """What an export wrote: the model's images and points, and what the user should know."""

    out_dir: Path
    images: int
    points: int
    summary: RunSummary
    notes: tuple[str, ...] = field(default=())


def run_export(request: ExportRequest) -> ExportRun:
    """Write the reconstruction of ``request.run`` as a COLMAP model into ``request.out``, all or nothing.

    Images are named after the source images when the run knows them (a ``demo`` of a folder of
    images), otherwise ``frame_000012.png`` by frame number (they sort in frame order); each point's
    colour is the mean grey or colour of the frames that saw it when the run kept frames or knows its
    images, else mid grey; ERROR is its reprojection RMS (pixels) and the track holds the observations
    the estimate used.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.io.cameras import cameras_csv
    >>> from kalmansfm.io.tracks import observations_csv
    >>> from kalmansfm.pipeline import FuseRequest, run_fuse
    >>> from kalmansfm.scenes.known_cameras import known_camera_scene
    >>> s = known_camera_scene(points=40, views=5, seed=1)
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "cameras.csv").write_text(cameras_csv(s.cameras))
    >>> _ = (d / "tracks.csv").write_text(observations_csv(s.observations, s.cameras.frames, np.arange(40)))
    >>> _ = run_fuse(FuseRequest(d / "tracks.csv", d / "cameras.csv", d / "fused", plot=False))
    >>> done = run_export(ExportRequest(d / "fused", d / "colmap"))
    >>> done.images, done.points, sorted(p.name for p in (d / "colmap" / "sparse" / "0").iterdir())[:3]
    (5, 40, ['cameras.txt', 'images.txt', 'points3D.txt'])
    """
    clock = Stopwatch()
    summary = read_summary(request.run / SUMMARY_FILE)
    if RECONSTRUCTION_FILE not in summary.files or not (request.run / RECONSTRUCTION_FILE).is_file():
        raise InvalidInputError(f"{request.run}: the run holds no {RECONSTRUCTION_FILE}; export needs a run that "
                                "reconstructed (reconstruct, fuse, demo) with this kalmansfm version")
    check_output_directory(request.out, inputs=[request.run])
    rec = read_reconstruction(request.run / RECONSTRUCTION_FILE)
    if rec.camera_model != "pinhole":
        raise InvalidInputError(f"{request.run}: an affine reconstruction (factorization) has no camera centres "
                                "and no focal length, and COLMAP's models are pinhole cameras; export a perspective "
                                "run (reconstruct --camera perspective) or a fusion run (fuse)")
    names, size = images_of(request.run / RECONSTRUCTION_FILE)
    sources = _source_images(summary, names)
    if request.images != "none" and sources is None:
        raise InvalidInputError(f"{request.run}: the run does not know its source images (only a demo of a folder "
                                "of images does); export without images")
    notes = []
    if names is None:
        names = [f"frame_{int(f):06d}.png" for f in rec.frame_ids]
    sizes = _image_sizes(rec, size, notes)
    colours = _colours(rec, run=request.run, sources=sources)
    export = colmap_of(rec, names, sizes, colours)
    notes += export.notes
    made_from = run_source(request.run / RECONSTRUCTION_FILE, [request.run / RECONSTRUCTION_FILE],
                           request_options(request))
    with output_directory(request.out, inputs=[request.run]) as out:
        with clock.step("writing"):
            model_dir = out.file(MODEL_FOLDER + "/x").parent
            written = write_colmap_model(export.model, model_dir, binary=request.binary)
            files = [f"{MODEL_FOLDER}/{Path(f).name}" for f in written.files]
            if np.any(export.skew != 0):
                out.write_text(f"{MODEL_FOLDER}/{SKEW_FILE}", skew_text(names, export.skew))
                files.append(f"{MODEL_FOLDER}/{SKEW_FILE}")
            if request.images != "none":
                files += _stage_images(out, sources, export.model.images.names, link=request.images == "link")
        record = RunSummary(command="export", input=str(request.run), source=made_from, warnings=tuple(notes))
        record = stage_summary(out, record, clock, files)
    return ExportRun(request.out, int(written.images), int(written.points), record, tuple(notes))


def _source_images(summary: RunSummary, names: list[str] | None) -> list[Path] | None:
    """The source image of every frame, when the run knows them and they are still there."""
    if names is None or summary.source is None:
        return None
    folder = Path(summary.source.input)
    if not folder.is_dir():
        return None
    paths = [folder / name for name in names]
    return paths if all(p.is_file() for p in paths) else None


def _image_sizes(rec: Reconstruction, size: tuple[int, int] | None, notes: list[str]) -> np.ndarray:
    if size is not None:
        return np.array(size)
    # unknown: the image that has its principal point at the centre, as most calibrations do
    K = rec.intrinsics[rec.registered]  # type: ignore[index]
    guess = np.ceil(2 * np.array([K[:, 0, 2].max(), K[:, 1, 2].max()]) + 1).astype(int)
    notes.append(f"the run does not record its image size: {guess[0]}x{guess[1]} assumed (principal point at "
                 "the centre)")
    return guess


def _colours(rec: Reconstruction, *, run: Path, sources: list[Path] | None) -> np.ndarray | None:
    """Each point's mean colour over the observations used, from the source images or the run's frames."""
    obs = rec.observations
    pick = obs.used & rec.reconstructed[obs.point]
    if not pick.any():
        return None
    if sources is not None:
        frame_files = sources
    else:
        try:
            frame_files = list(load_run(run).frame_paths)
        except InvalidInputError:
            return None
        if len(frame_files) != rec.n_frames:
            return None
    total = np.zeros((rec.n_points, 3))
    count = np.zeros(rec.n_points)
    for f in np.unique(obs.frame[pick]):
        image = cv2.imread(os.fspath(frame_files[f]), cv2.IMREAD_COLOR)
        if image is None:
            return None
        here = pick & (obs.frame == f)
        x = np.clip(np.rint(obs.xy[here, 0]).astype(int), 0, image.shape[1] - 1)
        y = np.clip(np.rint(obs.xy[here, 1]).astype(int), 0, image.shape[0] - 1)
        np.add.at(total, obs.point[here], image[y, x, ::-1].astype(float))  # BGR → RGB
        np.add.at(count, obs.point[here], 1.0)
    return np.where(count[:, None] > 0, total / np.maximum(count, 1)[:, None], 128).round().astype(np.uint8)


def _stage_images(out, sources: list[Path] | None, names: tuple[str, ...] | list[str], *, link: bool) -> list[str]:
    by_name = {p.name: p for p in sources or []}
    files = []
    for name in names:
        target = out.file(f"images/{name}")
        if link:
            os.symlink(by_name[name].resolve(), target)
        else:
            shutil.copyfile(by_name[name], target)
        files.append(f"images/{name}")
    return files
