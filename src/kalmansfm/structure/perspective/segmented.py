"""Calibrated reconstruction of a long video-ordered sequence in overlapping windows of frames.

A long sequence of short tracks (minutes of video, tens of thousands of tracks each seen in a
few dozen frames) is too large for one incremental reconstruction: its (frames × tracks) arrays
and its global bundle adjustments grow with the whole sequence.  Here memory and time follow the
observations instead:

1. **Windows.**  The frames are taken in windows of :data:`WINDOW_FRAMES` consecutive frames, each
   beginning :data:`WINDOW_OVERLAP` frames before the previous one ends (:func:`window_stop`).  Each
   window, with the tracks seen at least twice in it, is a small dense problem, reconstructed by
   :func:`~.reconstruct.reconstruct_perspective` (initial pair, PnP growth, bundle adjustment; no
   refinement rounds, :data:`WINDOW_REFINEMENT_ROUNDS`) in its own gauge.  A window that registers
   fewer than half its frames or reconstructs few of its tracks is refused
   (:data:`MIN_WINDOW_FRAME_SHARE`, :data:`MIN_WINDOW_POINT_SHARE`: a wrong initial pair leaves a
   handful of points).
2. **Chain.**  Each window is brought into the previous one's frame by the similarity (scale,
   rotation, translation) that best maps its camera centres of the shared frames and its points of
   the shared tracks onto the previous window's (:func:`robust_similarity`: least squares, refitted
   without the matches far beyond the median residual; refused when the residual is not small
   against the matches' spread, :data:`CHAIN_MAX_RELATIVE_RMS`).  A window that cannot be
   reconstructed or chained is tried again with lower registration thresholds (a growth that
   stalled at a weak frame), then over a shorter span (another initial pair).  The first window of
   the chain fixes the gauge: its initial pair's first camera at the origin, unit baseline (as the
   dense path's).  A window that still fails breaks the chain; the longest chained part is kept,
   the frames outside it have no camera, and a warning says where it broke.  Errors of scale and
   orientation add up along the chain (no loop closure).
3. **Cameras.**  A frame that several windows registered takes its camera from the window whose
   middle frame is nearest to it (the best-constrained one, away from a window's edges).
4. **Points.**  Every track is fused from all its observations with these cameras taken as exact
   (:func:`~kalmansfm.structure.fusion.fuse`, per-point maximum likelihood with the outlier test,
   σ estimated), per observation, in blocks of tracks: the point covariances are conditional on
   the cameras (:data:`SEGMENTED_GAUGE`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ...errors import InvalidInputError, NotEnoughDataError
from ..fusion import FusionSettings, fuse
from ..geometry.alignment import align_similarity
from ..geometry.pinhole import CameraSet
from ..reconstruction import SEGMENTED_GAUGE, FrameStatus, Observations, PerspectiveDetails, Reconstruction
from .reconstruct import reconstruct_perspective
from .settings import PerspectiveSettings, validate_intrinsics

__all__ = [
    "DENSE_MAX_ENTRIES",
    "DENSE_MAX_FRAMES",
    "SEGMENTED_GAUGE",
    "WINDOW_FRAMES",
    "WINDOW_OVERLAP",
    "WINDOW_REFINEMENT_ROUNDS",
    "SimilarityFit",
    "fits_dense_reconstruction",
    "reconstruct_segmented",
    "robust_similarity",
    "window_stop",
]

#: Frames per window: a small dense problem (a few hundred tracks of a video), long enough to span many track
#: lengths and give a wide baseline.
WINDOW_FRAMES = 150
#: Frames each window shares with the next: the chain's similarity rests on their cameras and on the tracks seen there.
WINDOW_OVERLAP = 30
#: Tracks are reconstructed in one dense problem up to this many frames and (frames × tracks) entries; beyond
#: either, in windows (:func:`reconstruct_segmented`).  The dense path's arrays and global bundle adjustments grow
#: with frames × tracks and its registration steps with the frames: on a sliding camera's 1 000 frames × 2 500
#: short tracks it took 73 s and 1.4 GB and registered 852 frames, the windows 20 s, 0.29 GB and 989 frames.
DENSE_MAX_FRAMES = 500
DENSE_MAX_ENTRIES = 5_000_000
#: A window is chained to the previous one only with at least this many shared camera centres and points agreeing.
MIN_CHAIN_MATCHES = 10
#: In the chain's similarity fit, a match whose residual exceeds this many times the median is left out.
CHAIN_OUTLIER_FACTOR = 3.0
#: A chain's similarity fit is refused when its RMS residual exceeds this share of the matches' spread (the RMS
#: distance from their centroid): the window does not agree with the one before (a wrong reconstruction).
CHAIN_MAX_RELATIVE_RMS = 0.03
#: A window's reconstruction is refused when it registers fewer than this share of its frames, or reconstructs
#: fewer than :data:`MIN_WINDOW_POINT_SHARE` of its tracks seen twice (a wrong initial pair leaves a few points).
MIN_WINDOW_FRAME_SHARE = 0.5
MIN_WINDOW_POINT_SHARE = 0.3
#: Refinement rounds of each window's reconstruction at most: its points are fused again with the chained cameras,
#: and the rounds barely move its cameras (3 000 frames of the benchmark's sliding scene: centres 0.118 m median
#: error both ways, rotations 0.437° with 8 rounds and 0.444° without; 36.7 s and 28.2 s).
WINDOW_REFINEMENT_ROUNDS = 0
_TRIM_ROUNDS = 5  # refits of the chain's similarity at most (the inliers settle in two or three)

def fits_dense_reconstruction(shape: tuple[int, int]) -> bool:
    """Whether tracks of ``shape`` (frames, tracks) are reconstructed as one dense problem, not in windows.

    Examples
    --------
    >>> fits_dense_reconstruction((36, 4983)), fits_dense_reconstruction((20000, 50047))
    (True, False)
    """
    frames, tracks = shape
    return frames <= DENSE_MAX_FRAMES and frames * tracks <= DENSE_MAX_ENTRIES


def window_stop(start: int, n_frames: int, window: int | None = None, overlap: int | None = None) -> int:
    """Where the window that begins at frame ``start`` ends (exclusive): ``window`` frames on, or at the last frame
    when less than half a step (``window`` − ``overlap``) would be left after it.

    ``window`` and ``overlap`` default to :data:`WINDOW_FRAMES` and :data:`WINDOW_OVERLAP`; the next
    window begins ``overlap`` frames before this one ends.

    Examples
    --------
    >>> window_stop(0, 1000, 150, 30), window_stop(840, 1000, 150, 30), window_stop(0, 100, 150, 30)
    (150, 1000, 100)
    """
    window = WINDOW_FRAMES if window is None else int(window)
    overlap = WINDOW_OVERLAP if overlap is None else int(overlap)
    if window < 2 or not 0 <= overlap < window:
        raise InvalidInputError(f"windows need >= 2 frames and an overlap in [0, window) frames; got {window} and "
                                f"{overlap}")
    stop = start + window
    return n_frames if n_frames - stop < (window - overlap) // 2 else stop


@dataclass(frozen=True)
class SimilarityFit:
    """``target ≈ scale * source @ rotation.T + translation``, fitted on the ``inliers``.

    Attributes
    ----------
    scale, rotation (3, 3), translation (3,) : the similarity.
    inliers : (N,) bool — the matches the final fit used.
    rms : RMS residual distance over the inliers.
    """

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    inliers: np.ndarray
    rms: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points moved by the similarity."""
        return self.scale * np.asarray(points) @ self.rotation.T + self.translation


