"""How well each point of an affine (Tomasi–Kanade) reconstruction is known, and which ones to trust.

Model (as in :mod:`~kalmansfm.structure.affine.factorization`): x_fp = M_f S_p + t_f + e_fp, with
e_fp zero-mean noise of covariance σ² W_fp⁻¹ (W_fp = diag of the factorization's weights;
the identity without weights).  Taking the recovered motion (M_f, t_f) as exact, the
weighted least-squares point S_p from the frames f that observed it has the covariance

    Σ_p = σ̂² (Σ_f M_fᵀ W_fp M_f)⁻¹,

a 3 × 3 matrix per point in the gauge of the reconstruction (frame 0's camera rows are the
X and Y axes; the shape is centred).  The variance of unit weight comes from the residuals
r_fp = M_f S_p + t_f − x_fp of the fit with the degrees of freedom counted:

    σ̂² = Σ_fp r_fpᵀ W_fp r_fp / (n − k),   k = 3 P + 8 F − 12,

n the observed coordinates, P and F the reconstructed points and frames (three
coordinates per point; two camera rows and a translation per frame; minus the 12 of the
affine ambiguity).  Without weights σ̂ is the image noise in pixels; with the tracker's
1 / σ² weights it is the factor by which those σ are too small (1 when they are right).

A point's depth is fixed only by the rotation between the frames that saw it: seen in two
frames a degree apart, its Z has a standard deviation of about σ / sin 1° ≈ 57 σ.  A point
is marked *unreliable* (:class:`~.points.PointStatus`) when it was seen in fewer than ``min_views``
(4) frames, or when the longest axis of its 1σ ellipsoid exceeds ``max_std_ratio`` (0.25)
times the radius of the shape (the median distance of the well-seen points from their
median; the covariances and the shape share the gauge, so a depth scale stretched by a
weak metric upgrade stretches both).  A point the factorization left out (NaN) is
*too_few_views* when fewer than 2 of the reconstructed frames saw it and *degenerate*
otherwise (it is not linked to the reconstructed frames).

What Σ_p leaves out:

- the uncertainty of the motion itself (M_f, t_f are estimated from the same tracks; their
  error moves every point of a frame together and is not in Σ_p) and of the metric upgrade;
  it is small when every frame sees many points, as on tracked video;
- correlations between points (each Σ_p is a marginal in a fixed gauge; the gauge's own
  freedom — rotation, and the centring — is not in it);
- model error beyond what the residuals show: perspective, tracker drift that moves with the
  scene, outliers (they inflate σ̂ for every point rather than their own).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..._validation import as_float_array
from ...errors import InvalidInputError
from . import factorization
from .factorization import AffineFactors
from ..points import PointStatus

__all__ = ["GAUGE_PARAMETERS", "MAX_STD_RATIO", "MIN_VIEWS", "PointUncertainty", "judge_points", "point_uncertainty"]

#: A point seen in fewer frames than this is unreliable: from 3 frames (6 numbers for its 3 coordinates)
#: one bad match is not noticed, and a tracker's new track spends its first 2 frames starting.
MIN_VIEWS = 4
#: A point whose largest 1σ axis exceeds this fraction of the shape's radius is unreliable.
MAX_STD_RATIO = 0.25
#: The affine ambiguity of factorization: an invertible 3 × 3 map and a 3D shift.
GAUGE_PARAMETERS = 12


@dataclass(frozen=True)
class PointUncertainty:
    """The covariance of every reconstructed point and the verdict on it.

    Attributes
    ----------
    covariances : (P, 3, 3) float — Σ_p in the reconstruction's gauge, pixels²; NaN for a
        point that was not reconstructed or when σ̂ cannot be estimated.
    views : (P,) int — frames in which the point was observed (and used by the fit).
    status : (P,) int8 — :class:`~.points.PointStatus` codes: ``OK`` or ``UNRELIABLE`` for a
        reconstructed point, ``TOO_FEW_VIEWS`` or ``DEGENERATE`` for one left out.
    reprojection_rms : (P,) float — RMS length of the point's rank-3 residuals
        |M_f S_p + t_f − x_fp| over the frames that saw it, pixels (NaN where none).
    noise_std : float — σ̂, the standard deviation of unit weight (pixels without weights).
    dof : int — the degrees of freedom n − k behind σ̂.
    radius_px : float — the shape's radius that the bound is relative to.
    min_views, max_std_ratio : the bound applied.
    depth_determined : False when the factorization found the depth not determined (see
        :class:`~.factorization.AffineFactors`): then no point is ``ok``.
    """

    covariances: np.ndarray
    views: np.ndarray
    status: np.ndarray
    reprojection_rms: np.ndarray
    noise_std: float
    dof: int
    radius_px: float
    min_views: int = MIN_VIEWS
    max_std_ratio: float = MAX_STD_RATIO
    depth_determined: bool = True

    @property
    def largest_std(self) -> np.ndarray:
        """(P,) the longest semi-axis of each point's 1σ ellipsoid, pixels (NaN where unknown)."""
        finite = np.isfinite(self.covariances).all(axis=(1, 2))
        out = np.full(len(self.views), np.nan)
        if finite.any():
            out[finite] = np.sqrt(np.clip(np.linalg.eigvalsh(self.covariances[finite])[:, -1], 0.0, None))
        return out

    @property
    def reliable(self) -> np.ndarray:
        """(P,) True for the points with status OK."""
        return self.status == PointStatus.OK

    @property
    def bound_px(self) -> float:
        """The largest 1σ axis a reliable point may have, pixels."""
        return self.max_std_ratio * self.radius_px

    @property
    def warnings(self) -> tuple[str, ...]:
        """One line on the unreliable points among the reconstructed ones (none when there are none)."""
        reconstructed = self.views >= 2  # a point is reconstructed only from two frames on
        bad = reconstructed & ~self.reliable
        if not self.depth_determined and reconstructed.any():
            return (f"depth is not determined (see the factorization's warning): all {int(reconstructed.sum())} "
                    "reconstructed points are marked 'unreliable' — their covariances take the motion as exact and "
                    "cannot show it",)
        if not bad.any():
            return ()
        few = int((bad & (self.views < self.min_views)).sum())
        reasons = []
        if few:
            reasons.append(f"{few} seen in fewer than {self.min_views} frames")
        if bad.sum() > few:
            reasons.append(
                f"{int(bad.sum()) - few} with a 1σ uncertainty above {self.bound_px:.3g} px = "
                f"{self.max_std_ratio:g} × the shape's radius"
            )
        return (
            f"{int(bad.sum())} of {int(reconstructed.sum())} reconstructed points are unreliable "
            f"({'; '.join(reasons)}): marked 'unreliable' in structure.csv and left out of the plots",
        )


