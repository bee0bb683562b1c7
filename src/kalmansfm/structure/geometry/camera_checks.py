"""What a camera given from outside must be: a rotation (repaired where only rounding spoils it) and sane intrinsics.

One place for the checks that :meth:`~kalmansfm.structure.geometry.pinhole.CameraSet.from_pose`
and the camera readers of ``io`` (cameras CSV, ``K.csv``, COLMAP models) apply, so that a file and
a caller meet the same rules:

* a matrix with |R Rᵀ - I| ≤ ``ROTATION_EXACT`` is a rotation to rounding and used as given;
* up to ``ROTATION_ROUNDED`` it is a rotation printed to a few digits (Middlebury's dinoRing: 1.6e-6)
  and replaced by the nearest rotation (SVD: R = U Vᵀ), with a warning saying how far it was off;
* farther from orthonormal, or a reflection (det R = -1), it is not a rotation and is refused;
* K is refused when it is not a camera's (:func:`intrinsics_problem`).

Everything is computed with NumPy's floating-point warnings silenced: absurd numbers become a
refusal with one line, not RuntimeWarnings printed before it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "MAX_ASPECT_RATIO",
    "MAX_INTRINSIC_PX",
    "PROJECTION_ENTRY_RANGE",
    "ROTATION_EXACT",
    "ROTATION_ROUNDED",
    "CheckedRotations",
    "check_rotations",
    "intrinsics_problem",
    "projection_scale_problem",
]

# Rotations given to a camera: |R Rᵀ - I| up to ROTATION_EXACT is rounding of an exact computation (used as
# given); up to ROTATION_ROUNDED it is a rotation printed to a few digits (replaced by the nearest rotation,
# with a warning); beyond that the matrix is not a rotation.
ROTATION_EXACT = 1e-9
ROTATION_ROUNDED = 1e-3
# Intrinsics: focal lengths and principal points are pixels, within ± this (as image coordinates are,
# io.tracks.MAX_COORDINATE_PX); |skew| beyond the focal length (pixel axes under 45° apart) or fy/fx
# beyond this ratio either way is not a camera.
MAX_INTRINSIC_PX = 1e7
MAX_ASPECT_RATIO = 1e3
# A projection matrix is defined up to scale; its largest entry must lie within these bounds, so that its
# determinants and products with points stay far from overflow and underflow (georeferenced cameras: ~1e9).
PROJECTION_ENTRY_RANGE = (1e-100, 1e100)

@dataclass(frozen=True)
class CheckedRotations:
    """Rotation matrices as a camera file or caller gives them, checked and repaired where rounding explains.

    Attributes
    ----------
    rotations : (V, 3, 3) — the nearest rotation (SVD, U Vᵀ) where ``repaired``, else as given.
    deviations : (V,) — max |R Rᵀ - I| of each given matrix (NaN where not finite).
    reflections : (V,) bool — orthonormal to rounding but det R < 0: a reflection, not a rotation.
    repaired : (V,) bool — off by more than ``ROTATION_EXACT`` and at most ``ROTATION_ROUNDED``.
    """

    rotations: np.ndarray
    deviations: np.ndarray
    reflections: np.ndarray
    repaired: np.ndarray

    @property
    def not_rotations(self) -> np.ndarray:
        """(V,) bool — too far from orthonormal for rounding (or not finite)."""
        return ~(self.deviations <= ROTATION_ROUNDED)

    def warning(self) -> str | None:
        """The one line that says how far the repaired rotations were off; None when none was."""
        n = int(self.repaired.sum())
        if not n:
            return None
        return (f"{n} of {len(self.repaired)} rotation(s) orthonormal only to {self.deviations[self.repaired].max():.2g} "
                f"(largest |R Rᵀ - I|); replaced by the nearest rotation(s) (SVD)")


def check_rotations(rotations: object) -> CheckedRotations:
    """Check (V, 3, 3) matrices for being rotations; repair those off by rounding only.

    Examples
    --------
    >>> R = np.round(np.array([[0.6, -0.8, 0.0], [0.8, 0.6, 0.0], [0.0, 0.0, 1.0]]) * (1 + 1e-6), 9)
    >>> checked = check_rotations(np.stack([R, np.diag([1.0, 1.0, -1.0]), 2 * np.eye(3)]))
    >>> checked.repaired.tolist(), checked.reflections.tolist(), checked.not_rotations.tolist()
    ([True, False, False], [False, True, False], [False, False, True])
    >>> float(np.abs(checked.rotations[0] @ checked.rotations[0].T - np.eye(3)).max()) < 1e-15
    True
    """
    R = np.array(rotations, dtype=np.float64).reshape(-1, 3, 3)
    with np.errstate(all="ignore"):
        off = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
        finite = np.isfinite(off)
        off[~finite] = np.nan
        repaired = finite & (off > ROTATION_EXACT) & (off <= ROTATION_ROUNDED)
        if repaired.any():
            U, _, Vt = np.linalg.svd(R[repaired])
            R[repaired] = U @ Vt
        reflections = finite & (off <= ROTATION_ROUNDED) & (np.linalg.det(np.where(finite[:, None, None], R, 0.0)) < 0)
    return CheckedRotations(R, off, reflections, repaired & ~reflections)


def intrinsics_problem(intrinsics: object) -> tuple[int, str] | None:
    """The first camera whose K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] is not a camera's, and why; None if all are.

    Checked: finite; fx, fy > 0; fx, fy, |cx|, |cy| at most ``MAX_INTRINSIC_PX``; |skew| at most
    the larger focal length; fy / fx within ``MAX_ASPECT_RATIO`` either way.  K is taken up to scale
    (divided by K[2, 2]).

    Examples
    --------
    >>> good, skewed = np.diag([800.0, 800.0, 1.0]), np.array([[800.0, 1e6, 320.0], [0, 800.0, 240.0], [0, 0, 1]])
    >>> intrinsics_problem([good, skewed])
    (1, 'skew 1e+06 px is larger than the focal length 800 px (pixel axes under 45° apart)')
    >>> intrinsics_problem(np.diag([800.0, 800.0, 1.0])) is None
    True
    """
    K = np.array(intrinsics, dtype=np.float64).reshape(-1, 3, 3)
    with np.errstate(all="ignore"):
        K = K / K[:, 2:3, 2:3]
        fx, fy, cx, cy, skew = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 0, 1]
        tests = [
            (~np.isfinite(K).all(axis=(1, 2)), lambda v: "K must be finite (and K[2, 2] nonzero)"),
            (~((fx > 0) & (fy > 0)), lambda v: f"fx and fy must be > 0 (pixels); got {fx[v]:g}, {fy[v]:g}"),
            (~((fx <= MAX_INTRINSIC_PX) & (fy <= MAX_INTRINSIC_PX)),
             lambda v: f"fx and fy must be at most {MAX_INTRINSIC_PX:g} px; got {fx[v]:g}, {fy[v]:g}"),
            (~((np.abs(cx) <= MAX_INTRINSIC_PX) & (np.abs(cy) <= MAX_INTRINSIC_PX)),
             lambda v: f"cx and cy must be within ±{MAX_INTRINSIC_PX:g} px; got {cx[v]:g}, {cy[v]:g}"),
            (~(np.abs(skew) <= np.maximum(fx, fy)),
             lambda v: f"skew {skew[v]:g} px is larger than the focal length {max(fx[v], fy[v]):g} px "
                       f"(pixel axes under 45° apart)"),
            (~((fy / fx <= MAX_ASPECT_RATIO) & (fx / fy <= MAX_ASPECT_RATIO)),
             lambda v: f"fy / fx = {fy[v] / fx[v]:.3g}: pixels that far from square are not a camera's"),
        ]
    for bad, message in tests:
        if bad.any():
            v = int(np.argmax(bad))
            return v, message(v)
    return None


def projection_scale_problem(matrices: object) -> tuple[int, str] | None:
    """The first projection matrix whose largest entry lies outside ``PROJECTION_ENTRY_RANGE``, and why; None if none.

    An all-zero matrix is left to the invertibility check.  Entries are not pixels: a georeferenced
    camera's p14 of 1e8 is fine.

    Examples
    --------
    >>> projection_scale_problem(np.stack([np.eye(3, 4), np.eye(3, 4) * 1e300]))  # doctest: +ELLIPSIS
    (1, 'has entries up to 1e+300; a projection matrix is defined up to scale: divide it so that ...')
    """
    P = np.array(matrices, dtype=np.float64).reshape(-1, 3, 4)
    size = np.abs(P).max(axis=(1, 2))
    low, high = PROJECTION_ENTRY_RANGE
    out = (size > 0) & ~((size >= low) & (size <= high))
    if not out.any():
        return None
    v = int(np.argmax(out))
    return v, (f"has entries up to {size[v]:.2g}; a projection matrix is defined up to scale: divide it so that its "
               f"largest entry lies in {low:g} … {high:g}")