def robust_similarity(source: np.ndarray, target: np.ndarray, *, min_matches: int = MIN_CHAIN_MATCHES) -> SimilarityFit:
    """Least-squares similarity of matched 3-D points, refitted without matches far beyond the median residual.

    Umeyama's fit (:func:`~kalmansfm.structure.geometry.alignment.align_similarity`) on all
    matches, then again on those whose residual is at most :data:`CHAIN_OUTLIER_FACTOR` times the
    median, until the inliers settle.

    Raises
    ------
    NotEnoughDataError
        Fewer than ``min_matches`` matches (finite in both), or fewer left agreeing.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> source = rng.normal(size=(30, 3))
    >>> target = 2.0 * source @ np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]).T + 5.0
    >>> target[0] += 10.0  # one wrong match
    >>> fit = robust_similarity(source, target)
    >>> round(fit.scale, 9), int(fit.inliers.sum()), fit.rms < 1e-9
    (2.0, 29, True)
    """
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    finite = np.isfinite(src).all(axis=1) & np.isfinite(dst).all(axis=1)
    inliers = finite
    for _ in range(_TRIM_ROUNDS):
        if inliers.sum() < min_matches:
            raise NotEnoughDataError(f"a similarity needs >= {min_matches} matches that agree; got {int(inliers.sum())}")
        fit = align_similarity(np.where(inliers[:, None], src, np.nan), dst)
        residual = np.linalg.norm(fit.scale * src @ fit.rotation.T + fit.translation - dst, axis=1)
        bound = CHAIN_OUTLIER_FACTOR * np.median(residual[inliers])
        agree = finite & (residual <= max(bound, 1e-12 * (1.0 + np.abs(dst[finite]).max())))
        if np.array_equal(agree, inliers):
            break
        inliers = agree
    if inliers.sum() < min_matches:
        raise NotEnoughDataError(f"a similarity needs >= {min_matches} matches that agree; got {int(inliers.sum())}")
    rms = float(np.sqrt(np.mean(residual[inliers] ** 2)))
    return SimilarityFit(fit.scale, fit.rotation, fit.translation, inliers, rms)


