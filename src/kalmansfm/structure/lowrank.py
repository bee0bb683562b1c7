"""Leading singular subspace of a tall-and-wide matrix, fast and to machine precision.

The factorization method needs only the rank-3 part of the centred
measurement matrix W (2F × P).  For small W a full LAPACK SVD is the simplest
exact answer; for large W (thousands of frames, 10⁵ points) the full SVD
takes minutes, while the rank-3 part can be had from a handful of passes over
W:

1. randomized range finder: Y = W Ω with a Gaussian Ω (P × ℓ, ℓ = rank +
   oversampling), Q = orth(Y);
2. Rayleigh–Ritz: Z = Wᵀ Q = V Σ Uᵦᵀ (a thin SVD of an P × ℓ matrix), so
   that U = Q Uᵦ, Σ and V are the Ritz triplets of W in span(Q);
3. certificate: one more product Y = W V gives the residual
   R = W Vₖ − Uₖ Σₖ of the leading k triplets (the right-hand residual
   Wᵀ Uₖ − Vₖ Σₖ is zero by construction), and Wedin's theorem bounds the
   angle between span(Uₖ) and the exact leading subspace by
   ‖R‖_F / (σₖ − σₖ₊₁).  If the bound is above ``tol``, Y is the next power
   iterate (Q = orth(Y)) and steps 2–3 repeat.

Every step is a product of W (or Wᵀ) with a thin ℓ-column matrix, so the
cost is a few memory-bound passes over W.  A per-row offset (the frame
centroids) is subtracted implicitly, so the centred matrix is never formed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError

__all__ = ["TruncatedSVD", "truncated_svd", "subspace_angle"]


@dataclass(frozen=True)
class TruncatedSVD:
    """The leading ``rank`` singular triplets of a matrix, W ≈ U diag(s) Vᵀ.

    Attributes
    ----------
    u : (m, rank) orthonormal columns.
    s : (rank,) singular values, descending.
    vt : (rank, n) orthonormal rows.
    extra_singular_values : the Ritz estimates of the next singular values
        (σ_{rank+1}, …) seen by the sketch (exact when ``method == "lapack"``).
    method : ``"lapack"`` (full SVD) or ``"randomized"``.
    passes : number of products with W or Wᵀ (0 for LAPACK).
    angle_bound : upper bound (radians, Wedin) on the largest principal angle between
        ``u`` and the exact leading subspace; 0 for LAPACK.
    """

    u: np.ndarray
    s: np.ndarray
    vt: np.ndarray
    extra_singular_values: np.ndarray
    method: str
    passes: int
    angle_bound: float


def subspace_angle(a: np.ndarray, b: np.ndarray) -> float:
    """Largest principal angle (radians) between the column spans of ``a`` and ``b``.

    Computed as arcsin of ‖(I − P_a) Q_b‖₂, which stays accurate for tiny angles
    (an arccos of the cosines cannot resolve angles below ~1e-8).

    Examples
    --------
    >>> a = np.eye(3)[:, :2]
    >>> b = np.array([[1.0, 0.0], [0.0, np.cos(0.1)], [0.0, np.sin(0.1)]])
    >>> round(subspace_angle(a, b), 12)
    0.1
    """
    qa, _ = np.linalg.qr(np.asarray(a, dtype=np.float64))
    qb, _ = np.linalg.qr(np.asarray(b, dtype=np.float64))
    rest = qb - qa @ (qa.T @ qb)
    return float(np.arcsin(min(1.0, np.linalg.norm(rest, 2))))


def truncated_svd(
    matrix: np.ndarray,
    rank: int = 3,
    *,
    row_offsets: np.ndarray | None = None,
    oversampling: int = 5,
    tol: float = 1e-10,
    max_passes: int = 21,
    method: str = "auto",
    rng: np.random.Generator | int | None = 0,
) -> TruncatedSVD:
    """Leading ``rank`` singular triplets of ``matrix - row_offsets[:, None]``.

    Parameters
    ----------
    matrix : (m, n) float array.
    rank : number of singular triplets wanted.
    row_offsets : (m,) subtracted from every column without forming the difference
        (e.g. the frame centroids of a measurement matrix).
    oversampling : extra sketch columns beyond ``rank`` (randomized method).
    tol : stop when the bound on the largest principal angle to the exact leading
        subspace is below ``tol`` radians (randomized method).
    max_passes : at most this many products with the matrix (randomized method).
    method : ``"lapack"``, ``"randomized"``, or ``"auto"`` (LAPACK when
        min(m, n) ≤ 300 or m·n ≤ 2·10⁶).
    rng : seed or generator for the Gaussian test matrix.

    Returns
    -------
    TruncatedSVD

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> w = rng.standard_normal((200, 3)) @ rng.standard_normal((3, 5000))
    >>> fast = truncated_svd(w, 3, method="randomized")
    >>> exact = np.linalg.svd(w, full_matrices=False)
    >>> bool(np.allclose(fast.s, exact.S[:3])), subspace_angle(fast.u, exact.U[:, :3]) < 1e-12
    (True, True)
    """
    w = np.asarray(matrix)
    if w.ndim != 2 or not np.issubdtype(w.dtype, np.floating):
        raise InvalidInputError(f"matrix must be a 2-D float array; got shape {w.shape}, dtype {w.dtype}")
    m, n = w.shape
    if not 1 <= rank <= min(m, n):
        raise InvalidInputError(f"rank must be between 1 and min(m, n) = {min(m, n)}; got {rank}")
    offsets = np.zeros(m) if row_offsets is None else np.asarray(row_offsets, dtype=np.float64)
    if offsets.shape != (m,):
        raise InvalidInputError(f"row_offsets must have shape ({m},); got {offsets.shape}")
    if method == "auto":
        method = "lapack" if min(m, n) <= 300 or m * n <= 2_000_000 else "randomized"
    if method == "lapack":
        u, s, vt = np.linalg.svd(w - offsets[:, None], full_matrices=False)
        return TruncatedSVD(u[:, :rank], s[:rank], vt[:rank], s[rank:], "lapack", 0, 0.0)
    if method != "randomized":
        raise InvalidInputError(f"method must be 'auto', 'lapack' or 'randomized'; got {method!r}")
    return _randomized(w, offsets, rank, oversampling, tol, max_passes, np.random.default_rng(rng))


def _randomized(
    w: np.ndarray, offsets: np.ndarray, k: int, oversampling: int, tol: float, max_passes: int, rng: np.random.Generator
) -> TruncatedSVD:
    m, n = w.shape
    width = min(k + max(oversampling, 0), m, n)
    dtype = np.result_type(w.dtype, np.float64)

    # (W - c 1ᵀ) X = W X - c (1ᵀ X)
    def times(x: np.ndarray) -> np.ndarray:
        return w @ x - np.outer(offsets, x.sum(axis=0))

    # (W - c 1ᵀ)ᵀ Y = Wᵀ Y - 1 (cᵀ Y)
    def times_transposed(y: np.ndarray) -> np.ndarray:
        return w.T @ y - (offsets @ y)[None, :]

    y = times(rng.standard_normal((n, width)).astype(dtype, copy=False))
    passes = 1
    while True:
        q, _ = np.linalg.qr(y)
        z = times_transposed(q)  # = (Qᵀ W)ᵀ
        passes += 1
        # Rayleigh–Ritz on span(Q): Qᵀ W = Uᵦ Σ Vᵀ with V = Q_z V_s from Z = Q_z R_z
        qz, rz = np.linalg.qr(z)
        ub, s, vst = np.linalg.svd(rz.T)
        u = q @ ub
        v = qz @ vst.T
        y = times(v)  # W V: the certificate, and the next power iterate
        passes += 1
        # Wedin: sin θ ≤ ‖W Vₖ − Uₖ Σₖ‖_F / (σₖ − σₖ₊₁), the right residual being zero
        residual = np.linalg.norm(y[:, :k] - u[:, :k] * s[:k])
        next_sigma = s[k] if width > k else 0.0
        gap = s[k - 1] - next_sigma - residual
        bound = float(np.inf) if gap <= 0 else min(np.pi / 2, residual / gap)
        if bound <= tol or passes + 2 > max_passes:
            break
    return TruncatedSVD(u[:, :k], s[:k], v[:, :k].T, s[k:], "randomized", passes, bound)
