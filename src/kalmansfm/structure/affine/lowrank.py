"""Leading singular subspace of a tall-and-wide matrix, fast and to machine precision.

The factorization method needs only the rank-3 part of the centred
measurement matrix W (2F × P).  For small W a full LAPACK SVD is the simplest
exact answer; for large W (thousands of frames, 10⁵ points) the full SVD
takes minutes, while the rank-k part can be had from a handful of products
of W with thin blocks of ℓ = k + oversampling columns:

1. start: ℓ rows of W drawn with probability proportional to their squared
   norm (length-squared sampling).  They are W'ᵀ e_rows, so this first
   right-side block costs no product at all, and it already lies close to the
   leading right subspace when the rows carry a strong rank-k signal;
2. Y = W Z gives the first left block U = orth(Y);
3. subspace iteration on the Gram matrix A = W Wᵀ, with Rayleigh–Ritz on
   every round trip: Z = Wᵀ U, the SVD of Zᵀ gives the Ritz triplets of W on
   span(U) (exact on that side: Wᵀ u = σ v), and Y = W Z = A U gives at once
   * their residual R = A Uₖ − Uₖ Σₖ², hence the Davis–Kahan bound
     sin θ ≤ ‖R‖₂ / (σₖ² − σₖ₊₁²) on the largest principal angle between
     the returned left subspace and the exact one;
   * the next block U = orth(Y), closer by a factor (σₖ₊₁ / σₖ)²;
4. stop when the bound is below ``tol``.

The gap needs an upper bound on σₖ₊₁; σₖ₊₁² ≤ ‖W‖_F² − Σᵢ≤ₖ σ̂ᵢ² holds
because Ritz values never exceed the exact ones, so the bound is rigorous
whenever that is smaller than σ̂ₖ² (a strong rank-k signal, the usual case for
a measurement matrix).  Otherwise the Ritz estimate of σₖ₊₁ is used and the
result says the bound is only an estimate (``certified`` is False).

A per-row offset (the frame centroids) is subtracted implicitly, so the centred
matrix is never formed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import InvalidInputError

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
    passes : number of products of W or Wᵀ with a thin block (0 for LAPACK).
    angle_bound : bound (radians) on the largest principal angle between the span of
        ``u`` and the exact leading left singular subspace (Davis–Kahan, from the
        residual of the returned triplets). 0 for LAPACK.
    certified : True when ``angle_bound`` is a rigorous bound (the gap used an upper
        bound of σ_{rank+1}); False when it had to use the Ritz estimate of σ_{rank+1}.
    """

    u: np.ndarray
    s: np.ndarray
    vt: np.ndarray
    extra_singular_values: np.ndarray
    method: str
    passes: int
    angle_bound: float
    certified: bool = True


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
    oversampling: int = 1,
    tol: float = 1e-9,
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
    oversampling : extra block columns beyond ``rank`` (randomized method). The
        convergence factor per round trip is (σ_{rank+oversampling+1} / σ_rank)²; a
        measurement matrix has a flat noise tail, where more columns only cost time.
    tol : stop when the bound on the largest principal angle to the exact leading
        subspace is below ``tol`` radians (randomized method).
    max_passes : at most this many products with the matrix (randomized method; each
        round trip is two).
    method : ``"lapack"``, ``"randomized"``, or ``"auto"`` (LAPACK when
        min(m, n) ≤ 300 or m·n ≤ 2·10⁶).
    rng : seed or generator for the choice of starting rows.

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
    centred = bool(np.any(offsets))

    # (W - c 1ᵀ) X = W X - c (1ᵀ X), for X = Zᵀ given as the (ℓ, n) block Z
    def times(zt: np.ndarray) -> np.ndarray:
        y = w @ zt.T
        return y - np.outer(offsets, zt.sum(axis=1)) if centred else y

    # Uᵀ (W - c 1ᵀ) = Uᵀ W - (Uᵀ c) 1ᵀ, an (ℓ, n) block (the faster GEMM orientation)
    def transposed_times(u: np.ndarray) -> np.ndarray:
        zt = u.T @ w
        if centred:
            zt -= (offsets @ u)[:, None]
        return zt

    row_norms = _centred_row_norms(w, offsets)
    frobenius = float(row_norms.sum())
    if frobenius == 0.0:
        zeros = np.zeros(k)
        return TruncatedSVD(np.eye(m, k), zeros, np.eye(k, n), np.zeros(width - k), "randomized", 0, 0.0)
    # Length-squared sampling of the starting rows (a pinch of uniform keeps every row possible).
    probability = row_norms + 1e-3 * frobenius / m
    rows = np.sort(rng.choice(m, size=width, replace=False, p=probability / probability.sum()))
    zt = w[rows] - offsets[rows, None]  # = (W - c 1ᵀ)ᵀ e_rows, no product needed
    u, _ = np.linalg.qr(times(zt))
    passes = 1
    while True:
        zt = transposed_times(u)  # Z = Wᵀ U
        y = times(zt)  # Y = W Z = A U with A = W Wᵀ
        passes += 2
        ritz = ritz_certificate(zt, y, u, k, frobenius)
        if ritz.bound <= tol or ritz.undetermined or passes + 2 > max_passes:
            break
        u, _ = np.linalg.qr(y)
    # The returned triplets from the SVD of Zᵀ = Uᵀ W = G Σ Bᵀ (no squaring): Wᵀ (U G) = B Σ.
    s = ritz.singular_values
    return TruncatedSVD(u @ ritz.vectors[:, :k], s[:k], ritz.right[:k], s[k:], "randomized", passes,
                        ritz.bound, ritz.certified)


