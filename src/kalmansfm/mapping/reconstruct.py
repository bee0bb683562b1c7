"""From calibrated images to cameras: features, matches, tracks, the calibrated back end, guided matching.

1. **Features** (:mod:`kalmansfm.features`): SIFT on every image, the pairs to match (all for a
   small set; else a sequential window and retrieval neighbours, so image order is free), mutual
   ratio-test matches verified by an essential matrix (USAC), tracks by union–find over every verified
   match, split where they hold two features of one image.
2. **First reconstruction** of a skeleton: for every view its longest tracks
   (``skeleton_tracks_per_view``); long tracks fix the cameras, and the back end's time grows with the
   number of tracks.
3. **Guided matching** (:mod:`.guided`): every known point is projected into every view that does
   not see it yet, with the covariance of the point and the camera plus σ² as a gate; a feature inside
   the gate whose descriptor matches the point's joins the track — or, when it already belongs to
   another track whose observations agree with the point, the two tracks merge.  A view that the first
   reconstruction could not register gets a pose from PnP on its 2-D–3-D matches (its features against
   those of the most similar registered views) and is searched the same way (:mod:`.active_search`).
4. **Track check**: each view's longest tracks after guided matching (``final_tracks_per_view``) are
   triangulated with the first reconstruction's cameras (the fusion engine, the back end's outlier test)
   and lose the observations that test rejects (:func:`.active_search.drop_inconsistent`).
5. **Final reconstruction** of those tracks: the back end re-triangulates, rejects outliers and
   bundle-adjusts.

Views that end without a camera are listed with a status and the reason.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from .._validation import as_float_array
from ..errors import InvalidInputError, NotEnoughDataError
from ..features import (
    FeatureTracks,
    ImageFeatures,
    MatchGraph,
    build_tracks,
    detect_all,
    match_images,
    select_pairs,
)
from ..structure.perspective import reconstruct_perspective
from ..structure.reconstruction import Reconstruction
from ..structure.perspective.settings import validate_intrinsics
from ..tracking.grey import colour_to_grey
from .active_search import GuidedMatchingSummary, active_search, drop_inconsistent
from .backend import CameraSolution, read_solution
from .settings import MappingSettings, ViewStatus

__all__ = ["ImageReconstruction", "reconstruct_images"]

@dataclass(frozen=True)
class ImageReconstruction:
    """Cameras and points from a set of calibrated images, with everything that led to them.

    Attributes
    ----------
    features : the features of every image.
    match_graph : every pair matched, its putative and verified match counts, and the verified matches.
    tracks : the tracks the final reconstruction was given (its points, in the same order): (F, P, 2)
        positions with NaN and the feature index of every observation.
    reconstruction : the calibrated back end's result (cameras, points, covariances, inliers, σ).
    view_status : (F,) int8 — :class:`~.settings.ViewStatus` of every image.
    view_reasons : (F,) why each unregistered view has no camera ('' for registered views).
    guided : what guided matching added.
    image_size : (width, height) of the images.
    settings : the settings of the run.
    warnings : things the user should know.
    timings : seconds per stage (detection, pair_selection, matching, tracks, first_reconstruction,
        guided_matching, final_reconstruction).
    """

    features: tuple[ImageFeatures, ...]
    match_graph: MatchGraph
    tracks: FeatureTracks
    reconstruction: Reconstruction
    view_status: np.ndarray
    view_reasons: tuple[str, ...]
    guided: GuidedMatchingSummary
    image_size: tuple[int, int]
    settings: MappingSettings
    warnings: tuple[str, ...] = ()
    timings: dict[str, float] = field(default_factory=dict, compare=False)

    @property
    def registered(self) -> np.ndarray:
        """(F,) bool — views with a camera."""
        return self.view_status == ViewStatus.REGISTERED

    def unregistered_lines(self) -> list[str]:
        """One line per view without a camera: ``view 5: no_matches (…reason…)``."""
        return [f"view {v}: {ViewStatus(int(self.view_status[v])).label} ({self.view_reasons[v]})"
                for v in np.flatnonzero(~self.registered)]


# -- input ------------------------------------------------------------------------------------------

class _GreyImages:
    """The images as grey, one by one as they are read (a lazy source such as a FrameSource is decoded while
    the features of the earlier ones are detected), each checked for its type, the size of the first
    (``shape``, known once one image is read) and repeats."""

    def __init__(self, images: object) -> None:
        if isinstance(images, np.ndarray):
            if images.ndim not in (3, 4):
                raise InvalidInputError(f"images must be a sequence of images or an (F, H, W[, C]) array; got shape "
                                        f"{images.shape}")
            images = list(images)
        try:
            self._items = iter(images)  # type: ignore[call-overload]
        except TypeError:
            raise InvalidInputError(f"images must be a sequence of arrays; got {type(images).__name__}") from None
        self.shape: tuple[int, ...] | None = None

    def __iter__(self) -> Iterator[np.ndarray]:
        seen: dict[bytes, int] = {}
        for k, item in enumerate(self._items):
            a = np.asarray(item)
            if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))):
                raise InvalidInputError(f"image {k} must be (H, W) grey, (H, W, 3) BGR or (H, W, 4) BGRA uint8; got "
                                        f"shape {a.shape}, dtype {a.dtype}")
            g = np.ascontiguousarray(colour_to_grey(a))
            if self.shape is None:
                self.shape = g.shape
            elif g.shape != self.shape:
                raise InvalidInputError(f"image {k} is {g.shape[1]} x {g.shape[0]} pixels but image 0 is "
                                        f"{self.shape[1]} x {self.shape[0]}; all images must have one size")
            digest = hashlib.blake2b(g.tobytes(), digest_size=16).digest()
            if digest in seen:
                raise InvalidInputError(f"image {k} repeats image {seen[digest]} (identical pixels); give each view "
                                        "once")
            seen[digest] = k
            yield g


def _enough_images(count: int) -> None:
    if count < 2:
        raise NotEnoughDataError(f"reconstruct_images needs >= 2 images; got {count}")


def _intrinsics(intrinsics: object, count: int) -> np.ndarray:
    K = as_float_array("intrinsics", intrinsics)
    if K.ndim == 3 and K.shape[0] != count:
        raise InvalidInputError(f"intrinsics hold {K.shape[0]} K matrices for {count} images; give one per image "
                                "or one (3, 3) K for all")
    return validate_intrinsics(K, count)


# -- steps ------------------------------------------------------------------------------------------

def _longest_tracks(tracks: FeatureTracks, per_view: int) -> np.ndarray:
    """Sorted indices of the union over views of each view's ``per_view`` longest tracks (0 = all)."""
    length = tracks.views
    if per_view == 0:
        return np.flatnonzero(length >= 2)
    frames, ids = np.nonzero(tracks.seen)
    order = np.lexsort((ids, -length[ids], frames))
    frames, ids = frames[order], ids[order]
    start = np.searchsorted(frames, np.arange(tracks.feature_index.shape[0]))
    rank = np.arange(len(frames)) - start[frames]
    return np.unique(ids[(rank < per_view) & (length[ids] >= 2)])


