"""Compiled errors-in-variables terms of the closed form (optional, needs numba).

:func:`eiv_windows` computes, for every window and output row and given the
closed-form parameters, the two ingredients of the ``"eiv"`` route of
:mod:`lrmfrf.uncertainty` without forming the regressor ``A``:

- ``S^H diag(w) S = [G^-1 H G^-1]`` at the window-centre band columns, with
  ``G = A^H A``, ``H = A^H diag(w) A`` and ``w_r = |e(x_r)|^2`` the squared
  local denominator of the row on the window;
- ``sum_r w_r (1 - h_r) = sum_r w_r - tr(G^-1 H)`` (``h_r`` the leverages).

Both Gram matrices come from the moment form of :mod:`lrmfrf._compiled`
(whose step functions are called, not copied): ``G`` with the closed form's
tables, ``H`` with its row-weighted tables (those of Sanathanan-Koerner), the
pair series multiplied by ``w(r)`` before their moments are taken, which is
exact because ``w`` multiplies every column product alike. ``G`` is
Cholesky-factorised with the same equilibrated pivot check as the closed
form; windows whose check fails are flagged (``ok`` False) for the caller's
dense fallback. Windows are processed in SIMD lanes and threads as in
:mod:`lrmfrf._compiled`.

Several output rows share a window's input and transient columns, as in
:func:`lrmfrf._compiled.solve_windows`: with those ``n_s`` columns first and
each row's ``R_e`` denominator columns last,

    G = [[G11, G12], [G21, G22]],   L = [[L11, 0], [L21, L22]],
    K = L^-1 = [[K11, 0], [X, K22]],  K11 = L11^-1,  K22 = L22^-1,
    X = -K22 L21 K11,

so ``G^-1 = K^H K`` has the leading block ``K11^H K11 + X^H X``. The factor
``L11``, its inverse ``K11`` and the Gram ``K11^H K11`` (the ``n_s^3`` work)
are computed once per window; each row adds its rows of ``L`` (the Schur
complement of its denominator columns), its rows ``[X, K22]`` of ``K`` and
their contribution to ``K^H K`` (``O(R_e p^2)`` work), then its ``H``,
``tr(G^-1 H)`` (``p^2``) and the band block from ``H G^-1[:, bands]``
(``p^2 n_bands / 2``, the lower triangle of ``H``).

:func:`solve_eiv_windows` fuses these terms into the closed-form solve of
:mod:`lrmfrf._compiled` (the estimators' route): each window's terms are
computed right after its solve, from the window data, moments and Cholesky
factor of ``G`` the solve has just built and from its refined denominator,
so the gather, the moments of ``G``, its factor and the denominator read of
:func:`eiv_windows` are not repeated (measured about 15 % of the closed form
with the default std, SISO and 2x2 alike). Only the solve's windows re-solved
by QR (rare) need :func:`eiv_windows` afterwards. Both give the same terms
bit for bit (the same step functions in the same order) when both kernels
were compiled alike. numba builds a kernel from the IR of the kernels it
calls, and that IR is not the same when they were compiled in the same
process and when they were loaded from its cache (which keeps their
optimised IR): two kernels built in the two states can contract other
multiply-adds and differ in the last bits (seen after deleting the cache
index of one of them; recompiling a kernel alone in the same state gives
its cached bits), which the terms multiply by the window's condition number
(1e9-1e11 for the LRM normal equations): up to about 1e-5 relative in the
worst windows.
"""

from __future__ import annotations

import numpy as np

from . import _compiled
from ._compiled import LANES
from ._jit_cache import key_caches_on

if _compiled.AVAILABLE:  # pragma: no branch
    from numba import njit

__all__ = ["eiv_windows", "solve_eiv_windows"]


