"""Reuse of the filter's per-step arrays once nothing outside the filter holds them (internal).

Every step of :class:`~kalmansfm.estimation.kalman.KalmanFilter` writes its
posterior into arrays other than its input (the input stays valid as the source
of the prior).  Allocating those afresh each step costs the kernel's page faults:
arrays above glibc's mmap threshold (32 MB, i.e. from about 10⁶ tracks) come back
as fresh zeroed pages, measured at +2.6 ns per track-step at 4·10⁶ tracks,
two thirds of the whole step.  The filter therefore hands the arrays it has finished
with to a :class:`BufferPool`, and takes a step's outputs from it.

An array is handed out again only when its reference count shows that the pool's
list is its only holder: a user's variable, a view (which holds its base) or the
filter's own state all keep it out.  So ``xs.append(kf.x)`` keeps its values, as
with FilterPy, where every step makes new arrays.
"""

from __future__ import annotations

import sys

import numpy as np

_PROBE = [np.empty(0)]
# References an array has while a list is its only holder, counted the way take() counts.
_ONLY_THE_POOL = sys.getrefcount(_PROBE[0])


class BufferPool:
    """Arrays the filter has finished with, handed out again when nothing else holds them."""

    def __init__(self, capacity: int = 8) -> None:
        self._arrays: list[np.ndarray] = []
        self._capacity = capacity

    def release(self, *arrays: object) -> None:
        """Offer arrays for reuse (views and arrays already offered are ignored)."""
        for a in arrays:
            if isinstance(a, np.ndarray) and a.base is None and a.flags.writeable and a.size:
                if not any(a is b for b in self._arrays):
                    self._arrays.append(a)
        if len(self._arrays) > self._capacity:
            del self._arrays[: len(self._arrays) - self._capacity]

    def take(self, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        """A free released array of this shape and dtype, or a new one (contents undefined).

        The most recently released free array is taken first, so a filter cycles through
        as few arrays as it needs and the others age out of the pool.
        """
        for k in reversed(range(len(self._arrays))):
            if (self._arrays[k].shape == shape and self._arrays[k].dtype == dtype
                    and sys.getrefcount(self._arrays[k]) == _ONLY_THE_POOL):
                return self._arrays.pop(k)
        return np.empty(shape, dtype=dtype)
