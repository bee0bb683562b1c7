"""Blocks of points that fusion works on: each point's observations over the views that see the block.

Points are independent given the cameras, so a fusion may hold its observations in any grouping
of the points.  A :class:`Block` is a dense (views × points) sub-array over only the views its
points are seen in.  Observations given as one dense (V, N, 2) array are one block; observations
given sparsely (:class:`~kalmansfm.structure.reconstruction.Observations`) — a long sequence of
short tracks — are cut into blocks of tracks that start close together, so that memory follows
the observations, not frames × tracks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.pinhole import CameraSet, triangulate_points
from ..reconstruction import Observations
from .inverse_depth import ViewGeometry, view_geometry
from .inputs import are_poses

__all__ = ["ONE_BLOCK_ENTRIES", "ONE_BLOCK_VIEWS", "Block", "dense_block", "fits_one_block", "orientation_of_blocks", "sparse_blocks"]

# Points used to decide the scene orientation (the sign of the depths most points agree on).
_ORIENTATION_SAMPLE = 2_000
# Tracks whose first views lie within the same window of this many views, and their last views too, share a block
# (then split by size).
_BLOCK_VIEWS = 32
# A block's dense array holds at most about this many (view, point) entries.
_BLOCK_ENTRIES = 2_000_000
#: Observations over at most this many views and (views × points) entries are fused as one dense array, as
#: they would be given densely; more in blocks (the recursive method's per-view geometry grows with the square
#: of the views, a dense array with views × points).
ONE_BLOCK_VIEWS = 256
ONE_BLOCK_ENTRIES = 20_000_000


def fits_one_block(shape: tuple[int, int]) -> bool:
    """Whether observations of ``shape`` (views, points) are fused as one dense array.

    Examples
    --------
    >>> fits_one_block((36, 4983)), fits_one_block((20000, 50047))
    (True, False)
    """
    views, points = shape
    return views <= ONE_BLOCK_VIEWS and views * points <= ONE_BLOCK_ENTRIES


@dataclass(frozen=True)
class Block:
    """Points fused together, over the views that see them.

    Attributes
    ----------
    views : (V_b,) ascending indices into the cameras.
    points : (n_b,) ascending point indices.
    observations : (V_b, n_b, 2) their positions in those views, NaN where unseen.
    """

    views: np.ndarray
    points: np.ndarray
    observations: np.ndarray

    def geometry(self, matrices: np.ndarray, orientation: int) -> ViewGeometry:
        """The per-view quantities of the block's views (built on demand: they grow with the square of the views)."""
        return view_geometry(matrices[self.views], orientation)


def chunks(n: int, size: int) -> list[slice]:
    """``size`` points at a time (at least one, possibly empty, slice).

    Examples
    --------
    >>> chunks(5, 2), chunks(0, 2)
    ([slice(0, 2, None), slice(2, 4, None), slice(4, 5, None)], [slice(0, 0, None)])
    """
    return [slice(s, min(s + size, n)) for s in range(0, n, size)] or [slice(0, 0)]


def dense_block(observations: np.ndarray) -> Block:
    """All views and points of a (V, N, 2) array as one block."""
    V, N, _ = observations.shape
    return Block(np.arange(V), np.arange(N), observations)


def sparse_blocks(observations: Observations) -> list[Block]:
    """Blocks of the points of sparse ``observations`` (frames = views), each a dense array over its own views.

    Points are ordered by their first and last views and cut where either moves into another
    window of :data:`_BLOCK_VIEWS` views, or where the dense array would pass :data:`_BLOCK_ENTRIES`
    entries; a point without observations falls in the first block.

    Examples
    --------
    Two tracks at the start of a 200-view sequence, one at its end: two blocks, each over the
    views its tracks are seen in.

    >>> obs = Observations.from_sparse((200, 3), [0, 1, 1, 2, 198, 199], [0, 0, 1, 1, 2, 2], np.ones((6, 2)))
    >>> [(b.views.tolist(), b.points.tolist(), b.observations.shape) for b in sparse_blocks(obs)]
    [([0, 1, 2], [0, 1], (3, 2, 2)), ([198, 199], [2], (2, 1, 2))]
    """
    frame, point, xy = observations.frame, observations.point, observations.xy
    V, N = observations.shape
    first = np.full(N, V, dtype=np.int64)
    np.minimum.at(first, point, frame)
    first = np.where(first == V, 0, first)
    last = np.zeros(N, dtype=np.int64)
    np.maximum.at(last, point, frame)
    # tracks that begin and end in the same windows of views: a block spans little more than its tracks
    window = (first // _BLOCK_VIEWS) * (V // _BLOCK_VIEWS + 1) + last // _BLOCK_VIEWS
    order = np.lexsort((np.arange(N), window))
    cuts = np.flatnonzero(np.diff(window[order])) + 1
    # observations sorted by (block point order) to slice each block's entries at once
    rank = np.empty(N, dtype=np.int64)
    rank[order] = np.arange(N)
    by_rank = np.argsort(rank[point], kind="stable")
    entry_rank = rank[point][by_rank]
    blocks = []
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, N]):
        for start, stop in _split(lo, hi, entry_rank, frame[by_rank], V):
            e = slice(*np.searchsorted(entry_rank, [start, stop]))
            members = np.sort(order[start:stop])
            entries = by_rank[e]
            views, local_view = np.unique(frame[entries], return_inverse=True)
            dense = np.full((views.size, members.size, 2), np.nan)
            dense[local_view, np.searchsorted(members, point[entries])] = xy[entries]
            blocks.append(Block(views, members, dense))
    return blocks


def _split(lo: int, hi: int, entry_rank: np.ndarray, frame: np.ndarray, n_views: int) -> list[tuple[int, int]]:
    """Ranks [lo, hi) in pieces whose (views × points) stays within :data:`_BLOCK_ENTRIES`."""
    e = slice(*np.searchsorted(entry_rank, [lo, hi]))
    seen = np.zeros(n_views, dtype=bool)
    seen[frame[e]] = True
    views = max(1, int(seen.sum()))
    size = max(1, _BLOCK_ENTRIES // views)
    return [(s, min(s + size, hi)) for s in range(lo, hi, size)] or [(lo, hi)]


def orientation_of_blocks(cams: CameraSet, blocks: list[Block]) -> int:
    """+1 for poses; otherwise the sign of the depths most points (a sample of those seen twice) agree on."""
    if are_poses(cams):
        return 1
    # the block with the most points seen in two views or more decides, as all the points would
    counts = [np.isfinite(b.observations[..., 0]).sum(axis=0) >= 2 for b in blocks]
    best = int(np.argmax([c.sum() for c in counts]))
    sample = np.flatnonzero(counts[best])[:_ORIENTATION_SAMPLE]
    if sample.size == 0:
        return 1
    block = blocks[best]
    return triangulate_points(cams.subset(block.views), block.observations[:, sample]).orientation