@dataclass
class _Window:
    """One window's reconstruction, in its own gauge until chained."""

    start: int
    stop: int
    frame_status: np.ndarray  # (stop - start,) for every frame of the window
    frames: np.ndarray | None = None  # registered, global indices
    rotations: np.ndarray | None = None
    centres: np.ndarray | None = None
    pose_covariances: np.ndarray | None = None
    tracks: np.ndarray | None = None  # reconstructed, global indices
    points: np.ndarray | None = None
    initial_pair: tuple[int, int] | None = None
    failure: str | None = None
    chain: int = -1  # which chained run of windows it belongs to

    @property
    def middle(self) -> float:
        return 0.5 * (self.start + self.stop - 1)

    def move(self, fit: SimilarityFit) -> None:
        """Carry the window into the frame ``fit`` maps it to."""
        assert self.rotations is not None and self.pose_covariances is not None
        Q = fit.rotation
        self.centres = fit.apply(self.centres)
        self.points = fit.apply(self.points)
        self.rotations = self.rotations @ Q.T
        turn = np.eye(6)
        turn[3:, 3:] = fit.scale * Q  # (δω, δC): the rotation's perturbation is in the camera frame
        self.pose_covariances = turn @ self.pose_covariances @ turn.T


def _window_observations(observations: Observations, by_frame: np.ndarray, frame_sorted: np.ndarray,
                         start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """The dense (stop − start, n, 2) observations of the n tracks seen at least twice in the window, and their ids."""
    lo, hi = np.searchsorted(frame_sorted, [start, stop])
    entries = by_frame[lo:hi]
    tracks, local, counts = np.unique(observations.point[entries], return_inverse=True, return_counts=True)
    dense = np.full((stop - start, tracks.size, 2), np.nan)
    dense[observations.frame[entries] - start, local] = observations.xy[entries]
    keep = counts >= 2
    return dense[:, keep], tracks[keep]


def _reconstruct_window(observations: Observations, by_frame: np.ndarray, frame_sorted: np.ndarray,
                        intrinsics: np.ndarray, settings: PerspectiveSettings, start: int, stop: int,
                        timings: dict[str, float]) -> _Window:
    dense, tracks = _window_observations(observations, by_frame, frame_sorted, start, stop)
    window = _Window(start, stop, np.full(stop - start, FrameStatus.NOT_CONNECTED, dtype=np.int8))
    try:
        rec = reconstruct_perspective(dense, intrinsics[start:stop], settings=settings)
    except NotEnoughDataError as exc:
        window.failure = str(exc)
        return window
    n_registered, n_ok = int(rec.registered.sum()), int(rec.reconstructed.sum())
    if n_registered < MIN_WINDOW_FRAME_SHARE * (stop - start) or n_ok < MIN_WINDOW_POINT_SHARE * tracks.size:
        window.failure = f"only {n_registered} of {stop - start} frames registered and {n_ok} of {tracks.size} tracks"
        return window
    for name, seconds in rec.timings.items():
        timings[name] = timings.get(name, 0.0) + seconds
    registered, ok = rec.registered, rec.reconstructed
    assert rec.pose_covariances is not None
    window.frame_status = rec.frame_status.copy()
    window.frames = start + np.flatnonzero(registered)
    window.rotations = rec.rotations[registered]
    window.centres = rec.centres[registered]
    window.pose_covariances = rec.pose_covariances[registered]
    window.tracks = tracks[ok]
    window.points = rec.points[ok]
    assert isinstance(rec.details, PerspectiveDetails)
    window.initial_pair = (start + rec.details.initial_pair[0], start + rec.details.initial_pair[1])
    return window


def _attempts(start: int, stop: int, overlap: int, settings: PerspectiveSettings
              ) -> list[tuple[tuple[int, int], PerspectiveSettings]]:
    """The spans and settings a window is tried with, in turn, until it is reconstructed and chained.

    Its span as planned; the same with lower registration thresholds (:func:`_relaxed`); and a
    shorter span, about half, by the frames it shares with the window before (another initial pair:
    the best-scoring pair of a window is now and then a wrong relative pose).
    """
    short = min(stop, start + max(3 * overlap, (stop - start) // 2))
    attempts = [((start, stop), settings), ((start, stop), _relaxed(settings))]
    return attempts + ([((start, short), settings)] if short < stop else [])


def _relaxed(settings: PerspectiveSettings) -> PerspectiveSettings:
    """The settings a window that could not be reconstructed or chained is tried again with.

    A window's growth can stall at a frame that sees few points already triangulated with enough
    parallax; a third fewer PnP inliers and half the triangulation angle let it go on.
    """
    return replace(settings, min_registration_points=max(6, 2 * settings.min_registration_points // 3),
                   min_triangulation_angle_deg=settings.min_triangulation_angle_deg / 2)


def _window_in_chain(observations: Observations, by_frame: np.ndarray, frame_sorted: np.ndarray,
                     intrinsics: np.ndarray, settings: PerspectiveSettings, start: int, stop: int,
                     previous: _Window | None, timings: dict[str, float]
                     ) -> tuple[_Window, SimilarityFit | None, str | None]:
    """A window, its similarity onto the ``previous`` one (None: none before it or no fit) and why it failed, if it did."""
    window = _reconstruct_window(observations, by_frame, frame_sorted, intrinsics, settings, start, stop, timings)
    if window.failure is not None:
        return window, None, f"frames {start}-{stop - 1} could not be reconstructed ({window.failure})"
    if previous is None:
        return window, None, None
    began = time.perf_counter()
    try:
        return window, _chain_fit(previous, window), None
    except NotEnoughDataError as exc:
        return window, None, f"frames {start}-{stop - 1} could not be chained to the window before ({exc})"
    finally:
        timings["chaining"] = timings.get("chaining", 0.0) + time.perf_counter() - began


def _chain_fit(previous: _Window, window: _Window) -> SimilarityFit:
    """The similarity taking ``window`` onto ``previous`` (already chained), from shared cameras and points."""
    assert previous.frames is not None and window.frames is not None
    shared_frames, a, b = np.intersect1d(previous.frames, window.frames, return_indices=True)
    _, c, d = np.intersect1d(previous.tracks, window.tracks, return_indices=True)
    source = np.concatenate([window.centres[b], window.points[d]])
    target = np.concatenate([previous.centres[a], previous.points[c]])
    fit = robust_similarity(source, target)
    used = target[fit.inliers]
    spread = float(np.sqrt(np.mean(np.sum((used - used.mean(axis=0)) ** 2, axis=1))))
    if fit.rms > CHAIN_MAX_RELATIVE_RMS * spread:
        raise NotEnoughDataError(f"the shared cameras and points disagree: RMS {fit.rms:.3g} after the similarity, "
                                 f"{fit.rms / spread:.1%} of their spread")
    return fit


def reconstruct_segmented(observations: Observations, intrinsics: object, settings: PerspectiveSettings | None = None,
                          *, window_frames: int | None = None, overlap_frames: int | None = None,
                          progress: Callable[[int, int], object] | None = None,
                          fusion_progress: Callable[[int, int], object] | None = None) -> Reconstruction:
    """Camera poses and 3-D points of a long video-ordered sequence, reconstructed in overlapping windows.

    The module docstring describes the method.  Frames are taken in their index order (the
    order of a video); tracks of any length are fine, but a window needs tracks seen in several of
    its frames with some parallax.

    Parameters
    ----------
    observations : Observations of shape (F, P) — one entry per observation (frame index, track
        index, pixel position), e.g. from a tracks file read per observation.
    intrinsics : (3, 3) or (F, 3, 3) — K of every frame.
    settings : PerspectiveSettings, optional — how each window is reconstructed (always by the
        batch method); its outlier probability is also the final fusion's.
    window_frames, overlap_frames : the windows (:func:`window_stop`; default :data:`WINDOW_FRAMES`
        and :data:`WINDOW_OVERLAP`).
    progress : called after each window with (frames reached, frames), e.g. for a progress bar.
    fusion_progress : the final fusion's ``progress`` (:func:`~kalmansfm.structure.fusion.fuse`).

    Returns
    -------
    Reconstruction
        ``kind="perspective"``, ``method="segmented"``: poses of the frames in the kept chain of
        windows, points and covariances from the fusion with those cameras (read in
        :data:`SEGMENTED_GAUGE`), σ estimated by the fusion, the observations (sparse) with the
        ones used and their residuals, the first window's initial pair in ``details``, and a
        warning saying that the sequence was reconstructed in windows.

    Raises
    ------
    InvalidInputError
        Not :class:`~kalmansfm.structure.Observations`, malformed K, a bad window size.
    NotEnoughDataError
        No window could be reconstructed.

    Examples
    --------
    >>> from kalmansfm.scenes.perspective import perspective_scene
    >>> scene = perspective_scene(frames=8, points=150, pixel_std=0.5, seed=3)
    >>> obs = Observations.from_dense(scene.observations)
    >>> rec = reconstruct_segmented(obs, scene.intrinsics, window_frames=6, overlap_frames=2)
    >>> rec.method, int(rec.registered.sum()), int(rec.reconstructed.sum()) >= 145, round(rec.noise.std, 1)
    ('segmented', 8, True, 0.5)
    """
    if not isinstance(observations, Observations):
        raise InvalidInputError(f"observations must be Observations (one entry per observation); got "
                                f"{type(observations).__name__}")
    settings = PerspectiveSettings() if settings is None else settings
    notes = [] if settings.method == "batch" else [
        f"the windows were reconstructed by the batch method, not {settings.method!r} (which needs parallax between "
        "consecutive frames and gives no camera covariances)"]
    settings = replace(settings, method="batch",
                       refinement_rounds=min(settings.refinement_rounds, WINDOW_REFINEMENT_ROUNDS))
    F = observations.shape[0]
    if F < 2:
        raise NotEnoughDataError(f"a reconstruction needs >= 2 frames; got {F}")
    K = validate_intrinsics(intrinsics, F)
    if not np.isfinite(observations.xy).all():
        raise InvalidInputError("observations given per observation must be finite (leave out what is unseen)")
    timings: dict[str, float] = {}
    by_frame = np.argsort(observations.frame, kind="stable")
    frame_sorted = observations.frame[by_frame]
    window_frames = WINDOW_FRAMES if window_frames is None else window_frames
    overlap_frames = WINDOW_OVERLAP if overlap_frames is None else overlap_frames
    windows: list[_Window] = []
    breaks: list[str] = []
    chains = retried = 0
    start = 0
    while True:
        stop = window_stop(start, F, window_frames, overlap_frames)
        previous = windows[-1] if windows and windows[-1].failure is None else None
        fallback = None  # when no attempt chains: the first that was reconstructed begins a new chain
        for span, how in _attempts(start, stop, overlap_frames, settings):
            window, fit, why = _window_in_chain(observations, by_frame, frame_sorted, K, how, *span, previous, timings)
            if why is None:
                break
            if fallback is None or (fallback[0].failure is not None and window.failure is None):
                fallback = (window, fit, why)
        else:
            assert fallback is not None
            window, fit, why = fallback
        retried += fallback is not None
        if why is not None:
            breaks.append(why)
        if window.failure is None:
            if fit is None:
                chains += 1
            else:
                window.move(fit)
            window.chain = chains - 1
        windows.append(window)
        if progress is not None:
            progress(window.stop, F)
        if window.stop >= F:
            break
        start = window.stop - overlap_frames
    done = [w for w in windows if w.failure is None]
    if not done:
        raise NotEnoughDataError(f"no window of {window_frames} frames could be reconstructed: "
                                 f"{windows[0].failure}")
    registered_per_chain = np.bincount([w.chain for w in done], weights=[w.frames.size for w in done])
    kept = int(np.argmax(registered_per_chain))
    rotations, centres, pose_cov, frame_status = _pick_cameras(F, [w for w in done if w.chain == kept], windows)
    first = next(w for w in done if w.chain == kept)
    registered = frame_status == FrameStatus.REGISTERED
    if registered.sum() < 2:
        raise NotEnoughDataError("fewer than 2 frames registered in the segmented reconstruction")
    began = time.perf_counter()
    translations = -np.einsum("fij,fj->fi", rotations, centres)
    rec, every = _fuse_points(observations, K, rotations, translations, registered, settings, fusion_progress)
    timings["fusion"] = time.perf_counter() - began
    warnings = [f"reconstructed in {len(windows)} windows of up to {min(window_frames, F)} frames overlapping by "
                f"{overlap_frames}, chained by similarities (no loop closure: scale and orientation drift along the "
                "sequence); the points are fused with the chained cameras taken as exact", *notes]
    if chains > 1:
        warnings.append(f"the chain of windows broke {chains - 1} times; kept the longest chained part, frames "
                        f"{first.start}-{max(w.stop for w in done if w.chain == kept) - 1}: " + "; ".join(breaks[:5])
                        + (f"; … ({len(breaks)} in all)" if len(breaks) > 5 else ""))
    elif breaks:
        warnings.append("; ".join(breaks[:5]))
    if retried:
        warnings.append(f"{retried} windows were tried again (lower registration thresholds, then a shorter span): "
                        "a growth that stalled, a wrong initial pair, or a window that did not chain")
    missing = np.flatnonzero(~registered)
    if missing.size:
        warnings.append(f"{missing.size} of {F} frames have no camera")
    projections = np.full((F, 3, 4), np.nan)
    projections[registered] = K[registered] @ np.concatenate([rotations[registered],
                                                              translations[registered, :, None]], axis=2)
    assert first.initial_pair is not None
    return Reconstruction(
        kind="perspective", method="segmented", camera_model="pinhole", projections=projections, rotations=rotations,
        frame_status=frame_status, points=rec.points, point_covariances=rec.point_covariances,
        point_status=rec.point_status, views=rec.views, point_reprojection_rms=rec.point_reprojection_rms,
        covariance_gauge=SEGMENTED_GAUGE, observations=every, noise=rec.noise,
        reprojection_rms=rec.reprojection_rms,
        details=PerspectiveDetails(initial_pair=first.initial_pair, outlier_threshold_px=settings.outlier_threshold_px,
                                   outlier_probability=settings.outlier_probability),
        intrinsics=K, translations=translations, pose_covariances=pose_cov, warnings=tuple(warnings),
        timings=timings)


def _pick_cameras(n_frames: int, chained: list[_Window], windows: list[_Window]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each frame's camera from the chained window whose middle is nearest; the statuses of the others."""
    rotations = np.full((n_frames, 3, 3), np.nan)
    centres = np.full((n_frames, 3), np.nan)
    pose_cov = np.full((n_frames, 6, 6), np.nan)
    distance = np.full(n_frames, np.inf)
    status = np.full(n_frames, FrameStatus.NOT_CONNECTED, dtype=np.int8)
    for w in windows:  # a frame some window tried and could not place
        span = slice(w.start, w.stop)
        status[span] = np.where(w.frame_status == FrameStatus.POSE_FAILED, FrameStatus.POSE_FAILED, status[span])
    for w in chained:
        assert w.frames is not None
        nearer = np.abs(w.frames - w.middle) < distance[w.frames]
        f = w.frames[nearer]
        distance[f] = np.abs(f - w.middle)
        rotations[f], centres[f], pose_cov[f] = w.rotations[nearer], w.centres[nearer], w.pose_covariances[nearer]
    status[np.isfinite(distance)] = FrameStatus.REGISTERED
    return rotations, centres, pose_cov, status


def _fuse_points(observations: Observations, intrinsics: np.ndarray, rotations: np.ndarray, translations: np.ndarray,
                 registered: np.ndarray, settings: PerspectiveSettings,
                 progress: Callable[[int, int], object] | None = None) -> tuple[Reconstruction, Observations]:
    """Every track fused from its observations in the registered frames; and all observations, over all frames."""
    F, P = observations.shape
    frames = np.flatnonzero(registered)
    view = np.full(F, -1)
    view[frames] = np.arange(frames.size)
    inside = registered[observations.frame]
    per_view = Observations.from_sparse((frames.size, P), view[observations.frame[inside]],
                                        observations.point[inside], observations.xy[inside])
    cameras = CameraSet.from_pose(intrinsics[frames], rotations[frames], translations[frames], frames=frames)
    fusion = FusionSettings(method="batch", outlier_probability=settings.outlier_probability, noise_model="gaussian")
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # points at a camera's plane
        fused = fuse(per_view, cameras, settings=fusion, progress=progress)
    o = fused.observations
    outside = np.flatnonzero(~inside)
    every = Observations.from_sparse(
        (F, P), np.concatenate([frames[o.frame], observations.frame[outside]]),
        np.concatenate([o.point, observations.point[outside]]), np.concatenate([o.xy, observations.xy[outside]]),
        used=np.concatenate([o.used, np.zeros(outside.size, bool)]),
        residual=np.concatenate([o.residual, np.full(outside.size, np.nan)]),
        rejected=np.concatenate([o.rejected, np.zeros(outside.size, bool)]))
    return fused, every