def point_uncertainty(
    reconstruction: AffineFactors,
    positions: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    min_views: int = MIN_VIEWS,
    max_std_ratio: float = MAX_STD_RATIO,
) -> PointUncertainty:
    """Covariance of each point of an affine reconstruction, given its motion, and which points to trust.

    Parameters
    ----------
    reconstruction : the result of :func:`~kalmansfm.structure.affine.factorization.factor_affine` on ``positions``.
    positions : (F, P, 2) float — the observations that were factorized (NaN where none).
    weights : (F, P) or (F, P, 2) float, optional — the weights given to
        :func:`~kalmansfm.structure.factorize`, if any.
    min_views : a point seen in fewer frames is unreliable.
    max_std_ratio : a point whose largest 1σ axis exceeds this fraction of the shape's radius
        is unreliable.

    Returns
    -------
    PointUncertainty

    Notes
    -----
    See the module notes for the model, the degrees of freedom and what the covariance
    leaves out (the motion's own uncertainty).

    Raises
    ------
    InvalidInputError
        ``positions`` or ``weights`` not of the reconstruction's shape, negative weights, or
        a bound that is not positive.

    Examples
    --------
    >>> from kalmansfm.structure import PointStatus
    >>> from kalmansfm.structure.affine.factorization import factor_affine
    >>> rng = np.random.default_rng(0)
    >>> shape = rng.normal(size=(30, 3)) * 50
    >>> rotations = [np.linalg.qr(rng.normal(size=(3, 3)))[0][:2] for _ in range(8)]
    >>> tracks = np.stack([shape @ m.T + 200 for m in rotations]) + rng.normal(scale=0.5, size=(8, 30, 2))
    >>> tracks[2:, 0] = np.nan                      # point 0 is seen in frames 0 and 1 only
    >>> rec = factor_affine(tracks)
    >>> u = point_uncertainty(rec, tracks)
    >>> round(u.noise_std, 1), u.views[:3].tolist(), [PointStatus(s).label for s in u.status[:3]]
    (0.5, [2, 8, 8], ['unreliable', 'ok', 'ok'])
    >>> bool(0.3 < u.reprojection_rms[1] < 1.0)
    True
    >>> u.warnings
    ("1 of 30 reconstructed points are unreliable (1 seen in fewer than 4 frames): marked 'unreliable' in \
structure.csv and left out of the plots",)
    >>> bool(u.largest_std[1] < 1.0)
    True
    """
    motion = np.asarray(reconstruction.motion)
    frames, n_points = reconstruction.observed.shape
    if np.shape(positions) != (frames, n_points, 2):
        raise InvalidInputError(f"positions must have the reconstruction's shape ({frames}, {n_points}, 2); got "
                                f"{np.shape(positions)}")
    if not (isinstance(min_views, (int, np.integer)) and min_views >= 2):
        raise InvalidInputError(f"min_views must be an integer >= 2; got {min_views!r}")
    if not (np.isfinite(max_std_ratio) and max_std_ratio > 0):
        raise InvalidInputError(f"max_std_ratio must be a finite number > 0; got {max_std_ratio!r}")
    frame_ok = np.isfinite(motion).all(axis=(1, 2)) & np.isfinite(reconstruction.translation).all(axis=1)
    point_ok = np.isfinite(reconstruction.points).all(axis=1)
    # the inputs the factorization streamed (complete, unweighted, 2F·P beyond its LAPACK limit)
    if (weights is None and 2 * frames * n_points > factorization._LAPACK_LIMIT and frame_ok.all()
            and point_ok.all() and np.all(reconstruction.observed)):
        return _complete_unweighted(reconstruction, min_views, max_std_ratio)
    x = as_float_array("positions", positions)
    w = _weights(weights, frames, n_points)
    used = reconstruction.observed & frame_ok[:, None] & point_ok[None, :]
    w = np.where(used[:, :, None], w, 0.0)
    views = used.sum(axis=0).astype(np.int64)

    # σ̂² = Σ rᵀ W r / (n − k), k = 3P + 8F − 12
    residual = np.where(used[:, :, None], reconstruction.reprojected() - np.where(used[:, :, None], x, 0.0), 0.0)
    chi_square = float(np.sum(w * residual**2))
    # each point's RMS residual length over the frames that saw it
    reprojection_rms = np.where(views > 0, np.sqrt(np.sum(residual**2, axis=(0, 2)) / np.maximum(views, 1)), np.nan)
    observed_coordinates = int(np.count_nonzero(w))
    parameters = 3 * int(point_ok.sum()) + 8 * int(frame_ok.sum()) - GAUGE_PARAMETERS
    dof = observed_coordinates - parameters
    noise_var = chi_square / dof if dof > 0 else np.nan

    # Σ_f M_fᵀ W_fp M_f for every point at once: (P, 2F) weights times the (2F, 9) outer products of the rows.
    rows = np.where(frame_ok[:, None, None], motion, 0.0).reshape(-1, 3)
    outer = (rows[:, :, None] * rows[:, None, :]).reshape(-1, 9)
    normal = (w.transpose(1, 0, 2).reshape(n_points, -1) @ outer).reshape(n_points, 3, 3)
    covariances = np.full((n_points, 3, 3), np.nan)
    solvable = point_ok & (views >= 2) & np.isfinite(noise_var)
    if solvable.any():
        eigenvalues, eigenvectors = np.linalg.eigh(normal[solvable])
        # a direction no frame constrains gets a huge but finite variance
        floor = np.maximum(eigenvalues[:, -1:], np.finfo(float).tiny) * 1e-15
        inverse = (eigenvectors / np.maximum(eigenvalues, floor)[:, None, :]) @ eigenvectors.transpose(0, 2, 1)
        covariances[solvable] = noise_var * inverse

    seen = None if point_ok.all() else (reconstruction.observed & frame_ok[:, None]).sum(axis=0)
    return judge_points(reconstruction.points, covariances, views, seen, reprojection_rms, noise_var, dof, point_ok,
                        min_views=min_views, max_std_ratio=max_std_ratio,
                        depth_determined=bool(getattr(reconstruction, "depth_determined", True)))