def _eiv_range_py(
    U, Y, bins, den, powers, F, n_shared, n_shared_pairs, band_first, n_bands,
    q_basis, g_kind, g_a, g_b, g_nd, g_off, g_ptr, g_mom, g_coef, g_conj,
    g_const, g_n_moments, w_kind, w_a, w_b, w_nd, w_off, w_ptr, w_mom, w_coef,
    w_conj, w_const, w_n_moments, p, tol2, lead, trace, wsum, wmin, wmax,
    ok_out, first_group, stop_group,
):
    """Lane groups ``first_group..stop_group-1`` (one thread's share), every
    output row ``Y[o]``; results ``lead[o]``, ``trace[o]`` ... of each row."""
    P = U.shape[0]
    L = powers.shape[0]
    n = L // 2
    M = Y.shape[2] // 2
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
    n_packed = p * (p + 1) // 2
    Hr = np.empty((n_packed, LANES), f64)
    Hi = np.empty((n_packed, LANES), f64)
    scale2 = np.empty((p, LANES), f64)
    ok_shared = np.empty(LANES, np.bool_)
    ok = np.empty(LANES, np.bool_)
    k = np.empty(LANES, np.int64)
    (mwr, mwi, Wr, Wi, Kr, Ki, Sh_r, Sh_i, Cr, Ci, cbr, cbi, ybr, ybi, qr, qi,
     acc_r, wt) = _row_scratch(p, n_shared, n_bands, L, w_n_moments)
    B = bins.shape[0]
    shared_entries = n_shared * (n_shared + 1) // 2
    n_g_pairs = g_kind.shape[0]
    for group in range(first_group, stop_group):
        first = group * LANES
        for w in range(LANES):
            k[w] = bins[min(first + w, B - 1)]
        # 1. shared by the rows: the inputs' window data, the Gram block of
        # the input and transient columns, its factor L11, K11 = L11^-1 and
        # K11^H K11
        _compiled._gather_inputs(U, M, k, F, n, sr, si)
        for t in range(n_shared_pairs):
            _compiled._pair_series(sr, si, g_kind[t], g_a[t], g_b[t], Sr, Si)
            _compiled._moments(Sr, Si, q_basis, g_off[t], g_nd[t], Er, Ei, Or,
                               Oi, mr, mi)
        _compiled._gram_entries(mr, mi, g_ptr, g_mom, g_coef, g_conj, g_const,
                                0, shared_entries, Hr, Hi)
        for w in range(LANES):
            ok_shared[w] = True
        _compiled._cholesky_rows(Hr, Hi, scale2, ok_shared, tol2, 0, n_shared)
        _inverse_rows(Hr, Hi, 0, n_shared, Kr, Ki)
        _lower_gram_rows(Kr, Ki, 0, n_shared, n_shared, Sh_r, Sh_i)
        for o in range(Y.shape[0]):
            # 2. this row's denominator columns: its rows of G and L, and
            # its rows [X, K22] of K = L^-1
            _compiled._gather_output(Y[o], k, F, n, sr, si)
            for t in range(n_shared_pairs, n_g_pairs):
                _compiled._pair_series(sr, si, g_kind[t], g_a[t], g_b[t], Sr, Si)
                _compiled._moments(Sr, Si, q_basis, g_off[t], g_nd[t], Er, Ei,
                                   Or, Oi, mr, mi)
            _compiled._gram_entries(mr, mi, g_ptr, g_mom, g_coef, g_conj,
                                    g_const, shared_entries, g_const.shape[0],
                                    Hr, Hi)
            for w in range(LANES):
                ok[w] = ok_shared[w]
            _compiled._cholesky_rows(Hr, Hi, scale2, ok, tol2, n_shared, p)
            _inverse_rows(Hr, Hi, n_shared, p, Kr, Ki)
            # 3.-5. this row's w(r) = |e(x_r)|^2, then its G^-1, H, trace
            # and band block (_row_terms)
            _denominator_weight(den[o], powers, first, wt)
            _row_terms(
                Kr, Ki, Sh_r, Sh_i, Cr, Ci, n_shared, p, sr, si, wt, w_kind,
                w_a, w_b, w_nd, w_off, w_ptr, w_mom, w_coef, w_conj, w_const,
                q_basis, Sr, Si, Er, Ei, Or, Oi, mwr, mwi, Wr, Wi, acc_r,
                P, first, band_first, n_bands, cbr, cbi, ybr, ybi, qr, qi,
                trace[o], wsum[o], wmin[o], wmax[o], lead[o],
            )
            for w in range(LANES):
                if first + w < B:
                    ok_out[o, first + w] = ok[w]


