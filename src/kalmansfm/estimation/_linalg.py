"""Small dense linear algebra over stacks of matrices, the arithmetic under the Kalman equations (internal).

:func:`~kalmansfm.estimation.kalman.kalman_predict`, :func:`~kalmansfm.estimation.kalman.kalman_update`
and the filter's engine (:mod:`.engine`) share it: symmetrising, products with one shared
matrix as a single GEMM over the stack, Cholesky factors and triangular solves written
elementwise for m <= 4 (LAPACK costs about a microsecond per tiny matrix), and the dense
gain and posterior of an update (:func:`gain_and_posterior`).
"""

from __future__ import annotations

import numpy as np

from ..errors import SingularCovarianceError

LOG_2PI = float(np.log(2.0 * np.pi))


def symmetrize(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def times_transposed(A: np.ndarray, M: np.ndarray) -> np.ndarray:
    """A Mᵀ for a stack A (..., p, q) and a shared M (r, q), as one GEMM over the stack.

    NumPy's stacked matmul handles a 4×4 product in ~80 ns; reshaping the stack into one
    (.. · p, q) matrix lets BLAS do it in ~17 ns.
    """
    if M.ndim == 2 and A.ndim > 2:
        A = np.ascontiguousarray(A)
        return (A.reshape(-1, A.shape[-1]) @ M.T).reshape(*A.shape[:-1], M.shape[0])
    return A @ np.swapaxes(M, -1, -2)


def cholesky_checked(S: np.ndarray, what: str) -> np.ndarray:
    """Lower Cholesky factor of every matrix in ``S`` (..., m, m).

    Small matrices (m <= 4) are factored with elementwise NumPy over the stack:
    ``np.linalg.cholesky`` calls LAPACK once per matrix, which costs about a
    microsecond each for a million 2x2 innovation covariances.
    """
    m = S.shape[-1]
    if m > 4:
        try:
            return np.linalg.cholesky(S)
        except np.linalg.LinAlgError:
            raise not_positive_definite(what) from None
    L = np.zeros_like(S)
    for j in range(m):
        # L_jj = sqrt(S_jj - sum_k<j L_jk^2)
        d = S[..., j, j] - np.sum(L[..., j, :j] ** 2, axis=-1)
        if not np.all(d > 0):
            raise not_positive_definite(what)
        L[..., j, j] = np.sqrt(d)
        for i in range(j + 1, m):
            # L_ij = (S_ij - sum_k<j L_ik L_jk) / L_jj
            L[..., i, j] = (S[..., i, j] - np.sum(L[..., i, :j] * L[..., j, :j], axis=-1)) / L[..., j, j]
    return L


def not_positive_definite(what: str) -> SingularCovarianceError:
    return SingularCovarianceError(
        f"{what} is not positive definite; check that R is positive definite and P has not collapsed"
    )


def solve_lower(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Solve L W = B for lower-triangular L (..., m, m) and B (..., m, k) by forward substitution."""
    m = L.shape[-1]
    if m > 4:
        return np.linalg.solve(L, B)
    W = np.empty(np.broadcast_shapes(L.shape[:-2], B.shape[:-2]) + B.shape[-2:], dtype=np.result_type(L, B))
    for i in range(m):
        # w_i = (b_i - sum_k<i L_ik w_k) / L_ii
        acc = B[..., i, :] - np.sum(L[..., i, :i, None] * W[..., :i, :], axis=-2)
        W[..., i, :] = acc / L[..., i, i, None]
    return W


def solve_upper_transposed(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Solve Lᵀ V = B for lower-triangular L (..., m, m) by back substitution."""
    m = L.shape[-1]
    if m > 4:
        return np.linalg.solve(np.swapaxes(L, -1, -2), B)
    V = np.empty(np.broadcast_shapes(L.shape[:-2], B.shape[:-2]) + B.shape[-2:], dtype=np.result_type(L, B))
    for i in reversed(range(m)):
        # v_i = (b_i - sum_k>i L_ki v_k) / L_ii
        acc = B[..., i, :] - np.sum(L[..., i + 1 :, i, None] * V[..., i + 1 :, :], axis=-2)
        V[..., i, :] = acc / L[..., i, i, None]
    return V


def mat_vec(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A v over the last axes; A (..., p, q), v (..., q)."""
    return np.matmul(A, v[..., None])[..., 0]


def gain_and_posterior(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    joseph: bool = True,
    measured_rows: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Dense update of filters that measured every component of ``z``.

    ``P``, ``H`` and ``R`` may be shared ((n, n), (m, n), (m, m)) or stacked
    ((k, n, n), (k, m, n), (k, m, m)); the outputs broadcast accordingly.
    ``measured_rows`` (k,) bool, if given, marks the filters that really measured:
    the others get a zero gain, so their posterior is exactly their prior, and
    NaN innovation statistics (their rows of ``z`` may hold anything finite).
    """
    stacked_P = P.ndim == 3
    if H.ndim == 2 and stacked_P:
        PHt = times_transposed(P, H)  # P Hᵀ (k, n, m)
        HP = np.ascontiguousarray(np.swapaxes(PHt, -1, -2))  # H P = (P Hᵀ)ᵀ, P symmetric
        HPHt = times_transposed(HP, H)
    else:
        HP = H @ P
        HPHt = HP @ np.swapaxes(H, -1, -2)
    S = symmetrize(HPHt + R)
    L = cholesky_checked(S, "the innovation covariance S = H P Hᵀ + R")
    # K = P Hᵀ S⁻¹ = (S⁻¹ H P)ᵀ with S⁻¹ = L⁻ᵀ L⁻¹ (S and P are symmetric).
    Kt = solve_upper_transposed(L, solve_lower(L, HP))
    if measured_rows is not None:
        Kt = Kt * measured_rows[:, None, None]
    K = np.swapaxes(Kt, -1, -2)
    y = z - (x @ H.T if H.ndim == 2 else mat_vec(H, x))
    # x = x⁻ + K y, written as a sum over the m components (cheaper than a stack of tiny matmuls)
    x_post = x + np.sum(K * y[..., None, :], axis=-1)
    if H.ndim == 2 and Kt.ndim == 3:
        KH = times_transposed(np.ascontiguousarray(K), H.T)
    else:
        KH = K @ H
    A = np.eye(P.shape[-1], dtype=P.dtype) - KH
    if joseph:
        # Joseph form: P = (I - KH) P (I - KH)ᵀ + K R Kᵀ, symmetric PSD even when K is not optimal.
        KR = times_transposed(np.ascontiguousarray(K), R) if R.ndim == 2 else K @ R
        P_post = symmetrize(A @ P @ np.swapaxes(A, -1, -2) + KR @ Kt)
    else:
        # Simple form: P = (I - KH) P, exact only for the optimal gain.
        P_post = symmetrize(A @ P)
    # yᵀ S⁻¹ y through the Cholesky factor: |L⁻¹ y|².
    w = solve_lower(L, y[..., None])[..., 0]
    nis = np.sum(w * w, axis=-1)
    log_det = 2.0 * np.sum(np.log(np.diagonal(L, axis1=-2, axis2=-1)), axis=-1)
    log_likelihood = -0.5 * (nis + log_det + H.shape[-2] * LOG_2PI)
    if measured_rows is not None:
        y = np.where(measured_rows[:, None], y, np.nan)
        nis = np.where(measured_rows, nis, np.nan)
        log_likelihood = np.where(measured_rows, log_likelihood, np.nan)
    return x_post, P_post, y, S, K, nis, log_likelihood