def _complete_unweighted(reconstruction: AffineFactors, min_views: int, max_std_ratio: float) -> PointUncertainty:
    """Every frame saw every point, no weights: one normal matrix for all points, σ̂ from the residual lengths.

    Reads the (F, P) residuals once and makes no (F, P, 2) temporary: the large complete inputs
    that take this path would otherwise need several arrays the size of the input.
    """
    motion = np.asarray(reconstruction.motion)
    frames, n_points = reconstruction.observed.shape
    squared_per_point = reconstruction.point_residual_sums
    views = np.full(n_points, frames, dtype=np.int64)
    reprojection_rms = np.sqrt(squared_per_point / frames)
    dof = 2 * frames * n_points - (3 * n_points + 8 * frames - GAUGE_PARAMETERS)
    noise_var = float(squared_per_point.sum()) / dof if dof > 0 else np.nan
    rows = motion.reshape(-1, 3)
    normal = rows.T @ rows
    covariances = np.full((n_points, 3, 3), np.nan)
    if np.isfinite(noise_var) and frames >= 2:
        eigenvalues, eigenvectors = np.linalg.eigh(normal)
        floor = max(eigenvalues[-1], np.finfo(float).tiny) * 1e-15
        covariances[:] = noise_var * (eigenvectors / np.maximum(eigenvalues, floor)) @ eigenvectors.T
    everything = np.ones(n_points, dtype=bool)
    return judge_points(reconstruction.points, covariances, views, None, reprojection_rms, noise_var, dof, everything,
                        min_views=min_views, max_std_ratio=max_std_ratio,
                        depth_determined=bool(getattr(reconstruction, "depth_determined", True)))


