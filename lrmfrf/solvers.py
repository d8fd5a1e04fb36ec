"""Batched least squares over all local windows, Lemma 2 variance, noise variance.

All functions work on a batch of ``B`` independent local problems at once
(array operations, no Python loop over bins).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "LocalSolution",
    "solve_local_least_squares",
    "noise_variance",
    "lemma2_variance",
]

#: Default relative threshold on the diagonal of R (equilibrated QR) below
#: which a local problem is declared rank-deficient.
RANK_TOL = 1e-10


@dataclass
class LocalSolution:
    """Result of a batch of local least-squares problems ``A theta = b``.

    Attributes
    ----------
    theta : ndarray of shape (B, n_params), complex
        Least-squares parameters (NaN where ``well_posed`` is False).
    gram_inv_diag : ndarray of shape (B, n_params), float
        Diagonal of ``(A^H A)^-1``.
    rss : ndarray of shape (B,), float
        Residual sum of squares ``||b - A theta||^2``.
    well_posed : ndarray of shape (B,), bool
        False where ``A`` is (numerically) rank-deficient.
    leverage : ndarray of shape (B, n_equations) or None
        Diagonal of the hat matrix ``A (A^H A)^-1 A^H`` (if requested).
    """

    theta: np.ndarray
    gram_inv_diag: np.ndarray
    rss: np.ndarray
    well_posed: np.ndarray
    leverage: np.ndarray | None = None


def solve_local_least_squares(
    A: np.ndarray,
    b: np.ndarray,
    *,
    rank_tol: float = RANK_TOL,
    return_leverage: bool = False,
) -> LocalSolution:
    """Solve the closed form eq. (linearSolution) for a batch of windows.

    ``theta = argmin ||b - A theta||^2`` per window, which is the paper's
    ``Theta = Y K^H (K K^H)^-1`` with ``A = K^T``. Columns are equilibrated to
    unit norm and the problem is solved by Householder QR, which is invariant
    to that scaling (an SVD cutoff is not, see ``METHOD.md``).

    Parameters
    ----------
    A : ndarray of shape (B, n_equations, n_params)
    b : ndarray of shape (B, n_equations)
    rank_tol : float, default=1e-10
        A window whose equilibrated ``R`` has ``min |R_jj| < rank_tol *
        max |R_jj|``, or a column of zeros, is declared not well posed.
    return_leverage : bool, default=False
        Also return the diagonal of the hat matrix (for PRESS).

    Returns
    -------
    LocalSolution
    """
    norms = np.linalg.norm(A, axis=1)  # (B, p)
    zero_column = norms <= np.finfo(float).tiny
    safe_norms = np.where(zero_column, 1.0, norms)
    Q, R = np.linalg.qr(A / safe_norms[:, None, :])
    diag = np.abs(np.diagonal(R, axis1=1, axis2=2))
    well_posed = ~zero_column.any(axis=1) & (
        diag.min(axis=1) > rank_tol * diag.max(axis=1)
    )
    p = A.shape[2]
    R = np.where(well_posed[:, None, None], R, np.eye(p))
    R_inv = np.linalg.inv(R)
    qhb = np.einsum("bij,bi->bj", Q.conj(), b)
    z = np.einsum("bij,bj->bi", R_inv, qhb)
    theta = z / safe_norms
    gram_inv_diag = np.sum(np.abs(R_inv) ** 2, axis=2) / safe_norms**2
    residual = b - np.einsum("bij,bj->bi", A, theta)
    rss = np.sum(np.abs(residual) ** 2, axis=1)
    leverage = np.sum(np.abs(Q) ** 2, axis=2) if return_leverage else None
    bad = ~well_posed
    theta[bad] = np.nan
    gram_inv_diag[bad] = np.nan
    rss[bad] = np.nan
    if leverage is not None:
        leverage[bad] = np.nan
    return LocalSolution(theta, gram_inv_diag, rss, well_posed, leverage)


def noise_variance(rss: np.ndarray, dof: int) -> np.ndarray:
    """Noise variance ``C_v(k)`` from the residual (paper, after Lemma 2).

    ``C_v = ||Y - Theta K||^2 / q`` with ``q = 2n+1 - n_params`` degrees of
    freedom (``P(2n+1) - n_params`` for ``P`` experiments). Returns NaN when
    ``q = 0``: the fit interpolates and the noise cannot be estimated.

    Parameters
    ----------
    rss : ndarray of shape (B,)
    dof : int

    Returns
    -------
    ndarray of shape (B,)
    """
    if dof <= 0:
        return np.full_like(rss, np.nan)
    return rss / dof


def lemma2_variance(
    gram_inv_diag_system: np.ndarray, noise_var: np.ndarray, F: int
) -> np.ndarray:
    """Variance of the FRF estimate, Lemma 2 / eq. (Variance) of the paper.

    ``var G(k+fM) = F^2 [(K K^H)^-1]_ff C_v(k)``.

    Parameters
    ----------
    gram_inv_diag_system : ndarray of shape (B, F)
        Diagonal entries of ``(A^H A)^-1`` at the columns of ``G(k+fM)/F``.
    noise_var : ndarray of shape (B,)
    F : int

    Returns
    -------
    ndarray of shape (B, F)
    """
    return F**2 * gram_inv_diag_system * noise_var[:, None]