def _row_scratch_py(p, n_shared, n_bands, L, w_n_moments):
    """Work arrays of :func:`_row_terms_py`: the weighted moments and ``H``
    (``W``), ``K = L^-1``, the shared ``K11^H K11`` (``Sh``) and ``G^-1``
    (``C``), packed lower, the band-block temporaries, a lane accumulator
    (the trace) and the squared denominator ``wt``."""
    f64 = np.float64
    n_packed = p * (p + 1) // 2
    n_packed_shared = n_shared * (n_shared + 1) // 2
    return (
        np.empty((w_n_moments, LANES), f64), np.empty((w_n_moments, LANES), f64),
        np.empty((n_packed, LANES), f64), np.empty((n_packed, LANES), f64),
        np.empty((n_packed, LANES), f64), np.empty((n_packed, LANES), f64),
        np.empty((n_packed_shared, LANES), f64),
        np.empty((n_packed_shared, LANES), f64),
        np.empty((n_packed, LANES), f64), np.empty((n_packed, LANES), f64),
        np.empty((p, n_bands, LANES), f64), np.empty((p, n_bands, LANES), f64),
        np.empty((p, n_bands, LANES), f64), np.empty((p, n_bands, LANES), f64),
        np.empty((n_bands, n_bands, LANES), f64),
        np.empty((n_bands, n_bands, LANES), f64),
        np.empty(LANES, f64), np.empty((L, LANES), f64),
    )


def _row_terms_py(
    Kr, Ki, Sh_r, Sh_i, Cr, Ci, n_shared, p, sr, si, wt, w_kind, w_a, w_b, w_nd,
    w_off, w_ptr, w_mom, w_coef, w_conj, w_const, q_basis, Sr, Si, Er, Ei, Or,
    Oi, mwr, mwi, Wr, Wi, acc_r, P, first, band_first, n_bands, cbr, cbi,
    ybr, ybi, qr, qi, trace, wsum, wmin, wmax, lead,
):
    """One output row's terms of the windows ``first + w``, given ``K = L^-1``
    (its rows ``n_shared..p-1`` this row's), the shared ``K11^H K11`` in
    ``Sh`` and the row's squared denominator ``wt``: ``G^-1`` (in ``C``),
    ``H`` (in ``W``), ``trace``, ``wsum``/``wmin``/``wmax`` and the band block
    ``lead`` of the real lanes (shared by :func:`_eiv_range_py` and the fused
    :func:`_solve_eiv_range_py`)."""
    L = wt.shape[0]
    B = trace.shape[0]
    # H = A^H diag(w) A: every pair series times w before its moments
    for t in range(w_kind.shape[0]):
        _compiled._pair_series(sr, si, w_kind[t], w_a[t], w_b[t], Sr, Si)
        for r in range(L):
            for w in range(LANES):
                Sr[r, w] *= wt[r, w]
                Si[r, w] *= wt[r, w]
        _compiled._moments(Sr, Si, q_basis, w_off[t], w_nd[t], Er, Ei, Or, Oi,
                           mwr, mwi)
    _compiled._gram_entries(mwr, mwi, w_ptr, w_mom, w_coef, w_conj, w_const, 0,
                            w_const.shape[0], Wr, Wi)
    # G^-1 = K^H K (lower): the sums over this row's rows of K plus the
    # shared K11^H K11, and tr(G^-1 H) as each entry is made
    _gram_and_trace(Kr, Ki, Sh_r, Sh_i, Wr, Wi, n_shared, p, Cr, Ci, acc_r)
    # the outputs of the real lanes
    for w in range(LANES):
        row = first + w
        if row < B:
            trace[row] = acc_r[w]
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
    _band_sandwich(Cr, Ci, Wr, Wi, p, band_first, n_bands, first, B, cbr, cbi,
                   ybr, ybi, qr, qi, lead)