def judge_points(points: np.ndarray, covariances: np.ndarray, views: np.ndarray, seen: np.ndarray | None,
                 reprojection_rms: np.ndarray, noise_var: float, dof: int, point_ok: np.ndarray, *,
                 min_views: int = MIN_VIEWS, max_std_ratio: float = MAX_STD_RATIO,
                 depth_determined: bool = True) -> PointUncertainty:
    """The status of every point from its views and covariance, relative to the shape's radius.

    ``points`` (P, 3) the shape (NaN where left out, ``point_ok`` False); ``views`` the frames
    that each point's estimate used; ``seen`` (P,) the reconstructed frames that observed each
    point (needed only when some point was left out, to tell ``too_few_views`` from ``degenerate``).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> points = rng.normal(size=(6, 3)) * 10
    >>> cov = np.broadcast_to(np.eye(3) * 0.01, (6, 3, 3)).copy()
    >>> u = judge_points(points, cov, np.array([5, 5, 5, 5, 5, 3]), None, np.full(6, 0.5), 0.25, 40, np.ones(6, bool))
    >>> [PointStatus(s).label for s in u.status]
    ['ok', 'ok', 'ok', 'ok', 'ok', 'unreliable']
    """
    well_seen = point_ok & (views >= min_views)
    reference = points[well_seen] if well_seen.sum() >= 4 else points[point_ok]
    radius = float(np.median(np.linalg.norm(reference - np.median(reference, axis=0), axis=1))) if len(reference) else np.nan
    status = np.full(len(views), PointStatus.UNRELIABLE, dtype=np.int8)
    if not point_ok.all():
        # a point left out: too few of the reconstructed frames saw it, or it is not linked to them
        assert seen is not None
        status[:] = np.where(point_ok, PointStatus.UNRELIABLE,
                             np.where(seen < 2, PointStatus.TOO_FEW_VIEWS, PointStatus.DEGENERATE))
    uncertainty = PointUncertainty(covariances, views, status, reprojection_rms, float(np.sqrt(noise_var)), int(dof),
                                   radius, int(min_views), float(max_std_ratio), bool(depth_determined))
    with np.errstate(invalid="ignore"):
        ok = well_seen & np.isfinite(covariances).all(axis=(1, 2)) & (uncertainty.largest_std <= uncertainty.bound_px)
    if depth_determined:
        # the covariance takes the motion as exact: it cannot see a depth the factorization did not determine
        uncertainty.status[ok] = PointStatus.OK
    return uncertainty


def _weights(weights: object, frames: int, n_points: int) -> np.ndarray:
    """(F, P, 2) weights (ones without any), checked."""
    if weights is None:
        return np.ones((frames, n_points, 2))
    w = as_float_array("weights", weights)
    if w.shape == (frames, n_points):
        w = np.repeat(w[:, :, None], 2, axis=2)
    if w.shape != (frames, n_points, 2):
        raise InvalidInputError(f"weights must have shape ({frames}, {n_points}) or ({frames}, {n_points}, 2); got {w.shape}")
    w = np.where(np.isnan(w), 0.0, w)
    if not (np.isfinite(w).all() and (w >= 0).all()):
        raise InvalidInputError("weights must be finite and >= 0")
    return w
