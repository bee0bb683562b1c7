"""``kalmansfm reconstruct IMAGES --camera perspective``: cameras and points straight from calibrated images.

The feature front end (:func:`kalmansfm.mapping.reconstruct_images`: features, matching over chosen
pairs, verification, tracks, guided matching) feeds the calibrated back end; the run folder holds
what every reconstruction writes (:func:`~kalmansfm.pipeline.stage.stage_reconstruction`), the
feature tracks it was given (``tracks.csv``, so that they can be fused or reconstructed again), the
match graph (``pairs.csv``) and each view's outcome (``views.csv``).
"""

from __future__ import annotations

import csv
import io
import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._version import __version__
from ..errors import InvalidInputError
from ..io._csv import csv_text
from ..io.atomic import check_output_directory, output_directory
from ..io.frames import IMAGE_EXTENSIONS, VIDEO_SUFFIXES, read_frames
from ..io.summary import RunSummary, run_source
from ..io.tracks import observations_csv
from ..mapping import ImageReconstruction, MappingSettings, ViewStatus, reconstruct_images
from .cluster import check_cluster, executor_for
from .evaluate import reconstruction_metrics
from .perspective import resolve_intrinsics
from .requests import Perspective, request_options
from .stage import Stopwatch, stage_reconstruction, stage_summary

__all__ = ["ImagesRequest", "ImagesRun", "is_image_input", "run_reconstruct_images"]

#: the file names of the front end's own tables in a run folder.
PAIRS_FILE, VIEWS_FILE = "pairs.csv", "views.csv"
_TRACK_SUFFIXES = {".csv", ".npz"}


def is_image_input(path: Path) -> bool:
    """True when ``path`` names images (a folder without tracks.npz, a glob, a video) rather than a tracks file.

    Examples
    --------
    >>> is_image_input(Path("clip.mp4")), is_image_input(Path("tracks.csv")), is_image_input(Path("shots/*.png"))
    (True, False, True)
    """
    text = str(path)
    if any(c in text for c in "*?["):
        return True
    if path.is_dir():  # a folder of images, not a run folder with its tracks
        return not (path / "tracks.npz").is_file() and any(p.suffix.lower() in IMAGE_EXTENSIONS for p in path.iterdir())
    return path.suffix.lower() in VIDEO_SUFFIXES or (path.suffix.lower() not in _TRACK_SUFFIXES and path.suffix != "")


@dataclass(frozen=True)
class ImagesRequest:
    """Cameras and points from a folder of images, a glob or a video.

    Attributes
    ----------
    images : the input; frame k is the k-th image in natural order (as ``track`` reads a folder).
    out : the run folder.
    camera : the :class:`~kalmansfm.pipeline.requests.Perspective` camera (intrinsics or focal).
    settings : the front end's and the back end's settings.
    plot : draw reconstruction.png.
    scheduler, workers : match the image pairs on Dask — an existing scheduler's address, or a local
        cluster of this many processes (:func:`~kalmansfm.pipeline.cluster.dask_client`); neither: here.
    """

    images: Path
    out: Path
    camera: Perspective
    settings: MappingSettings = field(default_factory=MappingSettings)
    plot: bool = True
    scheduler: str | None = None
    workers: int | None = None

    def __post_init__(self) -> None:
        check_cluster(self.scheduler, self.workers, scheduler_name="scheduler", workers_name="workers")
        object.__setattr__(self, "images", Path(self.images))
        object.__setattr__(self, "out", Path(self.out))
        if not isinstance(self.camera, Perspective):
            raise InvalidInputError("images are reconstructed with a perspective camera: give its intrinsics or focal",
                                    fields=("intrinsics", "focal"))


@dataclass(frozen=True)
class ImagesRun:
    """What ``reconstruct IMAGES`` read, computed and wrote."""

    out_dir: Path
    result: ImageReconstruction
    summary: RunSummary


def run_reconstruct_images(request: ImagesRequest) -> ImagesRun:
    """Reconstruct the images of ``request.images`` with their intrinsics and write the run folder, all or nothing.

    Views that get no camera are listed with their reason in the run's warnings (and ``views.csv``),
    never dropped silently.
    """
    inputs = [request.images, request.camera.intrinsics]
    check_output_directory(request.out, inputs=inputs)
    clock = Stopwatch()
    with clock.step("frames"):
        sequence = read_frames(request.images)
        reader = iter(sequence)
        first = next(reader, None)
        if sequence.files:  # the rest is decoded while the first images' features are detected
            count, frames = len(sequence.files), itertools.chain([first], reader)
        else:  # a video's length is known once it is read
            listed = [] if first is None else [first, *reader]
            count, frames = len(listed), iter(listed)
    if count < 2:
        raise InvalidInputError(f"{request.images}: a reconstruction needs at least 2 images; got {count}")
    height, width = first.shape[:2]
    frame_numbers = np.arange(count)
    K, source_k = resolve_intrinsics(frame_numbers, request.camera, (width, height))
    names = [Path(p).name for p in sequence.paths] if len(sequence.paths) == count else None
    made_from = run_source(sequence.description, [*sequence.paths, *[p for p in inputs[1:] if p is not None]],
                           request_options(request))
    with clock.step("reconstruction from the images"):
        with executor_for(request.scheduler, request.workers) as executor:
            result = reconstruct_images(frames, K, request.settings, executor=executor)
    rec = result.reconstruction.with_ids(frame_numbers, np.arange(result.reconstruction.n_points))
    metrics = reconstruction_metrics(rec, intrinsics=source_k)
    lines = result.unregistered_lines()
    warnings = [*result.warnings, *(f"no camera for {line}" for line in lines[:12])]
    if len(lines) > 12:
        warnings.append(f"… and {len(lines) - 12} more views without a camera ({VIEWS_FILE})")
    summary = RunSummary(command="reconstruct", input=sequence.description, source=made_from,
                         reconstruction=metrics, warnings=tuple(dict.fromkeys(warnings)))
    with output_directory(request.out, inputs=inputs) as out:
        with clock.step("writing"):
            files = stage_reconstruction(out, rec, comment=f"kalmansfm {__version__} from {request.images.name}",
                                         plot=request.plot, image_names=names, image_size=(width, height))
            out.write_text("tracks.csv", observations_csv(result.tracks.observations, frame_numbers,
                                                          np.arange(result.tracks.observations.shape[1])))
            out.write_text(PAIRS_FILE, pairs_csv(result))
            out.write_text(VIEWS_FILE, views_csv(result, names))
            files += ["tracks.csv", PAIRS_FILE, VIEWS_FILE]
        summary = stage_summary(out, summary, clock, files)
    return ImagesRun(request.out, result, summary)


def pairs_csv(result: ImageReconstruction) -> str:
    """``pairs.csv``: every image pair matched — ``i,j,putative,inliers`` (0 inliers: failed verification)."""
    graph = result.match_graph
    rows = ([int(i), int(j), int(p), int(v)] for (i, j), p, v in
            zip(graph.candidates, graph.putative_counts, graph.inlier_counts))
    return csv_text(("i", "j", "putative", "inliers"), rows)


def views_csv(result: ImageReconstruction, names: list[str] | None) -> str:
    """``views.csv``: each view's image, status (``registered``, ``no_matches``, …) and reason."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")  # a reason may hold commas: quoted
    writer.writerow(("view", "image", "status", "reason"))
    writer.writerows([v, "" if names is None else names[v], ViewStatus(int(s)).label, result.view_reasons[v]]
                     for v, s in enumerate(result.view_status))
    return buffer.getvalue()
