"""One round of guided matching (active search) over every view of a reconstruction.

For a registered view, each known point it does not see yet is predicted with the view's camera and
the covariances (:func:`.guided.predict_points`) and searched for inside its gate
(:func:`.guided.guided_search`), with the point's descriptor in the registered view that saw it from
nearest.  A view without a camera first gets one: its features are matched with the reconstructed
tracks' features in its most similar registered views, and PnP on those 2-D–3-D matches gives a pose,
searched with a pixel gate (no covariance).  Then every found feature is applied: a free feature joins
the track (the nearest descriptor wins when several points claim it); a feature that already belongs to
another track merges the two when all the other track's observations lie within the outlier threshold
of the point's projections.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..features import FeatureTracks, ImageFeatures, MatchGraph, add_observations, match_descriptors, merge_tracks
from ..structure import CameraSet, fuse
from ..structure.perspective import PerspectiveSettings
from .backend import CameraSolution
from .guided import Prediction, guided_search, pose_from_correspondences, predict_points
from .settings import MappingSettings

__all__ = ["GuidedMatchingSummary", "active_search", "drop_inconsistent"]

# An unregistered view is matched against this many of its most similar registered views to predict its pose.
_POSE_NEIGHBOURS = 3


@dataclass(frozen=True)
class GuidedMatchingSummary:
    """What guided matching did.

    Attributes
    ----------
    added_observations : features that joined a track inside its gate.
    merged_tracks : tracks absorbed into another (found to be the same point).
    predicted_views : views the first reconstruction had not registered that got a pose by PnP and were searched.
    dropped_observations : observations of the tracks kept for the final reconstruction that the first
        reconstruction's cameras reject (:func:`drop_inconsistent`).
    """

    added_observations: int = 0
    merged_tracks: int = 0
    predicted_views: tuple[int, ...] = ()
    dropped_observations: int = 0


def _unrelated_distance(features: Sequence[ImageFeatures], quantile: float, seed: int, samples: int = 4096) -> float:
    """The ``quantile`` of the descriptor distances between random features of two different images."""
    rng = np.random.default_rng(seed)
    sizes = np.array([len(f) for f in features])
    usable = np.flatnonzero(sizes > 0)
    if len(usable) < 2:
        return float("inf")
    offset = np.concatenate([[0], np.cumsum(sizes)])
    descriptors = np.concatenate([f.descriptors for f in features])
    first = rng.choice(usable, samples)
    # another usable image: a non-zero step around the list of usable images
    second = usable[(np.searchsorted(usable, first) + rng.integers(1, len(usable), samples)) % len(usable)]
    a = descriptors[offset[first] + (rng.random(samples) * sizes[first]).astype(np.int64)]
    b = descriptors[offset[second] + (rng.random(samples) * sizes[second]).astype(np.int64)]
    d2 = np.sum((a - b) ** 2, axis=1)
    return float(np.quantile(d2 if features[0].binary else np.sqrt(d2), quantile))


def _affinity(graph: MatchGraph) -> np.ndarray:
    """(F, F) how much two views have in common: the retrieval similarity plus their putative matches."""
    a = graph.selection.similarity.astype(np.float64).copy()
    i, j = graph.candidates.T if len(graph.candidates) else (np.zeros(0, int), np.zeros(0, int))
    a[i, j] += graph.putative_counts
    a[j, i] += graph.putative_counts
    return a


class _ActiveSearch:
    """One round of guided matching over all views (the state it needs, gathered once)."""

    def __init__(self, features: Sequence[ImageFeatures], tracks: FeatureTracks, solution: CameraSolution,
                 K: np.ndarray, image_size: tuple[int, int], settings: MappingSettings, max_distance: float,
                 affinity: np.ndarray) -> None:
        self.features, self.tracks, self.solution = features, tracks, solution
        self.points, self.covariances, self.K = solution.points, solution.point_covariances, K
        self.width, self.height = image_size
        self.settings, self.max_distance, self.affinity = settings, max_distance, affinity
        self.has_point = solution.reconstructed
        self.found: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []  # view, track, feature, distance
        self.predicted: list[int] = []

    def _reference_descriptors(self, view: int, ids: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each point's descriptor in the registered view that saw it from nearest ``centre``; and that angle (deg)."""
        registered = self.solution.registered
        X = self.points[ids]
        to_view = centre - X
        to_view /= np.linalg.norm(to_view, axis=1, keepdims=True)
        centres = self.solution.centres
        observers = self.tracks.seen[:, ids] & registered[:, None]
        rays = np.where(registered[:, None, None], centres[:, None, :] - X[None], 0.0)
        rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), 1e-300)
        cosine = np.where(observers, np.einsum("fnk,nk->fn", rays, to_view), -2.0)
        nearest = np.argmax(cosine, axis=0)
        angle = np.degrees(np.arccos(np.clip(cosine[nearest, np.arange(len(ids))], -1.0, 1.0)))
        width = self.features[view].descriptors.shape[1]
        descriptors = np.zeros((len(ids), width), np.float32)
        for u in np.unique(nearest):
            mine = nearest == u
            descriptors[mine] = self.features[u].descriptors[self.tracks.feature_index[u, ids[mine]]]
        return descriptors, angle

    def search(self, view: int, rotation: np.ndarray, translation: np.ndarray, camera_covariance: np.ndarray | None,
               floor_px: float) -> None:
        s = self.settings
        ids = np.flatnonzero(self.has_point & ~self.tracks.seen[view])
        if len(ids) == 0 or len(self.features[view]) == 0:
            return
        prediction = predict_points(self.points[ids], self.covariances[ids], rotation, translation, self.K[view],
                                    camera_covariance, self.solution.pixel_std)
        x, y = prediction.pixels.T
        visible = (prediction.depths > 0) & (x >= 0) & (y >= 0) & (x <= self.width - 1) & (y <= self.height - 1)
        ids = ids[visible]
        if len(ids) == 0:
            return
        centre = -rotation.T @ translation
        reference, angle = self._reference_descriptors(view, ids, centre)
        near = angle <= s.max_view_angle_deg
        ids, reference = ids[near], reference[near]
        keep = np.flatnonzero(visible)[near]
        prediction = Prediction(prediction.pixels[keep], prediction.covariances[keep], prediction.depths[keep])
        found = guided_search(prediction, reference, self.features[view], gate_chi2=s.gate_chi2,
                              gate_floor_px=floor_px, max_gate_px=max(s.max_gate_px, floor_px), ratio=s.guided_ratio,
                              max_distance=self.max_distance)
        self.found.append((np.full(len(found), view), ids[found.predictions], found.features, found.distances))

    def predict_pose(self, view: int) -> tuple[np.ndarray, np.ndarray] | None:
        """A pose for an unregistered view from its 2-D–3-D matches (PnP); its inliers are kept as matches."""
        rs = self.settings.reconstruction
        features = self.features[view]
        fi = self.tracks.feature_index
        ids = [np.flatnonzero(self.tracks.seen[view] & self.has_point)]
        feats = [fi[view, ids[0]]]
        registered = np.flatnonzero(self.solution.registered)
        for u in registered[np.argsort(-self.affinity[view, registered], kind="stable")][:_POSE_NEIGHBOURS]:
            theirs = np.flatnonzero(self.tracks.seen[u] & self.has_point)
            m = match_descriptors(features.descriptors, self.features[u].descriptors[fi[u, theirs]],
                                  self.settings.features.ratio, features.binary)
            ids.append(theirs[m.pairs[:, 1]])
            feats.append(m.pairs[:, 0])
        track_ids, feature_ids = np.concatenate(ids), np.concatenate(feats)
        _, first = np.unique(feature_ids, return_index=True)
        track_ids, feature_ids = track_ids[first], feature_ids[first]
        _, first = np.unique(track_ids, return_index=True)
        track_ids, feature_ids = track_ids[first], feature_ids[first]
        pose = pose_from_correspondences(self.points[track_ids], features.keypoints[feature_ids], self.K[view],
                                         rs.outlier_threshold_px, rs.min_registration_points, rs.seed)
        if pose is None:
            return None
        R, t, inliers = pose
        new = inliers & ~self.tracks.seen[view, track_ids]
        self.found.append((np.full(int(new.sum()), view), track_ids[new], feature_ids[new], np.zeros(int(new.sum()))))
        self.predicted.append(view)
        return R, t

    def run(self) -> None:
        sol = self.solution
        for view in range(len(self.features)):
            if sol.registered[view]:
                self.search(view, sol.rotations[view], sol.translations[view], sol.camera_covariances[view],
                            self.settings.gate_floor_px)
            elif len(self.features[view]):
                pose = self.predict_pose(view)
                if pose is not None:
                    self.search(view, pose[0], pose[1], None, self.settings.reconstruction.outlier_threshold_px)

    def apply(self) -> tuple[FeatureTracks, GuidedMatchingSummary]:
        """The tracks with the found features added (free features) or their tracks merged (owned features)."""
        tracks = self.tracks
        if not self.found:
            return tracks, GuidedMatchingSummary(predicted_views=tuple(self.predicted))
        view, track, feature, distance = (np.concatenate(c) for c in zip(*self.found))
        offset = np.concatenate([[0], np.cumsum([len(f) for f in self.features])])
        owner = np.full(offset[-1], -1, np.int64)
        frames, ids = np.nonzero(tracks.seen)
        owner[offset[frames] + tracks.feature_index[frames, ids]] = ids
        key = offset[view] + feature
        current = owner[key]
        # a free feature claimed by several points goes to the nearest descriptor
        free = np.flatnonzero(current < 0)
        free = free[np.lexsort((distance[free], key[free]))]
        free = free[np.r_[True, key[free][1:] != key[free][:-1]]] if len(free) else free
        tracks = add_observations(tracks, self.features, view[free], track[free], feature[free])
        # an owned feature: the two tracks are one point if the other track's observations agree with the point
        owned = np.flatnonzero(current >= 0)
        other = current[owned]
        agree = self._same_point(track[owned], other)
        owned, other = owned[agree], other[agree]
        order = np.argsort(distance[owned], kind="stable")
        before = tracks.feature_index.shape[1]
        tracks = merge_tracks(tracks, track[owned][order], other[order])
        merged = before - tracks.feature_index.shape[1]
        return tracks, GuidedMatchingSummary(len(free), merged, tuple(self.predicted))

    def _same_point(self, first: np.ndarray, second: np.ndarray) -> np.ndarray:
        """Whether track ``second``'s observations in the registered views all lie within the outlier threshold
        of the projections of track ``first``'s point: then the two are one point (a feature alone in a gate
        is not evidence enough to join whole tracks)."""
        sol = self.solution
        frames = np.flatnonzero(sol.registered)
        X = self.points[first]
        y = np.einsum("fij,kj->fki", sol.rotations[frames], X) + sol.translations[frames][:, None]
        h = np.einsum("fij,fkj->fki", self.K[frames], y)
        with np.errstate(invalid="ignore", divide="ignore"):
            pixels = h[..., :2] / h[..., 2:]
        seen = self.tracks.seen[np.ix_(frames, second)]
        error = np.linalg.norm(pixels - self.tracks.observations[np.ix_(frames, second)], axis=2)
        far = seen & ~((error <= self.settings.reconstruction.outlier_threshold_px) & (y[..., 2] > 0))
        return ~far.any(axis=0)