def _no_overlap_message(graph: MatchGraph, count: int, min_inliers: int) -> str:
    if len(graph.candidates) == 0:
        return f"no two of the {count} images were similar enough to be matched: the views do not overlap"
    best = int(np.argmax(graph.putative_counts))
    i, j = graph.candidates[best]
    return (f"no two of the {count} images share >= {min_inliers} verified matches (best: images {i} and {j}, "
            f"{int(graph.putative_counts[best])} putative matches, none consistent with one epipolar geometry): "
            "the views do not overlap")


def _view_status(features: Sequence[ImageFeatures], graph: MatchGraph, solution: CameraSolution,
                 tracks: FeatureTracks, settings: MappingSettings) -> tuple[np.ndarray, tuple[str, ...]]:
    F = len(features)
    fs, rs = settings.features, settings.reconstruction
    status = np.full(F, ViewStatus.REGISTERED, np.int8)
    reasons = [""] * F
    degree = graph.degree(F)
    shared = (tracks.seen & solution.reconstructed[None]).sum(axis=1)
    for v in np.flatnonzero(~solution.registered):
        if len(features[v]) < fs.min_inliers:
            status[v] = ViewStatus.NO_FEATURES
            reasons[v] = f"{len(features[v])} features detected, need >= {fs.min_inliers}"
        elif degree[v] == 0:
            status[v] = ViewStatus.NO_MATCHES
            mine = np.flatnonzero((graph.candidates == v).any(axis=1))
            if len(mine) == 0:
                reasons[v] = "not similar enough to any other image to be matched"
            else:
                best = mine[np.argmax(graph.putative_counts[mine])]
                other = int(graph.candidates[best][graph.candidates[best] != v][0])
                reasons[v] = (f"no verified pair; best: image {other}, {int(graph.putative_counts[best])} putative "
                              f"matches, need >= {fs.min_inliers} consistent")
        elif solution.pose_failed[v]:
            status[v] = ViewStatus.POSE_FAILED
            reasons[v] = f"no consistent pose from the {int(shared[v])} reconstructed points it sees"
        else:
            status[v] = ViewStatus.NOT_CONNECTED
            reasons[v] = (f"sees {int(shared[v])} reconstructed points, need >= {rs.min_registration_points}")
    return status, tuple(reasons)


