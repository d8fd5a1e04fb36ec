"""Batched least squares over all local windows, Lemma 2 variance, noise variance.

All functions work on a batch of ``B`` independent local problems at once
(array operations, no Python loop over bins).
"""

from __future__ import annotations

import functools
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from . import _compiled
from .windows import (
    LocalModelLayout,
    StructuredWindows,
    local_regressor,
    window_offsets,
)

__all__ = [
    "LocalSolution",
    "solve_local_least_squares",
    "solve_local_normal_equations",
    "noise_variance",
    "lemma2_variance",
    "resolve_backend",
    "qr_chunk_size",
]

#: Default relative threshold on the diagonal of R (equilibrated QR) below
#: which a local problem is declared rank-deficient.
RANK_TOL = 1e-10

#: Windows whose equilibrated Cholesky factor has ``min L_jj`` below this are
#: re-solved by QR in the fast solver (normal equations would lose too many
#: digits there, and the QR rank test decides whether they are well posed).
CHOLESKY_FALLBACK_TOL = 1e-6

#: Windows whose last iterative-refinement correction is larger than this
#: (relative, in equilibrated parameters) are re-solved by QR in the fast
#: solver: the correction estimates the error of the normal equations, which
#: is the square of the error left after it while refinement converges.
REFINEMENT_TOL = 1e-5

#: The package's one bound on the bytes of a batch's largest arrays: local
#: regressors and Gram matrices here, windows refined at once
#: (:mod:`lrmfrf.refinement`), samples simulated at once (:mod:`lrmfrf.simulate`).
CHUNK_BYTES = 2**26

#: Implementations of :func:`solve_local_normal_equations`.
BACKENDS = ("auto", "numpy", "numba")

#: ``backend="auto"`` uses the compiled kernel when ``n_windows * n_params**2``
#: reaches this (8192 windows at the paper's 27 parameters; the numpy path's
#: cost per window grows about as ``n_params**2``). Below it the numpy path takes
#: well under 0.5 s, and a process that only fits short records never pays the
#: kernel's one-off compilation (~15-30 s in a fresh environment, then loaded
#: from numba's cache in ~0.3 s).
COMPILED_MIN_WORK = 8192 * 27**2