def _solve_eiv_range_py(
    U, Y, bins, weights, col_base, data_index, F, n_centre, n_tail, n_shared,
    n_shared_pairs, q_basis, pair_kind, pair_a, pair_b, pair_nd, pair_off,
    ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef,
    n_moments, to_layout, fallback_tol, refine_tol, refine_steps, theta, rss, cvar,
    fast, den_cols, powers, w_kind, w_a, w_b, w_nd, w_off, w_ptr, w_mom, w_coef,
    w_conj, w_const, w_n_moments, lead, trace, wsum, wmin, wmax, first_group,
    stop_group,
):
    """The closed form of :func:`lrmfrf._compiled._solve_range` and the
    errors-in-variables terms of :func:`_eiv_range` in one pass: the terms
    reuse the solve's window data, Gram factor and refined denominator."""
    P = U.shape[0]
    L, p = weights.shape
    n = L // 2
    s = _compiled._scratch(F, P, L, p, n_moments, n_centre, n_tail)
    (sr, si, Sr, Si, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr, gi, xr, xi, dr, di,
     scale2, polyr, polyi, resr, resi, ok_shared, ok, change_num, change_den, k,
     tr, ti, cr, ci) = s
    n_packed_shared = n_shared * (n_shared + 1) // 2
    n_bands = F
    band_first = n_shared - n_centre
    (mwr, mwi, Wr, Wi, Kr, Ki, Sh_r, Sh_i, Cr, Ci, cbr, cbi, ybr, ybi, qr, qi,
     acc_r, wt) = _row_scratch(p, n_shared, n_bands, L, w_n_moments)
    B = bins.shape[0]
    n_pairs = pair_kind.shape[0]
    shared_entries = n_packed_shared
    tol2 = fallback_tol * fallback_tol
    for group in range(first_group, stop_group):
        first = group * LANES
        for w in range(LANES):
            k[w] = bins[min(first + w, B - 1)]
        # steps 1-4 of lrmfrf._compiled._lane_group: the inputs' window data,
        # moments, shared Gram block and its factor L11
        _compiled._gather_inputs(U, Y.shape[2] // 2, k, F, n, sr, si)
        for t in range(n_shared_pairs):
            _compiled._pair_series(sr, si, pair_kind[t], pair_a[t], pair_b[t],
                                   Sr, Si)
            _compiled._moments(Sr, Si, q_basis, pair_off[t], pair_nd[t], Er, Ei,
                               Or, Oi, mr, mi)
        _compiled._gram_entries(mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj,
                                ent_const, 0, shared_entries, Hr, Hi)
        for w in range(LANES):
            ok_shared[w] = True
        _compiled._cholesky_rows(Hr, Hi, scale2, ok_shared, tol2, 0, n_shared)
        # eiv, shared by the rows: K11 = L11^-1 and K11^H K11
        _inverse_rows(Hr, Hi, 0, n_shared, Kr, Ki)
        _lower_gram_rows(Kr, Ki, 0, n_shared, n_shared, Sh_r, Sh_i)
        for o in range(Y.shape[0]):
            # steps 5-9 of _lane_group: this row's solve
            _compiled._gather_output(Y[o], k, F, n, sr, si)
            for t in range(n_shared_pairs, n_pairs):
                _compiled._pair_series(sr, si, pair_kind[t], pair_a[t], pair_b[t],
                                       Sr, Si)
                _compiled._moments(Sr, Si, q_basis, pair_off[t], pair_nd[t], Er,
                                   Ei, Or, Oi, mr, mi)
            _compiled._gram_entries(mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj,
                                    ent_const, shared_entries, ent_const.shape[0],
                                    Hr, Hi)
            _compiled._rhs(mr, mi, rhs_ptr, rhs_mom, rhs_coef, gr, gi)
            for w in range(LANES):
                ok[w] = ok_shared[w]
            _compiled._cholesky_rows(Hr, Hi, scale2, ok, tol2, n_shared, p)
            _compiled._solve_refined(
                sr, si, Hr, Hi, gr, gi, xr, xi, dr, di, scale2, weights,
                col_base, data_index, F, polyr, polyi, resr, resi, change_num,
                change_den, refine_steps, p,
            )
            _compiled._tail_inverse(Hr, Hi, tr.shape[0], p, tr, ti)
            _compiled._tail_cov(tr, ti, n_centre, cr, ci)
            _compiled._to_layout(xr, xi, to_layout, dr, di)
            _compiled._write_lanes(
                first, B, dr, di, resr, resi, change_num, change_den, ok, cr, ci,
                refine_tol, refine_steps, theta[o], rss[o], cvar[o], fast[o],
            )
            # eiv terms of this row (steps 2-5 of _eiv_range) from the same
            # factor and window data, with the refined denominator (in dr/di)
            _inverse_rows(Hr, Hi, n_shared, p, Kr, Ki)
            _lane_denominator_weight(dr, di, den_cols, ok, powers, wt)
            _row_terms(
                Kr, Ki, Sh_r, Sh_i, Cr, Ci, n_shared, p, sr, si, wt, w_kind,
                w_a, w_b, w_nd, w_off, w_ptr, w_mom, w_coef, w_conj, w_const,
                q_basis, Sr, Si, Er, Ei, Or, Oi, mwr, mwi, Wr, Wi, acc_r,
                P, first, band_first, n_bands, cbr, cbi, ybr, ybi, qr, qi,
                trace[o], wsum[o], wmin[o], wmax[o], lead[o],
            )


def _lane_denominator_weight_py(dr, di, den_cols, ok, powers, wt):
    """``wt[r, w] = |e(x_r)|^2`` from the layout-order parameters ``dr/di``
    of each lane (the denominator at ``den_cols``; ``e = 1`` where ``ok`` is
    False), the sums of :func:`_denominator_weight` in the same order."""
    L, Re = powers.shape
    for r in range(L):
        for w in range(LANES):
            er = 1.0
            ei = 0.0
            if ok[w]:
                for s in range(Re):
                    er += dr[den_cols[s], w] * powers[r, s]
                    ei += di[den_cols[s], w] * powers[r, s]
            wt[r, w] = er * er + ei * ei


def _denominator_weight_py(den, powers, first, wt):
    """``wt[r, w] = |e(x_r)|^2`` of the windows ``first + w`` (the last window
    repeated in unused lanes); ``den`` of shape (B, R_e, 2)."""
    B = den.shape[0]
    L, Re = powers.shape
    for r in range(L):
        for w in range(LANES):
            row = min(first + w, B - 1)
            er = 1.0
            ei = 0.0
            for s in range(Re):
                er += den[row, s, 0] * powers[r, s]
                ei += den[row, s, 1] * powers[r, s]
            wt[r, w] = er * er + ei * ei


def _inverse_rows_py(Hr, Hi, lo, hi, Kr, Ki):
    """Rows ``lo..hi-1`` of ``K = L^-1`` (``L`` packed lower, inverse pivots
    in ``Hi`` at the diagonal; ``K`` packed lower), rows ``0..lo-1`` of ``K``
    given: ``K_ii = 1 / L_ii``, ``K_ic = -(sum_{m=c}^{i-1} L_im K_mc) /
    L_ii``.

    Row ``i`` is accumulated in place as ``sum_m L_im K[m, :m+1]``: each step
    streams one row of ``K`` (contiguous when packed) into row ``i`` (a few
    kB, cache-resident), where a sum per entry would read a column of ``K``,
    one far cache line per term (the MIMO blocks, n_s = 40, are MBs over the
    lanes)."""
    for i in range(lo, hi):
        ri = i * (i + 1) // 2
        inv = ri + i
        for c in range(i):
            for w in range(LANES):
                Kr[ri + c, w] = 0.0
                Ki[ri + c, w] = 0.0
        for m in range(i):
            rm = m * (m + 1) // 2
            for c in range(m + 1):
                for w in range(LANES):
                    lr = Hr[ri + m, w]
                    li = Hi[ri + m, w]
                    kr = Kr[rm + c, w]
                    ki = Ki[rm + c, w]
                    Kr[ri + c, w] += lr * kr - li * ki
                    Ki[ri + c, w] += lr * ki + li * kr
        for c in range(i):
            for w in range(LANES):
                Kr[ri + c, w] *= -Hi[inv, w]
                Ki[ri + c, w] *= -Hi[inv, w]
        for w in range(LANES):
            Kr[inv, w] = Hi[inv, w]
            Ki[inv, w] = 0.0


def _lower_gram_rows_py(Kr, Ki, lo, hi, n, Cr, Ci):
    """Lower triangle (packed) of ``sum_{i=lo}^{hi-1} conj(K[i, :n])^T
    K[i, :n]`` (``K`` lower triangular, packed: the sum for ``C[c, d]``,
    ``c >= d``, starts at ``i = max(lo, c)``).

    Row ``c`` of ``C`` is accumulated in place from the rows ``K[i, :c+1]``
    (contiguous), as in :func:`_inverse_rows`."""
    for c in range(n):
        rc = c * (c + 1) // 2
        for d in range(c + 1):
            for w in range(LANES):
                Cr[rc + d, w] = 0.0
                Ci[rc + d, w] = 0.0
        for i in range(max(lo, c), hi):
            ri = i * (i + 1) // 2
            for d in range(c + 1):
                for w in range(LANES):
                    # conj(K[i,c]) K[i,d]
                    kcr = Kr[ri + c, w]
                    kci = Ki[ri + c, w]
                    kdr = Kr[ri + d, w]
                    kdi = Ki[ri + d, w]
                    Cr[rc + d, w] += kcr * kdr + kci * kdi
                    Ci[rc + d, w] += kcr * kdi - kci * kdr


def _gram_and_trace_py(Kr, Ki, Sh_r, Sh_i, Wr, Wi, lo, p, Cr, Ci, acc_r):
    """``C = K^H K`` (packed lower) from this row's rows ``lo..p-1`` of ``K``
    plus the shared ``Sh = K11^H K11`` on the leading block, and ``acc_r =
    tr(C W)`` (``W`` Hermitian, packed lower) in the same pass.

    Each entry is the sum over the rows ``i`` in ascending order, then plus
    ``Sh``, and the trace takes row ``c``'s diagonal before its other
    entries: the results of :func:`_lower_gram_rows`, the ``Sh`` add and a
    separate trace, bit for bit, without streaming ``C`` and ``W`` (MBs over
    the lanes for MIMO blocks) a second time and with each entry's
    accumulator cache-resident while its ``i`` sum runs (11 % less time for
    these steps at the 2x2 default, p = 47)."""
    for w in range(LANES):
        acc_r[w] = 0.0
    for c in range(p):
        rc = c * (c + 1) // 2
        start = max(lo, c)
        for dd in range(c + 1):
            d = c if dd == 0 else dd - 1  # the diagonal first
            e = rc + d
            for w in range(LANES):
                Cr[e, w] = 0.0
                Ci[e, w] = 0.0
            for i in range(start, p):
                ri = i * (i + 1) // 2
                for w in range(LANES):
                    # conj(K[i,c]) K[i,d]
                    kcr = Kr[ri + c, w]
                    kci = Ki[ri + c, w]
                    kdr = Kr[ri + d, w]
                    kdi = Ki[ri + d, w]
                    Cr[e, w] += kcr * kdr + kci * kdi
                    Ci[e, w] += kcr * kdi - kci * kdr
            if c < lo:
                for w in range(LANES):
                    Cr[e, w] += Sh_r[e, w]
                    Ci[e, w] += Sh_i[e, w]
            if dd == 0:  # the diagonal of C and W is real
                for w in range(LANES):
                    acc_r[w] += Cr[e, w] * Wr[e, w]
            else:
                for w in range(LANES):
                    acc_r[w] += 2.0 * (Cr[e, w] * Wr[e, w] + Ci[e, w] * Wi[e, w])


def _band_sandwich_py(Cr, Ci, Wr, Wi, p, band_first, n_bands, first, B, cbr, cbi,
                      ybr, ybi, qr, qi, lead):
    """``lead[first + w] = C_b^H W C_b``, ``C_b = C[:, band_first:band_first +
    n_bands]`` (``C`` and ``W`` Hermitian, packed lower) from the lower
    triangle of ``W`` only: with ``W = W' + W'^H``, ``W'`` its strict lower
    triangle plus half its diagonal, ``Y = W' C_b`` (``p^2 n_bands / 2``
    products) and ``Q = C_b^H Y``, the sandwich is ``Q + Q^H``."""
    for j in range(p):  # C_b from the lower triangle of C
        for b in range(n_bands):
            cb = band_first + b
            if j >= cb:
                e = j * (j + 1) // 2 + cb
                for w in range(LANES):
                    cbr[j, b, w] = Cr[e, w]
                    cbi[j, b, w] = Ci[e, w]
            else:
                e = cb * (cb + 1) // 2 + j
                for w in range(LANES):
                    cbr[j, b, w] = Cr[e, w]
                    cbi[j, b, w] = -Ci[e, w]
    for i in range(p):
        ri = i * (i + 1) // 2
        for b in range(n_bands):
            for w in range(LANES):
                half = 0.5 * Wr[ri + i, w]  # the diagonal of W is real
                ybr[i, b, w] = half * cbr[i, b, w]
                ybi[i, b, w] = half * cbi[i, b, w]
        for j in range(i):
            for b in range(n_bands):
                for w in range(LANES):
                    hr = Wr[ri + j, w]
                    hi = Wi[ri + j, w]
                    vr = cbr[j, b, w]
                    vi = cbi[j, b, w]
                    ybr[i, b, w] += hr * vr - hi * vi
                    ybi[i, b, w] += hr * vi + hi * vr
    for a in range(n_bands):
        for b in range(n_bands):
            for w in range(LANES):
                qr[a, b, w] = 0.0
                qi[a, b, w] = 0.0
            for i in range(p):
                for w in range(LANES):
                    # conj(C_b[i, a]) Y[i, b]
                    vr = cbr[i, a, w]
                    vi = cbi[i, a, w]
                    qr[a, b, w] += vr * ybr[i, b, w] + vi * ybi[i, b, w]
                    qi[a, b, w] += vr * ybi[i, b, w] - vi * ybr[i, b, w]
    for w in range(LANES):
        row = first + w
        if row < B:
            for a in range(n_bands):
                for b in range(n_bands):
                    lead[row, a, b, 0] = qr[a, b, w] + qr[b, a, w]
                    lead[row, a, b, 1] = qi[a, b, w] - qi[b, a, w]


if _compiled.AVAILABLE:  # pragma: no branch
    _opts = {"cache": True, "fastmath": {"contract"}, "nogil": True,
             "error_model": "numpy"}
    _denominator_weight = njit(**_opts)(_denominator_weight_py)
    _inverse_rows = njit(**_opts)(_inverse_rows_py)
    _lower_gram_rows = njit(**_opts)(_lower_gram_rows_py)
    _gram_and_trace = njit(**_opts)(_gram_and_trace_py)
    _band_sandwich = njit(**_opts)(_band_sandwich_py)
    _row_terms = njit(**_opts)(_row_terms_py)
    _row_scratch = njit(**_opts)(_row_scratch_py)
    _eiv_range = njit(**_opts)(_eiv_range_py)
    _lane_denominator_weight = njit(**_opts)(_lane_denominator_weight_py)
    _solve_eiv_range = njit(**_opts)(_solve_eiv_range_py)
    # these kernels inline _compiled's steps and LANES: numba's cache does not
    # see that file change (lrmfrf._jit_cache)
    key_caches_on(globals(), [_compiled.__file__])


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
    """Errors-in-variables terms of every window and output row (compiled,
    threaded).

    Parameters
    ----------
    U : ndarray of shape (P, N) or (P, n_u, N), complex
    Y : ndarray of shape (P, M) or (P, n_rows, M), complex
        One output row, or ``n_rows`` rows whose windows share the input and
        transient columns.
    slow_bins : ndarray of shape (B,), int
    den : ndarray of shape (B, R_e) or (n_rows, B, R_e), complex
        Denominator coefficients ``e_1..e_Re`` of each window (finite) of
        each row.
    powers : ndarray of shape (2n+1, R_e)
        ``x_r^s``, ``s = 1..R_e``.
    weights, col_base : ndarray
        Internal column basis with the denominator columns (``col_base ==
        n_bands + P``) last (see :func:`lrmfrf.solvers._kernel_tables`).
    n_bands : int
        Number of input bands ``F n_u``; the band columns are the first of
        the ``n_centre`` columns before the denominator columns.
    n_centre : int
    tables, weighted_tables : dict
        :func:`lrmfrf._compiled.moment_tables` of ``weights`` and
        ``col_base`` without and with ``weighted=True``.
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

    With ``Y`` of shape (P, n_rows, M) every result has a leading axis of
    length ``n_rows``.
    """
    B, p = slow_bins.size, weights.shape[1]
    P = U.shape[0]
    if U.ndim == 2:
        U = U[:, None, :]
    one_row = Y.ndim == 2
    rows_first = np.moveaxis(Y[:, None, :] if one_row else Y, 1, 0)  # (R, P, M)
    R = rows_first.shape[0]
    den = np.asarray(den, dtype=np.complex128)
    if one_row:
        den = den[None]
    is_den = np.asarray(col_base) == n_bands + P
    n_shared = p - int(np.count_nonzero(is_den))
    if is_den[:n_shared].any():
        raise ValueError(
            "the denominator columns (col_base == n_bands + P) must come last; "
            "use the tables of lrmfrf.solvers._kernel_tables"
        )
    t, tw = tables, weighted_tables
    n_g = t["pair_kind"].size
    if not all(np.array_equal(t[key], tw[key][:n_g])
               for key in ("pair_kind", "pair_a", "pair_b", "pair_nd")):
        raise ValueError("tables and weighted_tables must be of the same layout")
    # the pairs with -Y (data index F first, or against a transient) come last
    with_y = (((t["pair_kind"] == _compiled._DATA_DATA) & (t["pair_a"] == n_bands))
              | (t["pair_kind"] == _compiled._DATA_CONST))
    n_shared_pairs = int(np.argmax(with_y)) if with_y.any() else with_y.size
    lead = np.empty((R, B, n_bands, n_bands, 2))
    trace = np.empty((R, B))
    wsum = np.empty((R, B))
    wmin = np.empty((R, B))
    wmax = np.empty((R, B))
    ok = np.empty((R, B), dtype=np.bool_)
    den2 = np.ascontiguousarray(den).view(np.float64).reshape(R, B, -1, 2)
    args = (
        _compiled._as_interleaved(U), _compiled._as_interleaved(rows_first),
        np.ascontiguousarray(slow_bins, dtype=np.int64), den2,
        np.ascontiguousarray(powers, dtype=np.float64), int(n_bands),
        n_shared, n_shared_pairs, int(n_shared - n_centre), int(n_bands),
        t["q_basis"], t["pair_kind"], t["pair_a"], t["pair_b"], t["pair_nd"],
        t["pair_off"], t["ent_ptr"], t["ent_mom"], t["ent_coef"], t["ent_conj"],
        t["ent_const"], int(t["n_moments"]),
        tw["pair_kind"], tw["pair_a"], tw["pair_b"], tw["pair_nd"], tw["pair_off"],
        tw["ent_ptr"], tw["ent_mom"], tw["ent_coef"], tw["ent_conj"],
        tw["ent_const"], int(tw["n_moments"]), int(p),
        float(fallback_tol) ** 2, lead, trace, wsum, wmin, wmax, ok,
    )
    _compiled.run_lane_groups(_eiv_range, args, B, n_threads)
    lead = lead.view(np.complex128)[..., 0]
    out = (lead, trace, wsum, wmin, wmax, ok)
    return tuple(part[0] for part in out) if one_row else out


def solve_eiv_windows(
    U: np.ndarray,
    Y: np.ndarray,
    slow_bins: np.ndarray,
    weights: np.ndarray,
    col_base: np.ndarray,
    F: int,
    n_centre: int,
    *,
    den_columns: np.ndarray,
    powers: np.ndarray,
    tables: dict,
    weighted_tables: dict,
    to_layout: np.ndarray,
    fallback_tol: float,
    refine_tol: float,
    refine_steps: int,
    n_threads: int | None = None,
):
    """:func:`lrmfrf._compiled.solve_windows` and :func:`eiv_windows` of its
    solution in one pass.

    The errors-in-variables terms of each window and row are computed right
    after its closed-form solve, from the solve's window data, Cholesky factor
    of ``G`` and refined denominator (instead of gathering, factoring and
    reading the denominator again): the same terms as :func:`eiv_windows` on
    the returned ``theta`` up to round-off, wherever ``fast`` is True (where
    it is False the caller re-solves the window, and the terms of the new
    solution must be computed again).

    Parameters
    ----------
    U, Y, slow_bins, weights, col_base, F, n_centre
        As in :func:`lrmfrf._compiled.solve_windows` (the denominator columns
        last; ``F`` the number of input bands).
    den_columns : ndarray of shape (R_e,), int
        The denominator's columns ``e_1..e_Re`` in the layout order of
        ``theta`` (after ``to_layout``).
    powers : ndarray of shape (2n+1, R_e)
        ``x_r^s``, ``s = 1..R_e``.
    tables, weighted_tables : dict
        :func:`lrmfrf._compiled.moment_tables` of ``weights`` and
        ``col_base``, without and with ``weighted=True``.
    to_layout : ndarray of shape (p, p)
    fallback_tol, refine_tol : float
    refine_steps : int
    n_threads : int, optional

    Returns
    -------
    solution : tuple
        ``(theta, rss, centre_cov, fast)`` of ``solve_windows(...,
        return_cov=True)``.
    terms : tuple
        ``(lead, hw_trace, w_sum, w_min, w_max)`` of :func:`eiv_windows`
        (its ``ok`` is the solve's pivot check, part of ``fast``).

    With ``Y`` of shape (P, n_rows, M) every result has a leading axis of
    length ``n_rows``.
    """
    args, outputs, one_row = _compiled._solve_arguments(
        U, Y, slow_bins, weights, col_base, F, n_centre, fallback_tol,
        refine_tol, refine_steps, tables, to_layout,
    )
    R, B = outputs[1].shape
    t, tw = tables, weighted_tables
    n_g = t["pair_kind"].size
    if not all(np.array_equal(t[key], tw[key][:n_g])
               for key in ("pair_kind", "pair_a", "pair_b", "pair_nd")):
        raise ValueError("tables and weighted_tables must be of the same layout")
    lead = np.empty((R, B, F, F, 2))
    trace = np.empty((R, B))
    wsum = np.empty((R, B))
    wmin = np.empty((R, B))
    wmax = np.empty((R, B))
    args = args + (
        np.ascontiguousarray(den_columns, dtype=np.int64),
        np.ascontiguousarray(powers, dtype=np.float64),
        tw["pair_kind"], tw["pair_a"], tw["pair_b"], tw["pair_nd"], tw["pair_off"],
        tw["ent_ptr"], tw["ent_mom"], tw["ent_coef"], tw["ent_conj"],
        tw["ent_const"], int(tw["n_moments"]), lead, trace, wsum, wmin, wmax,
    )
    _compiled.run_lane_groups(_solve_eiv_range, args, B, n_threads)
    solution = _compiled._solve_results(outputs, one_row, True)
    terms = (lead.view(np.complex128)[..., 0], trace, wsum, wmin, wmax)
    if one_row:
        terms = tuple(part[0] for part in terms)
    return solution, terms