def active_search(features: Sequence[ImageFeatures], tracks: FeatureTracks, solution: CameraSolution,
                  intrinsics: np.ndarray, image_size: tuple[int, int], graph: MatchGraph,
                  settings: MappingSettings) -> tuple[FeatureTracks, GuidedMatchingSummary]:
    """Search every view for the known points where the cameras predict them; the tracks with what was found.

    Parameters
    ----------
    features : the features of every view.
    tracks : the tracks; ``solution.points`` holds a point (or NaN) for each of them.
    solution : cameras, points and covariances (:func:`.backend.read_solution`).
    intrinsics : (F, 3, 3).
    image_size : (width, height).
    graph : the match graph (its similarities rank the views an unregistered view is matched with).
    settings : the gate, the descriptor tests, the view-angle limit.

    Returns
    -------
    tracks : FeatureTracks — with the found observations added and the tracks found to be one point merged.
    summary : GuidedMatchingSummary.

    Examples
    --------
    Forget view 2's observations, then find them again where its camera says they are.

    >>> from dataclasses import replace
    >>> from kalmansfm.mapping import reconstruct_images, read_solution
    >>> from kalmansfm.scenes.textured import textured_views
    >>> views = textured_views(frames=4, arc_deg=45.0, seed=2)
    >>> result = reconstruct_images(views.images, views.intrinsics)
    >>> t = result.tracks
    >>> hidden = FeatureTracks(t.observations.copy(), t.feature_index.copy())
    >>> hidden.observations[2], hidden.feature_index[2] = np.nan, -1
    >>> found, summary = active_search(result.features, hidden, read_solution(result.reconstruction),
    ...                                np.repeat(views.intrinsics[None], 4, 0), result.image_size,
    ...                                result.match_graph, result.settings)
    >>> bool(summary.added_observations > 0.8 * (t.feature_index[2] >= 0).sum())
    True
    """
    search = _ActiveSearch(features, tracks, solution, intrinsics, image_size, settings,
                           _unrelated_distance(features, settings.unrelated_quantile, settings.features.seed),
                           _affinity(graph))
    search.run()
    return search.apply()