#: How much dearer a window of the numpy path is with the errors-in-variables
#: terms of the default std (``std_method="eiv"``): 3.3-4.0x the closed form
#: alone (SISO, F = 3, N = 3e3-2.4e4, 2026-11-27). ``resolve_backend(...,
#: eiv=True)`` divides :data:`COMPILED_MIN_WORK` by it, so a default fit keeps
#: about the closed form's time budget on numpy before it compiles (~0.3 s:
#: N = 1.2e4 at F = 3 stays on numpy; the closed form's threshold alone had let
#: eiv fits of up to ~1-2 s run there).
EIV_NUMPY_COST = 4


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
    lead_cov : ndarray of shape (B, c, c), complex, or None
        ``(A^H A)^-1`` at the leading ``c = cov_columns`` columns (the
        window-centre values of the input bands in the layout order), when
        requested.
    eiv_raw : tuple or None
        With ``eiv=True`` of :func:`solve_local_normal_equations` (compiled
        kernel): ``(lead, hw_trace, w_sum, w_min, w_max, valid)``, the terms of
        :func:`lrmfrf._compiled_uncertainty.eiv_windows` of the closed-form
        solution, computed with the solve; ``valid`` is False where the window
        was re-solved by QR (its terms must be computed again).
    """

    theta: np.ndarray
    gram_inv_diag: np.ndarray
    rss: np.ndarray
    well_posed: np.ndarray
    leverage: np.ndarray | None = None
    lead_cov: np.ndarray | None = None
    eiv_raw: tuple | None = None


def solve_local_least_squares(
    A: np.ndarray,
    b: np.ndarray,
    *,
    rank_tol: float = RANK_TOL,
    return_leverage: bool = False,
    rank_columns: int | None = None,
    cov_columns: int = 0,
) -> LocalSolution:
    """Solve the closed form eq. (linearSolution) for a batch of windows.

    ``theta = argmin ||b - A theta||^2`` per window, which is the paper's
    ``Theta = Y K^H (K K^H)^-1`` with ``A = K^T``. Columns are equilibrated to
    unit norm and the problem is solved by Householder QR, which is invariant
    to that scaling (an SVD cutoff is not, see ``docs/method.md``).

    Parameters
    ----------
    A : ndarray of shape (B, n_equations, n_params)
    b : ndarray of shape (B, n_equations)
    rank_tol : float, default=1e-10
        A window whose equilibrated ``R`` has ``min |R_jj| < rank_tol *
        max |R_jj|``, or a column of zeros, is declared not well posed.
    return_leverage : bool, default=False
        Also return the diagonal of the hat matrix (for PRESS).
    rank_columns : int, optional
        Apply the rank test only to the leading ``rank_columns`` columns
        (default: all). The local models pass the input and transient columns:
        those decide whether ``G`` is identifiable. A rank-deficient
        denominator block (an over-parameterised model on noise-free data: a
        common factor of numerators and denominator) leaves ``G(k+fM)`` unique,
        because ``e(0) = 1`` fixes the factor's value at the window centre, and
        is not flagged. Exactly-zero columns beyond the block get a zero
        coefficient.
    cov_columns : int, default=0
        Also return ``(A^H A)^-1`` at the leading ``cov_columns`` columns
        (``LocalSolution.lead_cov``).

    Returns
    -------
    LocalSolution
    """
    return _solve_dense(
        A, b, rank_tol=rank_tol, return_leverage=return_leverage,
        rank_columns=rank_columns, cov_columns=cov_columns,
    )[0]


def _solve_dense(
    A, b, *, rank_tol=RANK_TOL, return_leverage=False, rank_columns=None,
    cov_columns=0, eiv_layout=None,
):
    """:func:`solve_local_least_squares` as ``(solution, terms)``.

    With ``eiv_layout`` (the windows' :class:`~lrmfrf.windows.LocalModelLayout`)
    ``terms`` are the errors-in-variables terms of the well-posed windows,
    ``(lead, trace, done)`` as :func:`lrmfrf.uncertainty._terms_of_chunk`'s
    ``eiv_lead`` and ``eiv_trace`` (``done``: the well-posed windows, where
    they are computed), from this solve's factors
    (:func:`lrmfrf.uncertainty._dense_eiv_terms`); else None."""
    norms = np.linalg.norm(A, axis=1)  # (B, p)
    zero_column = norms <= np.finfo(float).tiny
    safe_norms = np.where(zero_column, 1.0, norms)
    A_eq = A / safe_norms[:, None, :]
    Q, R = np.linalg.qr(A_eq)
    diag = np.abs(np.diagonal(R, axis1=1, axis2=2))
    p = A.shape[2]
    m = p if rank_columns is None else rank_columns
    well_posed = ~zero_column[:, :m].any(axis=1) & (
        diag[:, :m].min(axis=1) > rank_tol * diag[:, :m].max(axis=1)
    )
    # Columns beyond the leading block that depend on others (e.g. a
    # denominator block of rank 1 where the output is zero but in one row):
    # the triangular solve would divide round-off by a tiny pivot. Those
    # windows are solved by the truncated SVD instead.
    trailing = np.where(zero_column, np.inf, diag)
    deficient = well_posed & (
        trailing.min(axis=1) <= rank_tol * diag.max(axis=1)
    )
    R = np.where(well_posed[:, None, None], R, np.eye(p))
    idx = np.arange(p)
    R[:, idx, idx] = np.where(diag == 0, 1.0, R[:, idx, idx])  # zero columns
    if deficient.any():  # (the truncated SVD solves those: no inverse of R)
        R_inv = np.empty_like(R)
        R_inv[deficient] = np.eye(p)
        R_inv[~deficient] = np.linalg.inv(R[~deficient])
    else:
        R_inv = np.linalg.inv(R)
    # Q^H b as the conjugate of Q^T conj(b) (the same products and sums,
    # without a conjugated copy of Q)
    qhb = np.conj(np.einsum("bij,bi->bj", Q, b.conj()))
    z = np.einsum("bij,bj->bi", R_inv, qhb)
    gram_inv_eq = np.sum(np.abs(R_inv) ** 2, axis=2)
    c = cov_columns
    lead_eq = None
    if c:
        lead = R_inv[:, :c, :]
        lead_eq = np.einsum("bck,bdk->bcd", lead, lead.conj())
    leverage = np.sum(np.abs(Q) ** 2, axis=2) if return_leverage else None
    svd = None
    if deficient.any():
        sel = np.flatnonzero(deficient)
        z[sel], gram_inv_eq[sel], lev, lead_sel, svd = _truncated_svd_solve(
            A_eq[sel], b[sel], rank_tol, c
        )
        if leverage is not None:
            leverage[sel] = lev
        if c:
            lead_eq[sel] = lead_sel
    theta = np.where(zero_column, 0.0, z / safe_norms)
    terms = None
    if eiv_layout is not None:
        from .uncertainty import _dense_eiv_terms

        terms = _dense_eiv_terms(
            theta, A_eq, safe_norms, zero_column, well_posed, deficient, Q,
            R_inv, svd, eiv_layout,
        )
    gram_inv_diag = gram_inv_eq / safe_norms**2
    lead_cov = None
    if c:
        lead_cov = lead_eq / (safe_norms[:, :c, None] * safe_norms[:, None, :c])
        lead_cov[~well_posed] = np.nan
    residual = b - np.einsum("bij,bj->bi", A, theta)
    rss = np.sum(np.abs(residual) ** 2, axis=1)
    bad = ~well_posed
    theta[bad] = np.nan
    gram_inv_diag[bad] = np.nan
    rss[bad] = np.nan
    if leverage is not None:
        leverage[bad] = np.nan
    solution = LocalSolution(theta, gram_inv_diag, rss, well_posed, leverage,
                             lead_cov)
    return solution, terms


def _truncated_svd_solve(A_eq, b, rank_tol, cov_columns=0):
    """Minimum-norm least squares of equilibrated, rank-deficient windows.

    Singular values below ``rank_tol`` times the largest are dropped. The
    window-centre values ``G(k+fM)`` are the same for every least-squares
    solution when only trailing (denominator) columns are dependent, so the
    minimum-norm one gives them without amplifying round-off; the diagonal of
    the pseudo-inverse Gram matrix is their variance factor.

    Returns
    -------
    z : ndarray of shape (B, p), complex
    gram_inv_eq : ndarray of shape (B, p)
        Diagonal of ``(A_eq^H A_eq)^+``.
    leverage : ndarray of shape (B, n_equations)
    lead_cov : ndarray of shape (B, c, c) or None
        ``(A_eq^H A_eq)^+`` at the leading ``c = cov_columns`` columns.
    factors : tuple
        ``(U, s, Vh)``: the thin SVD ``A_eq = U diag(s) Vh``.
    """
    U, s, Vh = np.linalg.svd(A_eq, full_matrices=False)
    keep = s > rank_tol * s[:, :1]
    inv_s = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    uhb = np.einsum("bij,bi->bj", U.conj(), b)
    z = np.einsum("bji,bj->bi", Vh.conj(), inv_s * uhb)
    gram_inv_eq = np.einsum("bji,bj->bi", np.abs(Vh) ** 2, inv_s**2)
    leverage = np.sum(np.abs(U) ** 2 * keep[:, None, :], axis=2)
    lead_cov = None
    if cov_columns:
        lead = Vh[:, :, :cov_columns]
        lead_cov = np.einsum("bkc,bk,bkd->bcd", lead.conj(), inv_s**2, lead)
    return z, gram_inv_eq, leverage, lead_cov, (U, s, Vh)


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


def solve_local_normal_equations(
    U: np.ndarray,
    Y: np.ndarray,
    slow_bins: np.ndarray,
    layout: LocalModelLayout,
    *,
    rank_tol: float = RANK_TOL,
    refine_steps: int = 1,
    fallback_tol: float = CHOLESKY_FALLBACK_TOL,
    rank_columns: int | None = None,
    backend: str = "auto",
    cov_columns: int = 0,
    eiv: bool = False,
) -> LocalSolution:
    """Fast closed form eq. (linearSolution) by structured normal equations.

    Same problems and results as ``solve_local_least_squares(*local_regressor(
    U, Y, slow_bins, layout))`` without building ``A``: the Gram matrices of
    all windows come from sliding weighted sums (:class:`~lrmfrf.windows.
    StructuredWindows`), in a basis of polynomials orthonormal on the window;
    they are equilibrated, Cholesky-factorised in batch, and the solution is
    improved by ``refine_steps`` steps of iterative refinement with the
    explicit residual ``b - A theta`` (which recovers the accuracy lost to
    squaring the condition number). Windows whose equilibrated factor has
    ``min L_jj < fallback_tol`` (near rank deficiency) are re-solved by
    Householder QR, which also applies the ``rank_tol`` test to them; so are
    windows whose last refinement correction exceeds ``REFINEMENT_TOL``
    relative (ill-conditioned for the normal equations, e.g. a denominator
    degree far above the system's).

    Parameters
    ----------
    U : ndarray of shape (P, N), complex
    Y : ndarray of shape (P, M) or (P, n_rows, M), complex
        One output row, or ``n_rows`` rows (one local problem each, with its
        own denominator): the compiled kernel then builds and factors the
        input and transient block of each window once for all rows.
    slow_bins : ndarray of shape (B,), int, in ``0..M-1``
    layout : LocalModelLayout
    rank_tol : float, default=1e-10
        QR rank test of the fallback windows, as in
        :func:`solve_local_least_squares`.
    refine_steps : int, default=1
        Iterative-refinement steps (each costs one residual and one pair of
        triangular solves). With 0, ill-conditioning is only detected through
        ``fallback_tol``.
    fallback_tol : float, default=1e-6
    rank_columns : int, optional
        Passed to the QR fallback (see :func:`solve_local_least_squares`).
    backend : {"auto", "numpy", "numba"}, default="auto"
        ``"numba"``: the compiled kernel of :mod:`lrmfrf._compiled`, windows
        in SIMD lanes and threads (Gram matrix, Cholesky, solves, refinement
        and variance without batched temporaries; needs the ``fast`` extra,
        ``pip install numba``); ``"numpy"``: batched array operations; ``"auto"``:
        ``"numba"`` when it is importable, the environment variable
        ``LRMFRF_DISABLE_NUMBA`` is not set to a non-empty value other than
        ``0`` and the problem is large enough to pay for it
        (:data:`COMPILED_MIN_WORK`), else ``"numpy"``. Both give the same
        results up to round-off.
    cov_columns : int, default=0
        Also return ``(A^H A)^-1`` at the leading ``cov_columns`` layout
        columns (at most ``layout.n_bands``: the window-centre band values).
    eiv : bool, default=False
        With the compiled kernel, also compute the errors-in-variables terms
        of the solution in the same pass (``eiv_raw`` of the result; see
        :func:`lrmfrf._compiled_uncertainty.solve_eiv_windows`): the window
        data and the factor of ``A^H A`` are then built once for the solve and
        the terms. Ignored by the numpy path (``eiv_raw`` None).

    Returns
    -------
    LocalSolution, or list of LocalSolution (one per row of a 3-D ``Y``)
        ``theta`` in monomial coefficients and layout order; ``gram_inv_diag``
        is exact at the window-centre columns (``G(k+fM)/F`` and ``T(k)``,
        columns ``0..F-1`` and ``layout.transient_column(p)``) and NaN at the
        other columns (use :func:`solve_local_least_squares` for those);
        ``leverage`` is None.
    """
    solutions, _, _ = _solve_normal_rows(
        U, Y[:, None] if Y.ndim == 2 else Y, slow_bins, layout,
        rank_tol=rank_tol, refine_steps=refine_steps, fallback_tol=fallback_tol,
        rank_columns=rank_columns, backend=backend, cov_columns=cov_columns,
        eiv=eiv,
    )
    return solutions[0] if Y.ndim == 2 else solutions


def _solve_normal_rows(
    U, rows, slow_bins, layout, *, rank_tol=RANK_TOL, refine_steps=1,
    fallback_tol=CHOLESKY_FALLBACK_TOL, rank_columns=None, backend="auto",
    cov_columns=0, eiv=False,
):
    """:func:`solve_local_normal_equations` of the rows of ``rows`` (P,
    n_rows, M): the list of solutions, and also the arrays they are views of,
    for callers that want all rows at once without stacking them again:
    ``theta`` (n_rows, B, n_params), whose row ``o`` is ``solutions[o].theta``
    (the same memory, so later changes of one show in the other), and the
    ``eiv_raw`` terms with a leading row axis and, after them, the dense
    terms of the windows re-solved by QR, ``(lead, trace, done)``
    (:func:`_with_qr_fallback`; None without them)."""
    slow_bins = np.asarray(slow_bins, dtype=int)
    backend = resolve_backend(backend, slow_bins.size, layout.n_params)
    n_centre = layout.n_bands + layout.n_experiments
    eiv_raw = None
    if backend == "numba" and eiv:
        from ._compiled_uncertainty import solve_eiv_windows

        weights, col_base, tables, to_layout = _kernel_tables(layout)
        _, x = window_offsets(layout.half_window)
        solved, eiv_raw = solve_eiv_windows(
            U.reshape(U.shape[0], layout.n_inputs, -1), rows, slow_bins, weights,
            col_base, layout.n_bands, n_centre,
            den_columns=np.arange(layout.n_params)[layout.den_columns],
            powers=x[:, None] ** np.arange(1, layout.den_degree + 1),
            tables=tables, weighted_tables=_kernel_weighted_tables(layout),
            to_layout=to_layout, fallback_tol=fallback_tol,
            refine_tol=REFINEMENT_TOL, refine_steps=refine_steps,
        )
        # the terms hold where the kernel's own solution is kept
        eiv_raw = eiv_raw + (solved[3].copy(),)
        n_rows, B, nb = rows.shape[1], slow_bins.size, layout.n_bands
        dense = (np.full((n_rows, B, nb, nb), np.nan, dtype=complex),
                 np.full((n_rows, B), np.nan), np.zeros((n_rows, B), dtype=bool))
    elif backend == "numba":
        weights, col_base, tables, to_layout = _kernel_tables(layout)
        solved = _compiled.solve_windows(
            U.reshape(U.shape[0], layout.n_inputs, -1), rows, slow_bins, weights,
            col_base, layout.n_bands, n_centre,
            fallback_tol=fallback_tol, refine_tol=REFINEMENT_TOL,
            refine_steps=refine_steps, tables=tables, to_layout=to_layout,
            return_cov=True,
        )
    else:
        solved = []
        for o in range(rows.shape[1]):
            windows = StructuredWindows(U, rows[:, o], slow_bins, layout)
            theta, rss, centre_cov, fast = _normal_equations_numpy(
                windows, n_centre, fallback_tol, refine_steps
            )
            solved.append((windows.to_layout(theta), rss, centre_cov, fast))
        solved = [np.stack(parts) for parts in zip(*solved, strict=True)]
    order = _empty_windows(layout).order
    # the windows re-solved by QR get their dense terms there (``dense``
    # changed in place: a row's entries are views of its arrays)
    solutions = [
        _with_qr_fallback(
            U, rows[:, o], slow_bins, layout, order, *(part[o] for part in solved),
            n_centre=n_centre, cov_columns=cov_columns, rank_tol=rank_tol,
            rank_columns=rank_columns,
            dense_row=None if eiv_raw is None else tuple(part[o] for part in dense),
        )
        for o in range(rows.shape[1])
    ]
    if eiv_raw is not None:
        for o, solution in enumerate(solutions):
            solution.eiv_raw = tuple(part[o] for part in eiv_raw)
        eiv_raw = eiv_raw + (dense,)
    return solutions, solved[0], eiv_raw


def _with_qr_fallback(
    U, Y, slow_bins, layout, order, theta, rss, centre_cov, fast, *, n_centre,
    cov_columns, rank_tol, rank_columns, dense_row=None,
) -> LocalSolution:
    """The :class:`LocalSolution` of one output row from the normal equations
    (``order``: internal column order, the window-centre columns last), with
    the windows they could not solve re-solved by QR.

    ``dense_row``: None, or the row's arrays ``(lead, trace, done)`` that
    receive, in place, the errors-in-variables terms of the dense route
    (:func:`lrmfrf.uncertainty._terms_of_chunk`'s ``eiv_lead`` and
    ``eiv_trace``) of the re-solved windows that are well posed, computed
    from this solve's factors (:func:`lrmfrf.uncertainty._dense_eiv_terms`),
    ``done`` True there. Where the kernel pass of the terms fails on such a
    window (every window of a noise-free record with an over-parameterised
    denominator) they stand in for the dense route, which would build and
    factor the window again."""
    c = cov_columns
    centre_var = np.real(np.diagonal(centre_cov, axis1=1, axis2=2))
    gram_inv_diag = np.full((slow_bins.size, layout.n_params), np.nan)
    gram_inv_diag[:, order[-n_centre:]] = centre_var
    # the internal centre columns start with the bands in layout order
    lead_cov = np.array(centre_cov[:, :c, :c]) if c else None
    well_posed = fast.copy()

    slow = np.flatnonzero(~fast)
    chunk = qr_chunk_size(layout)
    for start in range(0, slow.size, chunk):  # bounded memory, however many
        part = slow[start : start + chunk]
        A, b = local_regressor(U, Y, slow_bins[part], layout)
        qr, terms = _solve_dense(
            A, b, rank_tol=rank_tol, rank_columns=rank_columns, cov_columns=c,
            eiv_layout=None if dense_row is None else layout,
        )
        del A, b
        if terms is not None:
            done = terms[-1]
            for target, value in zip(dense_row, terms, strict=True):
                target[part[done]] = value[done]
        theta[part] = qr.theta
        gram_inv_diag[part] = qr.gram_inv_diag
        rss[part] = qr.rss
        well_posed[part] = qr.well_posed
        if c:
            lead_cov[part] = qr.lead_cov
    return LocalSolution(theta, gram_inv_diag, rss, well_posed, None, lead_cov)


def qr_chunk_size(layout: LocalModelLayout) -> int:
    """Windows per batch of the QR solver that keep its regressor near
    :data:`CHUNK_BYTES`."""
    return max(1, CHUNK_BYTES // (16 * layout.n_equations * layout.n_params))


def _normal_equations_numpy(windows, n_centre, fallback_tol, refine_steps):
    """Array-operation path: (theta internal, rss, centre_var, fast)."""
    p = windows.layout.n_params
    gram, rhs, _ = windows.normal_equations()
    # Cholesky is invariant to diagonal scaling (van der Sluis): factor the raw
    # Gram and read the equilibrated pivots as L_jj / sqrt(G_jj).
    scale = np.sqrt(np.abs(np.real(np.diagonal(gram, axis1=1, axis2=2))))
    zero_column = ~(scale > np.finfo(float).tiny)
    scale = np.where(zero_column, 1.0, scale)
    chol = _batched_cholesky(gram)
    del gram
    pivots = np.real(np.diagonal(chol, axis1=1, axis2=2)) / scale
    with np.errstate(invalid="ignore"):
        fast = ~zero_column.any(axis=1) & np.all(pivots > fallback_tol, axis=1)
    if not fast.all():
        chol[~fast] = np.eye(p)
    chol_t = np.ascontiguousarray(chol.transpose(1, 2, 0))

    theta = _cholesky_solve(chol_t, rhs)
    for step in range(refine_steps + 1):
        res = windows.residual(theta)
        rss = np.sum(res.real**2 + res.imag**2, axis=(0, 2))
        if step == refine_steps:
            break
        correction = windows.adjoint(res)
        delta = _cholesky_solve(chol_t, correction)
        with np.errstate(invalid="ignore", divide="ignore"):
            change = np.linalg.norm(delta * scale, axis=1) / np.linalg.norm(
                theta * scale, axis=1
            )
        theta += delta
        # ||r - A delta||^2 = ||r||^2 - Re(delta^H A^H r) at the refined solution
        rss = rss - np.real(np.sum(np.conj(delta) * correction, axis=1))
    del res
    if refine_steps > 0:
        fast &= change <= REFINEMENT_TOL

    tail = chol[:, -n_centre:, -n_centre:]
    tail_inv = np.linalg.inv(tail)
    # (L L^H)^-1 at the trailing block is tail_inv^H tail_inv
    centre_cov = np.einsum("bkc,bkd->bcd", tail_inv.conj(), tail_inv)
    return theta, rss, centre_cov, fast


def resolve_backend(
    backend: str, n_windows: int | None = None, n_params: int = 27, *,
    eiv: bool = False,
) -> str:
    """Map ``backend`` of :func:`solve_local_normal_equations` to a path.

    Parameters
    ----------
    backend : {"auto", "numpy", "numba"}
    n_windows : int, optional
        Number of windows of the whole fit. With ``"auto"``, ``n_windows *
        n_params**2`` below :data:`COMPILED_MIN_WORK` selects ``"numpy"``.
    n_params : int, default=27
        Parameters of one local problem.
    eiv : bool, default=False
        The fit computes the errors-in-variables terms of the std: the numpy
        path costs :data:`EIV_NUMPY_COST` times more per window, and the
        threshold is that much lower.

    Returns
    -------
    {"numpy", "numba"}
    """
    if backend not in BACKENDS:
        raise ValueError(
            f"`backend` must be one of {BACKENDS}. Got {backend!r} instead. Use "
            "'auto' unless you are comparing implementations."
        )
    disabled = os.environ.get("LRMFRF_DISABLE_NUMBA", "") not in ("", "0")
    if backend == "numba" and not _compiled.AVAILABLE:
        raise ImportError(
            "backend='numba' needs numba, which is not importable. Install it "
            "(pip install 'lrmfrf[fast]' or pip install numba) or use "
            "backend='auto' or 'numpy'."
        )
    if backend == "auto":
        cost = EIV_NUMPY_COST if eiv else 1
        small = (n_windows is not None
                 and cost * n_windows * n_params**2 < COMPILED_MIN_WORK)
        use_compiled = _compiled.AVAILABLE and not disabled and not small
        return "numba" if use_compiled else "numpy"
    return backend


#: Bytes each per-layout table cache below may hold (least recently used
#: layouts are dropped first): a default grid of 64 SISO layouts takes about
#: 7 MB in all four caches, but a 4x4, P = 4 layout at F = 8 about 3.8 MB.
TABLE_CACHE_BYTES = 2**26


def _nbytes(value) -> int:
    """Bytes of the numpy arrays in ``value`` (tuples, lists, dicts and object
    attributes): an object's attributes that are arrays, tuples, lists or
    dicts are counted, and the containers are followed into the objects they
    hold; an attribute that is itself an object is not (a layout, the
    ``LocalBasis`` of a :class:`~lrmfrf.windows.StructuredWindows`). An array
    held twice counts twice; a container that holds its own owner would
    recurse without end (no cached table does)."""
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, (tuple, list)):
        return sum(_nbytes(v) for v in value)
    if isinstance(value, dict):
        return sum(_nbytes(v) for v in value.values())
    if hasattr(value, "__dict__") and not isinstance(value, type):
        return sum(_nbytes(v) for v in vars(value).values()
                   if isinstance(v, (np.ndarray, tuple, list, dict)))
    return 0


def _layout_cache(function):
    """Least-recently-used cache of a layout's tables, bounded by
    :data:`TABLE_CACHE_BYTES` (read at each insertion) and 128 layouts; the
    newest entry is kept even when it alone exceeds the bound. Thread-safe; a
    table computed twice by racing threads is equal either way."""
    entries: OrderedDict = OrderedDict()
    lock = threading.Lock()
    total = [0]

    @functools.wraps(function)
    def cached(layout):
        with lock:
            if layout in entries:
                entries.move_to_end(layout)
                return entries[layout][0]
        value = function(layout)
        size = _nbytes(value)
        with lock:
            if layout not in entries:
                entries[layout] = (value, size)
                total[0] += size
            while len(entries) > 1 and (total[0] > TABLE_CACHE_BYTES
                                        or len(entries) > 128):
                _, (_, dropped) = entries.popitem(last=False)
                total[0] -= dropped
        return value

    def cache_info() -> dict:
        with lock:
            return {"entries": len(entries), "bytes": total[0]}

    def cache_clear() -> None:
        with lock:
            entries.clear()
            total[0] = 0

    cached.cache_info = cache_info
    cached.cache_clear = cache_clear
    return cached


@_layout_cache
def _compiled_tables(layout: LocalModelLayout):
    """Column weights, bases and moment tables of a layout (data-independent),
    in the internal order of :class:`~lrmfrf.windows.StructuredWindows`."""
    weights, col_base = _empty_windows(layout).column_weights()
    tables = _compiled.moment_tables(
        weights, col_base, layout.n_bands, layout.n_experiments
    )
    return weights, col_base, tables


@_layout_cache
def _kernel_tables(layout: LocalModelLayout):
    """Column weights, bases, moment tables and ``to_layout`` matrix of
    :func:`lrmfrf._compiled.solve_windows`: the internal order with the
    denominator columns moved last (the kernel shares the Gram block of the
    other columns between output rows)."""
    P = layout.n_experiments
    empty = _empty_windows(layout)
    weights, col_base = empty.column_weights()
    den = col_base == layout.n_bands + P
    move = np.concatenate([np.flatnonzero(~den), np.flatnonzero(den)])
    weights, col_base = weights[:, move], col_base[move]
    tables = _compiled.moment_tables(weights, col_base, layout.n_bands, P)
    return weights, col_base, tables, empty.to_layout_matrix[move]


@_layout_cache
def _kernel_weighted_tables(layout: LocalModelLayout) -> dict:
    """Row-weighted moment tables (for ``A^H diag(w) A``) in the column order
    of :func:`_kernel_tables` (the denominator columns last)."""
    weights, col_base, _, _ = _kernel_tables(layout)
    return _compiled.moment_tables(
        weights, col_base, layout.n_bands, layout.n_experiments, weighted=True
    )


@_layout_cache
def _empty_windows(layout: LocalModelLayout) -> StructuredWindows:
    """A :class:`~lrmfrf.windows.StructuredWindows` without data: its column
    order, weights and ``to_layout`` matrix depend on the layout only. The
    matrix (``n_params**2`` floats, a cached property) is made here, so that
    the cache counts its bytes."""
    P = layout.n_experiments
    empty = StructuredWindows(
        np.zeros((P, layout.n_bands)), np.zeros((P, 1)), np.zeros(0, dtype=int),
        layout,
    )
    empty.to_layout_matrix  # noqa: B018 - computed before the cache counts it
    return empty


def _batched_cholesky(gram: np.ndarray) -> np.ndarray:
    """Lower Cholesky factors; NaN (not an exception) where one fails."""
    try:
        return np.linalg.cholesky(gram)
    except np.linalg.LinAlgError:
        pass
    out = np.full_like(gram, np.nan)
    for i in range(gram.shape[0]):
        try:
            out[i] = np.linalg.cholesky(gram[i])
        except np.linalg.LinAlgError:
            continue
    return out


def _cholesky_solve(chol_t: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``L L^H z = rhs`` for a batch by forward and back substitution.

    ``chol_t`` is the batch of lower factors with the batch axis last, shape
    (p, p, B), so that every step works on contiguous rows.
    """
    p = chol_t.shape[0]
    z = np.array(rhs.T, dtype=complex, order="C")  # (p, B)
    for j in range(p):
        z[j] /= chol_t[j, j]
        z[j + 1 :] -= chol_t[j + 1 :, j] * z[j]
    for j in range(p - 1, -1, -1):
        z[j] -= np.sum(np.conj(chol_t[j + 1 :, j]) * z[j + 1 :], axis=0)
        z[j] /= chol_t[j, j]
    return z.T