# Matrix products here are many and small, and the threads of the pools below already use the cores:
# BLAS threads inside them only contend (as in the back end, structure.perspective.bundle).
@threadpool_limits.wrap(limits=1, user_api="blas")
def reconstruct_images(images: object, intrinsics: object, settings: MappingSettings | None = None,
                       executor: Any | None = None) -> ImageReconstruction:
    """Cameras and points from a set of calibrated images, in any order.

    Parameters
    ----------
    images : sequence of F images, or an (F, H, W) / (F, H, W, C) array — uint8 grey, BGR or BGRA, one size.
    intrinsics : (3, 3) K for every image, or (F, 3, 3).
    settings : MappingSettings, default ``MappingSettings()``.
    executor : object with a ``map(fn, items)`` method, optional
        Matches the image pairs in chunks there (e.g. on Dask, :func:`~kalmansfm.features.match_images`);
        by default on ``settings.features.thread_count`` threads here.  The result is the same.

    Returns
    -------
    ImageReconstruction

    Raises
    ------
    InvalidInputError
        Images of different sizes or types, a repeated image, intrinsics that do not match the images.
    NotEnoughDataError
        Fewer than 2 images; no two images overlap (no verified pair); no pair to start from.

    Examples
    --------
    >>> from kalmansfm.scenes.textured import textured_views
    >>> views = textured_views(frames=5, arc_deg=80.0, seed=0)    # 20° between views
    >>> result = reconstruct_images(views.images, views.intrinsics)
    >>> int(result.registered.sum()), result.reconstruction.reprojection_rms < 1.0
    (5, True)
    """
    settings = MappingSettings() if settings is None else settings
    if not isinstance(settings, MappingSettings):
        raise InvalidInputError(f"settings must be a MappingSettings; got {type(settings).__name__}")
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = timings.get(name, 0.0) + now - clock
        clock = now

    fs, rs = settings.features, settings.reconstruction
    try:
        known: int | None = len(images)  # type: ignore[arg-type]
    except TypeError:  # a generator, or a video of unknown length
        known = None
    if known is not None:  # checked before any image is read
        _enough_images(known)
        K = _intrinsics(intrinsics, known)
    lap("input")
    grey = _GreyImages(images)
    features = detect_all(grey, fs)  # the images are read as the first ones are detected
    lap("detection")
    F = len(features)
    if known is None:
        _enough_images(F)
        K = _intrinsics(intrinsics, F)
    image_size = (grey.shape[1], grey.shape[0])  # type: ignore[index]
    selection = select_pairs(features, fs)
    lap("pair_selection")
    graph = match_images(features, K, fs, selection, executor=executor)
    lap("matching")
    if not graph.verified.any():
        raise NotEnoughDataError(_no_overlap_message(graph, F, fs.min_inliers))
    tracks = build_tracks(features, graph)
    lap("tracks")
    warnings: list[str] = []
    summary = GuidedMatchingSummary()
    first = None
    if settings.guided_matching:
        index = _longest_tracks(tracks, settings.skeleton_tracks_per_view)
        try:
            # a rough skeleton is enough to predict where features are: its refinement rounds are left to the final
            first = reconstruct_perspective(tracks.subset(index).observations, K,
                                            settings=replace(rs, refinement_rounds=0))
        except NotEnoughDataError as exc:  # the skeleton was too thin: reconstruct the full selection directly
            warnings.append(f"guided matching skipped: the first reconstruction of each view's "
                            f"{settings.skeleton_tracks_per_view} longest tracks failed ({exc})")
        lap("first_reconstruction")
    if first is not None:
        solution = read_solution(first)
        # the skeleton's points, placed among all tracks
        points = np.full((tracks.feature_index.shape[1], 3), np.nan)
        covariances = np.full((len(points), 3, 3), np.nan)
        points[index] = solution.points
        covariances[index] = solution.point_covariances
        every = replace(solution, points=points, point_covariances=covariances,
                        inliers=np.zeros(tracks.feature_index.shape, bool))
        tracks, summary = active_search(features, tracks, every, K, image_size, graph, settings)
        lap("guided_matching")
        selected = tracks.subset(_longest_tracks(tracks, settings.final_tracks_per_view))
        tracks, dropped = drop_inconsistent(selected, every, K, rs)
        summary = replace(summary, dropped_observations=dropped)
        lap("track_check")
    final_tracks = tracks.subset(_longest_tracks(tracks, settings.final_tracks_per_view))
    # from the first reconstruction's poses: its initial pair and growth need not be found again
    rec = reconstruct_perspective(final_tracks.observations, K, settings=rs, start=first)
    lap("final_reconstruction")
    final = read_solution(rec)
    status, reasons = _view_status(features, graph, final, final_tracks, settings)
    missing = np.flatnonzero(status != ViewStatus.REGISTERED)
    if missing.size:
        warnings.append(f"{missing.size} of {F} views have no camera: " + "; ".join(
            f"view {v} {ViewStatus(int(status[v])).label}" for v in missing))
    return ImageReconstruction(features, graph, final_tracks, rec, status, reasons, summary, image_size, settings,
                               tuple(warnings) + final.warnings, timings)