def drop_inconsistent(tracks: FeatureTracks, solution: CameraSolution, intrinsics: np.ndarray,
                      settings: PerspectiveSettings) -> tuple[FeatureTracks, int]:
    """The tracks without the observations that the registered cameras call outliers; and how many went.

    Each track is triangulated with the cameras of its registered views (the fusion engine's per-point
    maximum likelihood with leave-one-out outlier rounds, the test and threshold of the back end), and
    the observations it rejects are removed.  Observations in views without a camera are kept.

    Examples
    --------
    A track's observation moved 10 px off is dropped; the others stay.

    >>> from kalmansfm.mapping import reconstruct_images, read_solution
    >>> from kalmansfm.scenes.textured import textured_views
    >>> views = textured_views(frames=4, arc_deg=45.0, seed=2)
    >>> result = reconstruct_images(views.images, views.intrinsics)
    >>> t = result.tracks
    >>> moved = t.observations.copy()
    >>> k = int(np.flatnonzero(t.seen.all(axis=0))[0])       # a track seen in all four views
    >>> moved[1, k] += 10.0
    >>> checked, dropped = drop_inconsistent(FeatureTracks(moved, t.feature_index),
    ...                                      read_solution(result.reconstruction),
    ...                                      np.repeat(views.intrinsics[None], 4, 0), result.settings.reconstruction)
    >>> bool(checked.seen[1, k]), int(checked.seen[:, k].sum()), bool(dropped < 0.02 * t.seen.sum())
    (False, 3, True)
    """
    frames = np.flatnonzero(solution.registered)
    if len(frames) < 2 or tracks.feature_index.shape[1] == 0:
        return tracks, 0
    cameras = CameraSet.from_pose(intrinsics[frames], solution.rotations[frames], solution.translations[frames])
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # points at a camera's plane
        fused = fuse(tracks.observations[frames], cameras, method="batch",
                     pixel_std=settings.outlier_threshold_px / np.sqrt(settings.chi2_bound),
                     outlier_probability=settings.outlier_probability)
    drop = np.zeros(tracks.feature_index.shape, bool)
    drop[frames] = fused.observations.rejected_mask() & tracks.seen[frames]
    observations = np.where(drop[..., None], np.nan, tracks.observations)
    feature_index = np.where(drop, -1, tracks.feature_index)
    return FeatureTracks(observations, feature_index, tracks.split_components), int(drop.sum())