@dataclass(frozen=True)
class RitzCertificate:
    """Rayleigh–Ritz pairs of A = W Wᵀ on span(U) and the Davis–Kahan bound of their k leading ones.

    singular_values : (ℓ,) Ritz estimates σ̂ᵢ of the singular values (descending; σ̂ᵢ² are the Ritz
    values of A); vectors : (ℓ, ℓ) their coordinates G in the basis U; right : (ℓ, n) Bᵀ, with
    Uᵀ W = G diag(σ̂) Bᵀ; bound : bound (radians) on the largest principal angle between span(U Gₖ)
    and the exact leading k-dimensional left subspace; certified : the gap used a rigorous upper
    bound of σₖ₊₁²; undetermined : σₖ at rounding level (no direction to find).
    """

    singular_values: np.ndarray
    vectors: np.ndarray
    right: np.ndarray
    bound: float
    certified: bool
    undetermined: bool


def ritz_certificate(
    zt: np.ndarray,
    y: np.ndarray,
    u: np.ndarray | None,
    k: int,
    frobenius: float,
    *,
    upper_next: float | None = None,
    fallback_next: float = 0.0,
) -> RitzCertificate:
    """Rayleigh–Ritz on span(U) from Zᵀ = Uᵀ W (ℓ, n) and the Davis–Kahan bound.

    ``y`` is A U (then ``u`` is U), or, with ``u`` None, already the residual A U − U (Uᵀ A U).
    σₖ₊₁² is bounded by ``upper_next`` when given (e.g. ‖W − U Uᵀ W‖²_F), else by
    ‖W‖²_F − Σᵢ≤ₖ λᵢ (Ritz values never exceed the exact ones); when that bound is not below
    λₖ, the Ritz estimate λₖ₊₁ (or ``fallback_next`` if ℓ = k) is used and the bound is only an
    estimate.
    """
    # Zᵀ = Uᵀ W = G Σ Bᵀ, so Uᵀ A U = G Σ² Gᵀ: Ritz values λ = σ², vectors U G. (The SVD of Zᵀ,
    # not the eigen-decomposition of Zᵀ Z, resolves a σ far below σ₁: no squaring.)
    g, s, bt = np.linalg.svd(zt, full_matrices=False)
    lam = s**2
    # Davis–Kahan residual of the leading Ritz pairs of A: R = A U G - U G Λ
    if u is None:
        residual = np.linalg.norm(y @ g[:, :k], 2)
    else:
        residual = np.linalg.norm(y @ g[:, :k] - (u @ g[:, :k]) * lam[:k], 2)
    # σₖ₊₁² ≤ ‖W‖_F² − Σᵢ≤ₖ σ̂ᵢ² (Ritz values are lower bounds), with room for rounding
    upper = frobenius - lam[:k].sum() if upper_next is None else upper_next
    upper += 1e-12 * frobenius
    certified = bool(upper < lam[k - 1])
    next_value = upper if certified else (lam[k] if lam.size > k else fallback_next)
    gap = lam[k - 1] - next_value
    bound = float(np.pi / 2) if gap <= 0 else float(np.arcsin(min(1.0, residual / gap)))
    # σₖ at rounding level: the k-th direction is not determined by the matrix; iterating cannot help.
    undetermined = bool(lam[k - 1] <= (64 * np.finfo(float).eps) ** 2 * lam[0])
    return RitzCertificate(s, g, bt, bound, certified, undetermined)


def _centred_row_norms(w: np.ndarray, offsets: np.ndarray, block_rows: int = 16) -> np.ndarray:
    """Squared norms of the rows of W − c 1ᵀ, a block of rows at a time (no full-size temporary)."""
    if not np.any(offsets):
        return np.einsum("ij,ij->i", w, w)
    out = np.empty(w.shape[0])
    for start in range(0, w.shape[0], block_rows):
        block = w[start : start + block_rows] - offsets[start : start + block_rows, None]
        out[start : start + block_rows] = np.einsum("ij,ij->i", block, block)
    return out
