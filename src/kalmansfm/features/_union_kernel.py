"""Compiled (numba) kernel of the union–find that refuses a merge which would put two different
features of one image into one set (:func:`kalmansfm.features.tracks.union_without_conflicts`).

Each element (a feature, or a whole track) owns entries (image, feature).  Edges are taken in
the order given (strongest first); an edge joins its two sets unless some image has an entry in
both with different features.  Sets are kept as linked lists of their elements; the check marks
the larger set's images in a scratch array and scans the smaller one.  The plain-Python
reference with Python sets is ``_union_reference`` in the tests' eyes
(:func:`kalmansfm.features.tracks.union_reference`).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _find(parent: np.ndarray, x: int) -> int:
    root = x
    while parent[root] != root:
        root = parent[root]
    while parent[x] != root:  # path compression
        nxt = parent[x]
        parent[x] = root
        x = nxt
    return root


@njit(cache=True)
def union_kernel(count: int, entry_start: np.ndarray, entry_image: np.ndarray, entry_feature: np.ndarray,
                 first: np.ndarray, second: np.ndarray, image_count: int) -> np.ndarray:
    """(count,) root label of every element after the constrained unions of the edges (first[k], second[k])."""
    parent = np.arange(count)
    next_member = np.full(count, -1)
    last_member = np.arange(count)
    size = np.ones(count, np.int64)
    mark = np.full(image_count, -1, np.int64)
    for e in range(first.shape[0]):
        ra = _find(parent, first[e])
        rb = _find(parent, second[e])
        if ra == rb:
            continue
        if size[ra] < size[rb]:
            ra, rb = rb, ra
        member = ra
        while member != -1:
            for k in range(entry_start[member], entry_start[member + 1]):
                mark[entry_image[k]] = entry_feature[k]
            member = next_member[member]
        conflict = False
        member = rb
        while member != -1 and not conflict:
            for k in range(entry_start[member], entry_start[member + 1]):
                seen = mark[entry_image[k]]
                if seen != -1 and seen != entry_feature[k]:
                    conflict = True
                    break
            member = next_member[member]
        member = ra
        while member != -1:
            for k in range(entry_start[member], entry_start[member + 1]):
                mark[entry_image[k]] = -1
            member = next_member[member]
        if conflict:
            continue
        parent[rb] = ra
        next_member[last_member[ra]] = rb
        last_member[ra] = last_member[rb]
        size[ra] += size[rb]
    labels = np.empty(count, np.int64)
    for x in range(count):
        labels[x] = _find(parent, x)
    return labels
