"""Compiled errors-in-variables terms of the closed form (optional, needs numba).

:func:`eiv_windows` computes, for every window and given the closed-form
parameters, the two ingredients of the ``"eiv"`` route of
:mod:`lrmfrf.uncertainty` without forming the regressor ``A``:

- ``S^H diag(w) S = [G^-1 H G^-1]`` at the window-centre band columns, with
  ``G = A^H A``, ``H = A^H diag(w) A`` and ``w_r = |e(x_r)|^2`` the squared
  local denominator on the window;
- ``sum_r w_r (1 - h_r) = sum_r w_r - tr(G^-1 H)`` (``h_r`` the leverages).

Both Gram matrices come from the moment form of :mod:`lrmfrf._compiled`
(whose step functions are called, not copied): ``G`` with the closed form's
tables, ``H`` with its row-weighted tables (those of Sanathanan-Koerner), the
pair series multiplied by ``w(r)`` before their moments are taken, which is
exact because ``w`` multiplies every column product alike. ``G`` is
Cholesky-factorised with the same equilibrated pivot check as the closed
form; ``G^-1`` follows from the inverse of the factor. Windows whose check
fails are flagged (``ok`` False) for the caller's dense fallback. Windows are
processed in SIMD lanes and threads as in :mod:`lrmfrf._compiled`.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from . import _compiled
from ._compiled import LANES

if _compiled.AVAILABLE:  # pragma: no branch
    import numba
    from numba import njit

__all__ = ["eiv_windows"]

_GROUPS_PER_TASK = 8


def _eiv_range_py(
    U, Y, bins, den, powers, data_index, F, n_centre, n_bands, q_basis,
    g_kind, g_a, g_b, g_nd, g_off, g_ptr, g_mom, g_coef, g_conj, g_const,
    g_rhs_ptr, g_rhs_mom, g_rhs_coef, g_n_moments,
    w_kind, w_a, w_b, w_nd, w_off, w_ptr, w_mom, w_coef, w_conj, w_const,
    w_rhs_ptr, w_rhs_mom, w_rhs_coef, w_n_moments, p, tol2, lead, trace, wsum,
    wmin, wmax, ok_out,
    first_group, stop_group,
):
    """Lane groups ``first_group..stop_group-1`` (one thread's share)."""
    P = U.shape[0]
    L = powers.shape[0]
    n = L // 2
    f64 = np.float64
    sr = np.empty((F + 1, P, L, LANES), f64)
    si = np.empty((F + 1, P, L, LANES), f64)
    Sr = np.empty((L, LANES), f64)
    Si = np.empty((L, LANES), f64)
    Er = np.empty((n + 1, LANES), f64)
    Ei = np.empty((n + 1, LANES), f64)
    Or = np.empty((n + 1, LANES), f64)
    Oi = np.empty((n + 1, LANES), f64)
    mr = np.empty((g_n_moments, LANES), f64)
    mi = np.empty((g_n_moments, LANES), f64)
    mwr = np.empty((w_n_moments, LANES), f64)
    mwi = np.empty((w_n_moments, LANES), f64)
    n_packed = p * (p + 1) // 2
    Hr = np.empty((n_packed, LANES), f64)
    Hi = np.empty((n_packed, LANES), f64)
    Wr = np.empty((n_packed, LANES), f64)
    Wi = np.empty((n_packed, LANES), f64)
    gr = np.empty((p, LANES), f64)
    gi = np.empty((p, LANES), f64)
    scale2 = np.empty((p, LANES), f64)
    ok = np.empty(LANES, np.bool_)
    k = np.empty(LANES, np.int64)
    wt = np.empty((L, LANES), f64)
    Kr = np.empty((p, p, LANES), f64)
    Ki = np.empty((p, p, LANES), f64)
    Cr = np.empty((p, p, LANES), f64)
    Ci = np.empty((p, p, LANES), f64)
    Zr = np.empty((p, LANES), f64)
    Zi = np.empty((p, LANES), f64)
    acc_r = np.empty(LANES, f64)
    acc_i = np.empty(LANES, f64)
    B = bins.shape[0]
    Re = powers.shape[1]
    off = p - n_centre
    for group in range(first_group, stop_group):
        first = group * LANES
        for w in range(LANES):
            k[w] = bins[min(first + w, B - 1)]
        _compiled._gather(U, Y, k, F, n, sr, si)
        # the squared denominator on the window, w(r) = |e(x_r)|^2
        for r in range(L):
            for w in range(LANES):
                row = min(first + w, B - 1)
                er = 1.0
                ei = 0.0
                for s in range(Re):
                    er += den[row, s, 0] * powers[r, s]
                    ei += den[row, s, 1] * powers[r, s]
                wt[r, w] = er * er + ei * ei
        # G = A^H A (the closed form's tables) and H = A^H diag(w) A (the
        # weighted tables: the same pairs at the same offsets, then the
        # transient-transient series, which is w itself): each pair series
        # once, its moments as it is and times w(r)
        for t in range(w_kind.shape[0]):
            _compiled._pair_series(sr, si, w_kind[t], w_a[t], w_b[t], Sr, Si)
            if t < g_kind.shape[0]:
                _compiled._moments(Sr, Si, q_basis, g_off[t], g_nd[t], Er, Ei,
                                   Or, Oi, mr, mi)
            for r in range(L):
                for w in range(LANES):
                    Sr[r, w] *= wt[r, w]
                    Si[r, w] *= wt[r, w]
            _compiled._moments(Sr, Si, q_basis, w_off[t], w_nd[t], Er, Ei, Or,
                               Oi, mwr, mwi)
        _compiled._gram(mr, mi, g_ptr, g_mom, g_coef, g_conj, g_const, g_rhs_ptr,
                        g_rhs_mom, g_rhs_coef, Hr, Hi, gr, gi)
        _compiled._cholesky(Hr, Hi, scale2, ok, tol2, p)
        _compiled._gram(mwr, mwi, w_ptr, w_mom, w_coef, w_conj, w_const, w_rhs_ptr,
                        w_rhs_mom, w_rhs_coef, Wr, Wi, gr, gi)
        # K = L^-1 (lower), then G^-1 = K^H K, lower triangle in C
        _compiled._tail_inverse(Hr, Hi, p, p, Kr, Ki)
        for c in range(p):
            for d in range(c + 1):
                for w in range(LANES):
                    acc_r[w] = 0.0
                    acc_i[w] = 0.0
                for i in range(c, p):
                    for w in range(LANES):
                        # conj(K[i,c]) K[i,d]
                        kcr = Kr[i, c, w]
                        kci = Ki[i, c, w]
                        acc_r[w] += kcr * Kr[i, d, w] + kci * Ki[i, d, w]
                        acc_i[w] += kcr * Ki[i, d, w] - kci * Kr[i, d, w]
                for w in range(LANES):
                    Cr[c, d, w] = acc_r[w]
                    Ci[c, d, w] = acc_i[w]
        # tr(G^-1 H) from the lower triangles of both (Hermitian)
        for w in range(LANES):
            acc_r[w] = 0.0
        for c in range(p):
            rc = c * (c + 1) // 2
            for w in range(LANES):
                acc_r[w] += Cr[c, c, w] * Wr[rc + c, w]
            for d in range(c):
                for w in range(LANES):
                    acc_r[w] += 2.0 * (Cr[c, d, w] * Wr[rc + d, w]
                                       + Ci[c, d, w] * Wi[rc + d, w])
        for w in range(LANES):
            row = first + w
            if row < B:
                trace[row] = acc_r[w]
                ok_out[row] = ok[w]
        for w in range(LANES):
            row = first + w
            if row < B:
                total = 0.0
                lo = np.inf
                hi = 0.0
                for r in range(L):
                    total += wt[r, w]
                    lo = min(lo, wt[r, w])
                    hi = max(hi, wt[r, w])
                wsum[row] = P * total
                wmin[row] = lo
                wmax[row] = hi
        # [G^-1 H G^-1] at the centre bands: z_b = H g_b, lead[a, b] = g_a^H z_b
        for b in range(n_bands):
            cb = off + b
            for i in range(p):
                for w in range(LANES):
                    acc_r[w] = 0.0
                    acc_i[w] = 0.0
                for j in range(p):
                    if i >= j:
                        e = i * (i + 1) // 2 + j
                        sgn = 1.0
                    else:
                        e = j * (j + 1) // 2 + i
                        sgn = -1.0
                    if j >= cb:
                        jr = j
                        jc = cb
                        tg = 1.0
                    else:
                        jr = cb
                        jc = j
                        tg = -1.0
                    for w in range(LANES):
                        hr = Wr[e, w]
                        hi_ = sgn * Wi[e, w]
                        vr = Cr[jr, jc, w]
                        vi = tg * Ci[jr, jc, w]
                        acc_r[w] += hr * vr - hi_ * vi
                        acc_i[w] += hr * vi + hi_ * vr
                for w in range(LANES):
                    Zr[i, w] = acc_r[w]
                    Zi[i, w] = acc_i[w]
            for a in range(n_bands):
                ca = off + a
                for w in range(LANES):
                    acc_r[w] = 0.0
                    acc_i[w] = 0.0
                for i in range(p):
                    # conj(G^-1[i, ca]) = G^-1[ca, i]
                    if ca >= i:
                        tg = 1.0
                        ir = ca
                        ic = i
                    else:
                        tg = -1.0
                        ir = i
                        ic = ca
                    for w in range(LANES):
                        vr = Cr[ir, ic, w]
                        vi = tg * Ci[ir, ic, w]
                        acc_r[w] += vr * Zr[i, w] - vi * Zi[i, w]
                        acc_i[w] += vr * Zi[i, w] + vi * Zr[i, w]
                for w in range(LANES):
                    row = first + w
                    if row < B:
                        lead[row, a, b, 0] = acc_r[w]
                        lead[row, a, b, 1] = acc_i[w]


if _compiled.AVAILABLE:  # pragma: no branch
    _eiv_range = njit(cache=True, fastmath={"contract"}, nogil=True,
                      error_model="numpy")(_eiv_range_py)


def eiv_windows(
    U: np.ndarray,
    Y: np.ndarray,
    slow_bins: np.ndarray,
    den: np.ndarray,
    powers: np.ndarray,
    weights: np.ndarray,
    col_base: np.ndarray,
    n_bands: int,
    n_centre: int,
    *,
    tables: dict,
    weighted_tables: dict,
    fallback_tol: float,
    n_threads: int | None = None,
):
    """Errors-in-variables terms of every window (compiled, threaded).

    Parameters
    ----------
    U : ndarray of shape (P, n_u, N), complex
    Y : ndarray of shape (P, M), complex
    slow_bins : ndarray of shape (B,), int
    den : ndarray of shape (B, R_e), complex
        Denominator coefficients ``e_1..e_Re`` of each window (finite).
    powers : ndarray of shape (2n+1, R_e)
        ``x_r^s``, ``s = 1..R_e``.
    weights, col_base : ndarray
        Internal column basis (see :func:`lrmfrf._compiled.moment_tables`).
    n_bands : int
        Window-centre band columns (the first of the last ``n_centre``
        internal columns).
    n_centre : int
    tables, weighted_tables : dict
        :func:`lrmfrf._compiled.moment_tables` without and with
        ``weighted=True``.
    fallback_tol : float
        Equilibrated-pivot threshold of the Cholesky factor of ``G``.
    n_threads : int, optional

    Returns
    -------
    lead : ndarray of shape (B, n_bands, n_bands), complex
        ``S^H diag(w) S`` at the band columns.
    hw_trace : ndarray of shape (B,)
        ``tr(G^-1 H) = sum_r w_r h_r``.
    w_sum, w_min, w_max : ndarray of shape (B,)
        ``sum_r w_r`` over all ``P (2n+1)`` rows, and ``min``/``max`` of ``w``.
    ok : ndarray of shape (B,), bool
        False where the pivot check failed (the terms are then not reliable).
    """
    B, p = slow_bins.size, weights.shape[1]
    if U.ndim == 2:
        U = U[:, None, :]
    lead = np.empty((B, n_bands, n_bands, 2))
    trace = np.empty(B)
    wsum = np.empty(B)
    wmin = np.empty(B)
    wmax = np.empty(B)
    ok = np.empty(B, dtype=np.bool_)
    t, tw = tables, weighted_tables
    den2 = np.ascontiguousarray(np.asarray(den, dtype=np.complex128)).view(np.float64)
    den2 = den2.reshape(B, -1, 2)
    args = (
        _compiled._as_interleaved(U), _compiled._as_interleaved(Y),
        np.ascontiguousarray(slow_bins, dtype=np.int64), den2,
        np.ascontiguousarray(powers, dtype=np.float64), t["data_index"],
        int(n_bands), int(n_centre), int(n_bands), t["q_basis"],
        t["pair_kind"], t["pair_a"], t["pair_b"], t["pair_nd"], t["pair_off"],
        t["ent_ptr"], t["ent_mom"], t["ent_coef"], t["ent_conj"], t["ent_const"],
        t["rhs_ptr"], t["rhs_mom"], t["rhs_coef"], int(t["n_moments"]),
        tw["pair_kind"], tw["pair_a"], tw["pair_b"], tw["pair_nd"], tw["pair_off"],
        tw["ent_ptr"], tw["ent_mom"], tw["ent_coef"], tw["ent_conj"],
        tw["ent_const"], tw["rhs_ptr"], tw["rhs_mom"], tw["rhs_coef"],
        int(tw["n_moments"]), int(p),
        float(fallback_tol) ** 2, lead, trace, wsum, wmin, wmax, ok,
    )
    n_groups = (B + LANES - 1) // LANES
    tasks = [
        (start, min(n_groups, start + _GROUPS_PER_TASK))
        for start in range(0, n_groups, _GROUPS_PER_TASK)
    ]
    threads = min(n_threads or numba.config.NUMBA_NUM_THREADS, len(tasks))
    if threads <= 1:
        if n_groups:
            _eiv_range(*args, 0, n_groups)
    else:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(lambda task: _eiv_range(*args, *task), tasks))
    return lead.view(np.complex128)[..., 0], trace, wsum, wmin, wmax, ok
