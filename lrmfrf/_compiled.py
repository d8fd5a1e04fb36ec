"""Compiled kernel of the fast closed form (optional, needs numba).

:func:`solve_windows` does, for every window and output row, what
:func:`lrmfrf.solvers.solve_local_normal_equations` does with array
operations: gather the window data from the DFTs, build the Gram matrix
``A^H A`` and ``A^H b`` from polynomial moments of the products of the window
sequences, Cholesky-factorise it with the equilibrated pivot check, solve,
refine once with the explicit residual ``b - A theta``, and compute the
centre-column diagonal of ``(A^H A)^-1``.

Layout of the work ("lanes"): windows are processed ``LANES`` at a time, and
every per-window quantity is stored with the lane index last, real and
imaginary parts apart. Every inner loop then runs over the lanes with unit
stride, which the compiler turns into SIMD instructions: the small dense
linear algebra of one window (a 27 x 27 complex Cholesky for the paper's
degrees) is vectorised *across* windows instead of within one. Groups of
lanes are shared by threads (the kernel releases the GIL; numba's own
``parallel=True`` doubled the compile time for nothing).

Structure used (all exact up to round-off):

- every column of ``A`` is a real basis polynomial ``w_i(r)`` times a base
  sequence (an input band ``U(k+r+fM)``, the constant of a transient, or
  ``-Y(k+r)``), so a Gram entry is ``sum_r w_i(r) w_j(r) S_ab(r)`` with the
  pair series ``S_ab = sum_q conj(s_a) s_b``. The products ``w_i w_j`` are
  expanded in an orthonormal polynomial basis ``q_d`` of the window, so the
  whole Gram matrix needs only the moments ``m_ab[d] = sum_r q_d(r) S_ab(r)``
  (``moment_tables``);
- the window is symmetric and the ``q_d`` and ``w_i`` are even or odd in
  ``r``: a moment is a sum over ``r >= 0`` of ``S(r) +- S(-r)`` (half the
  work), and half of the expansion coefficients are exactly zero and skipped;
- the transient-transient block is the same in every window (a constant);
- the columns of the inputs and transients do not depend on the output: with
  the denominator columns (``-Y``) last, their Gram block, moments and
  Cholesky rows are built once per window for all output rows, and each row
  adds only its own trailing rows of the factor (the Schur complement of its
  denominator columns). The centre block of ``(A^H A)^-1`` is then read from
  the inverse of the factor's tail from the centre columns on.

Compiled with ``cache=True``; the only fast-math flag is ``contract`` (fused
multiply-add, which rounds once instead of twice), so results equal the numpy
path up to round-off. Import never fails without numba: see
:data:`AVAILABLE`.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

try:  # pragma: no cover - exercised when numba is installed
    import numba
    from numba import njit

    AVAILABLE = True
except ImportError:  # pragma: no cover - exercised when numba is absent
    numba = None
    AVAILABLE = False

__all__ = ["AVAILABLE", "LANES", "moment_tables", "solve_windows"]

#: Windows solved together in SIMD lanes. Loops over 32 lanes or fewer are
#: fully unrolled by LLVM and then not vectorised (it cannot prove that the
#: scratch rows do not alias); longer ones vectorise behind runtime alias
#: checks, whose cost per loop favours long loops, while the scratch (one
#: cache line per 8 lanes and matrix entry) favours short ones once the
#: errors-in-variables terms and MIMO layouts make it MBs. Measured with the
#: default degrees, F = 3, one thread, on the N = 1.2e5 records of
#: ``benchmarks/speed.py`` (closed form with the eiv terms, per window; solve
#: alone in brackets): 15.3 (7.0), 12.8-13.4 (6.0), 14.6-15.5 (6.7-7.1) and
#: 14.0-14.9 (6.6) us with 48, 64, 96 and 128 lanes; the 2x2 record's fit
#: is fastest at 64 lanes too.
LANES = 64

#: Lane groups a thread takes at a time from the shared queue (at most).
_GROUPS_PER_TASK = 8

#: Pair kinds of the moment tables.
_DATA_DATA, _CONST_DATA, _DATA_CONST, _ONES = 0, 1, 2, 3


# ---------------------------------------------------------------------------
# tables (per layout, data-independent)
# ---------------------------------------------------------------------------


def moment_tables(
    weights: np.ndarray, col_base: np.ndarray, F: int, P: int, *,
    weighted: bool = False,
) -> dict:
    """Per-layout tables of the moment form of the normal equations.

    Parameters
    ----------
    weights : ndarray of shape (2n+1, p)
        Basis polynomial of each column on the window (internal order of
        :class:`lrmfrf.windows.StructuredWindows`).
    col_base : ndarray of shape (p,), int
        Base sequence of each column: ``f < F`` the input band ``f``,
        ``F + q`` the transient constant of experiment ``q``, ``F + P`` the
        sequence ``-Y``.
    F, P : int
    weighted : bool, default=False
        Tables for row-weighted problems (Sanathanan-Koerner): the
        transient-transient block is then no constant but a moment of the
        weight itself, a pair of kind ``_ONES`` (series 1) added last.

    Returns
    -------
    dict of ndarrays
        ``q_basis`` (2n+1, D): orthonormal polynomials on the window, ``q_d``
        of parity ``d``. One entry per base pair ``t`` (``a >= b`` in base
        code, not both constants): ``pair_kind``, ``pair_a``, ``pair_b``
        (data index ``0..F`` with ``F`` for ``-Y``, or experiment), ``pair_nd``
        moments from ``pair_off``. The packed lower Gram entry ``e = I(I+1)/2
        + J`` is ``ent_const[e] + sum coef * m`` over
        ``ent_ptr[e]:ent_ptr[e+1]`` of ``ent_mom``/``ent_coef``, conjugated
        where ``ent_conj``. ``A^H b`` at column ``I`` is ``-conj(sum coef *
        m)`` over ``rhs_ptr``/``rhs_mom``/``rhs_coef``. ``data_index`` maps a
        base code to its data index (``-1`` for constants).
    """
    weights = np.asarray(weights, dtype=float)
    col_base = np.asarray(col_base, dtype=np.int64)
    L, p = weights.shape
    n = L // 2
    den_code = F + P
    x = (np.arange(L) - n) / max(n, 1)
    deg = _degrees(x, weights)
    top = np.zeros(F + P + 1, dtype=np.int64)
    for i in range(p):
        top[col_base[i]] = max(top[col_base[i]], deg[i])
    q_basis = _parity_basis(x, min(L - 1, 2 * int(top.max())))

    def data_index(code):
        if code < F:
            return code
        return F if code == den_code else -1

    pairs = {}
    kind, pa, pb, pnd, poff = [], [], [], [], []
    offset = 0
    for a in range(F + P + 1):
        for b in range(a + 1):
            da, db = data_index(a), data_index(b)
            if da < 0 and db < 0:
                continue  # constant block
            if da >= 0 and db >= 0:
                kind.append(_DATA_DATA)
                pa.append(da)
                pb.append(db)
            elif da < 0:  # a constant (transient), b an input band
                kind.append(_CONST_DATA)
                pa.append(a - F)
                pb.append(db)
            else:  # a = -Y, b a transient constant
                kind.append(_DATA_CONST)
                pa.append(da)
                pb.append(b - F)
            nd = int(min(L, top[a] + top[b] + 1))
            pairs[(a, b)] = (len(kind) - 1, offset, nd)
            pnd.append(nd)
            poff.append(offset)
            offset += nd

    if weighted:  # the weight's own moments: the transient-transient block
        kind.append(_ONES)
        pa.append(0)
        pb.append(0)
        nd = int(min(L, 2 * top[F:F + P].max() + 1))
        pairs["ones"] = (len(kind) - 1, offset, nd)
        pnd.append(nd)
        poff.append(offset)
        offset += nd

    # the packed lower Gram entries: a constant, or moments of one pair (the
    # products of the two columns' polynomials expanded all at once)
    ent_conj, ent_const, ent_key, expanded = [], [], [], []
    for i in range(p):
        for j in range(i + 1):
            a, b = col_base[i], col_base[j]
            lo, hi = max(a, b), min(a, b)
            ent_conj.append(a < b)
            key = (lo, hi)
            if key not in pairs:  # both transient constants
                if not weighted or a != b:
                    product = weights[:, i] * weights[:, j]
                    ent_const.append(product.sum() if a == b else 0.0)
                    ent_key.append(None)
                    continue
                key = "ones"
            ent_const.append(0.0)
            ent_key.append(key)
            expanded.append((i, j, key))
    first = np.array([e[0] for e in expanded], dtype=np.int64)
    second = np.array([e[1] for e in expanded], dtype=np.int64)
    column, index, ent_coef = _expand_columns(
        q_basis, weights[:, first] * weights[:, second],
        [pairs[e[2]][2] for e in expanded])
    ent_mom = np.array([pairs[e[2]][1] for e in expanded],
                       dtype=np.int64)[column] + index
    # entry e's moments are ent_mom[ent_ptr[e]:ent_ptr[e+1]]; constants none
    moments = np.zeros(len(ent_key), dtype=np.int64)
    moments[[e for e, key in enumerate(ent_key) if key is not None]] = (
        np.bincount(column, minlength=len(expanded)))
    ent_ptr = np.concatenate([[0], np.cumsum(moments)])

    rhs_pairs = [pairs[(den_code, col_base[i])] for i in range(p)]
    column, index, rhs_coef = _expand_columns(
        q_basis, weights, [nd for _, _, nd in rhs_pairs])
    rhs_mom = np.array([off for _, off, _ in rhs_pairs],
                       dtype=np.int64)[column] + index
    rhs_ptr = np.concatenate([[0], np.cumsum(np.bincount(column, minlength=p))])

    as_int = lambda v: np.asarray(v, dtype=np.int64)  # noqa: E731
    return {
        "q_basis": np.ascontiguousarray(q_basis),
        "pair_kind": as_int(kind), "pair_a": as_int(pa), "pair_b": as_int(pb),
        "pair_nd": as_int(pnd), "pair_off": as_int(poff),
        "ent_ptr": as_int(ent_ptr), "ent_mom": as_int(ent_mom),
        "ent_coef": np.asarray(ent_coef, dtype=float),
        "ent_conj": np.asarray(ent_conj, dtype=np.bool_),
        "ent_const": np.asarray(ent_const, dtype=float),
        "rhs_ptr": as_int(rhs_ptr), "rhs_mom": as_int(rhs_mom),
        "rhs_coef": np.asarray(rhs_coef, dtype=float),
        "data_index": as_int([data_index(c) for c in range(F + P + 1)]),
        "n_moments": offset,
    }


def _parity_basis(x: np.ndarray, degree: int) -> np.ndarray:
    """Orthonormal polynomials of degree 0..degree on the symmetric grid ``x``,
    each exactly even or odd (QR of a Chebyshev Vandermonde matrix, condition
    number ~3, then the parity enforced)."""
    q, r = np.linalg.qr(np.polynomial.chebyshev.chebvander(x, degree))
    q = q * np.sign(np.diag(r))
    sign = (-1.0) ** np.arange(degree + 1)
    return 0.5 * (q + sign * q[::-1])


def _expand_columns(q_basis: np.ndarray, values: np.ndarray, nds):
    """Coefficients of every column ``values[:, e]`` in the orthonormal
    ``q_basis[:, :nds[e]]``, with one product of matrices (the first ``nd``
    coefficients in the whole basis are those in its first ``nd`` columns);
    coefficients that are zero by parity (round-off relative to the column's
    largest) are set to 0.

    Returns the nonzero coefficients, column by column and in increasing
    order within a column: ``(column, index, value)`` arrays.
    """
    nds = np.asarray(nds, dtype=np.int64)
    coef = q_basis.T @ values  # (D, E)
    coef[np.arange(q_basis.shape[1])[:, None] >= nds[None, :]] = 0.0
    error = np.max(np.abs(q_basis @ coef - values), axis=0, initial=0.0)
    scale = np.max(np.abs(values), axis=0, initial=0.0)
    if np.any(error > 1e-11 * np.maximum(scale, 1e-300)):
        raise AssertionError("moment expansion is not exact; degree bound wrong")
    largest = np.max(np.abs(coef), axis=0, initial=0.0)
    coef[np.abs(coef) <= 1e-13 * largest[None, :]] = 0.0
    column, index = np.nonzero(coef.T)
    return column, index, coef[index, column]


def _degrees(x, values):
    """Degree of the polynomial taking ``values[:, i]`` on the grid ``x``, for
    every column: the lowest Chebyshev fit whose residual is round-off (one
    fit of all columns per degree)."""
    p = values.shape[1]
    deg = np.full(p, x.size - 1, dtype=np.int64)
    scale = np.max(np.abs(values), axis=0)
    todo = scale > 0
    deg[~todo] = 0
    for d in range(x.size):
        if not todo.any():
            break
        part = values[:, todo]
        fit = np.polynomial.chebyshev.chebfit(x, part, d)
        residual = part - np.polynomial.chebyshev.chebval(x, fit).T
        done = np.max(np.abs(residual), axis=0) <= 1e-12 * scale[todo]
        index = np.flatnonzero(todo)[done]
        deg[index] = d
        todo[index] = False
    return deg


# ---------------------------------------------------------------------------
# the kernel (plain Python, compiled below when numba is available)
# ---------------------------------------------------------------------------


def _solve_range_py(
    U, Y, bins, weights, col_base, data_index, F, n_centre, n_tail, n_shared,
    n_shared_pairs, q_basis, pair_kind, pair_a, pair_b, pair_nd, pair_off,
    ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef,
    n_moments, to_layout, fallback_tol, refine_tol, refine_steps, theta, rss, cvar,
    fast, first_group, stop_group,
):
    """Lane groups ``first_group..stop_group-1`` (one thread's share)."""
    P = U.shape[0]
    L, p = weights.shape
    s = _scratch(F, P, L, p, n_moments, n_centre, n_tail)
    for group in range(first_group, stop_group):
        _lane_group(
            U, Y, bins, group * LANES, weights, col_base,
            data_index, F, n_centre, n_shared, n_shared_pairs, q_basis,
            pair_kind, pair_a, pair_b, pair_nd, pair_off, ent_ptr, ent_mom,
            ent_coef, ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef, to_layout,
            fallback_tol, refine_tol, refine_steps, theta, rss, cvar, fast, s,
        )


def _scratch_py(F, P, L, p, n_moments, n_centre, n_tail):
    """Work arrays of one lane group, reused by all groups of a thread
    (~1.7 MB at the paper's degrees); unpacked in :func:`_lane_group`."""
    n_base = F + P + 1
    n = L // 2
    f64 = np.float64
    return (
        np.empty((F + 1, P, L, LANES), f64), np.empty((F + 1, P, L, LANES), f64),
        np.empty((L, LANES), f64), np.empty((L, LANES), f64),
        np.empty((n + 1, LANES), f64), np.empty((n + 1, LANES), f64),
        np.empty((n + 1, LANES), f64), np.empty((n + 1, LANES), f64),
        np.empty((n_moments, LANES), f64), np.empty((n_moments, LANES), f64),
        np.empty((p * (p + 1) // 2, LANES), f64),
        np.empty((p * (p + 1) // 2, LANES), f64),
        np.empty((p, LANES), f64), np.empty((p, LANES), f64),
        np.empty((p, LANES), f64), np.empty((p, LANES), f64),
        np.empty((p, LANES), f64), np.empty((p, LANES), f64),
        np.empty((p, LANES), f64),
        np.empty((n_base, L, LANES), f64), np.empty((n_base, L, LANES), f64),
        np.empty((P, L, LANES), f64), np.empty((P, L, LANES), f64),
        np.empty(LANES, np.bool_), np.empty(LANES, np.bool_),
        np.empty(LANES, f64), np.empty(LANES, f64),
        np.empty(LANES, np.int64),
        np.empty((n_tail, n_tail, LANES), f64),
        np.empty((n_tail, n_tail, LANES), f64),
        np.empty((n_centre, n_centre, LANES), f64),
        np.empty((n_centre, n_centre, LANES), f64),
    )


def _lane_group(
    U, Y, bins, first, weights, col_base, data_index, F, n_centre, n_shared,
    n_shared_pairs, q_basis, pair_kind, pair_a, pair_b, pair_nd, pair_off,
    ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef,
    to_layout, fallback_tol, refine_tol, refine_steps, theta, rss, cvar, fast, s,
):
    """Solve the windows ``bins[first:first+LANES]`` of every output row (the
    last group repeats its final window in the unused lanes) and write rows
    ``first..`` of ``theta[o]``, ``rss[o]``, ``cvar[o]`` and ``fast[o]``.

    The leading ``n_shared`` columns (inputs and transients) do not depend on
    the output: their moments, Gram block and Cholesky factor are computed
    once (steps 1-4), and every output row only adds its trailing columns
    (``-Y`` times the denominator basis): the rows of ``L`` below the shared
    block are the Schur complement of this row (steps 5-10)."""
    (sr, si, Sr, Si, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr, gi, xr, xi, dr, di,
     scale2, polyr, polyi, resr, resi, ok_shared, ok, change_num, change_den, k,
     tr, ti, cr, ci) = s
    L, p = weights.shape
    n = L // 2
    B = bins.shape[0]
    n_pairs = pair_kind.shape[0]
    shared_entries = n_shared * (n_shared + 1) // 2
    tol2 = fallback_tol * fallback_tol
    for w in range(LANES):
        k[w] = bins[min(first + w, B - 1)]
    # 1. window data of the inputs
    _gather_inputs(U, Y.shape[2] // 2, k, F, n, sr, si)
    # 2. moments of the pair series without -Y, by parity
    for t in range(n_shared_pairs):
        _pair_series(sr, si, pair_kind[t], pair_a[t], pair_b[t], Sr, Si)
        _moments(Sr, Si, q_basis, pair_off[t], pair_nd[t], Er, Ei, Or, Oi, mr, mi)
    # 3. the shared Gram block (packed lower, internal order)
    _gram_entries(mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
                  0, shared_entries, Hr, Hi)
    # 4. its Cholesky factor, with the equilibrated pivot check (van der Sluis)
    for w in range(LANES):
        ok_shared[w] = True
    _cholesky_rows(Hr, Hi, scale2, ok_shared, tol2, 0, n_shared)
    for o in range(Y.shape[0]):
        # 5. window data of this output row, its moments, Gram rows and A^H b
        _gather_output(Y[o], k, F, n, sr, si)
        for t in range(n_shared_pairs, n_pairs):
            _pair_series(sr, si, pair_kind[t], pair_a[t], pair_b[t], Sr, Si)
            _moments(Sr, Si, q_basis, pair_off[t], pair_nd[t], Er, Ei, Or, Oi,
                     mr, mi)
        _gram_entries(mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
                      shared_entries, ent_const.shape[0], Hr, Hi)
        _rhs(mr, mi, rhs_ptr, rhs_mom, rhs_coef, gr, gi)
        # 6. the trailing rows of the Cholesky factor
        for w in range(LANES):
            ok[w] = ok_shared[w]
        _cholesky_rows(Hr, Hi, scale2, ok, tol2, n_shared, p)
        # 7. solve, then refine with the explicit residual
        _solve_refined(
            sr, si, Hr, Hi, gr, gi, xr, xi, dr, di, scale2, weights, col_base,
            data_index, F, polyr, polyi, resr, resi, change_num, change_den,
            refine_steps, p,
        )
        # 8. (L L^H)^-1 at the centre columns (the n_centre columns before the
        # trailing ones) from the inverse of the tail of L
        _tail_inverse(Hr, Hi, tr.shape[0], p, tr, ti)
        _tail_cov(tr, ti, n_centre, cr, ci)
        # 9. outputs of the real lanes (parameters mapped by ``to_layout``)
        _to_layout(xr, xi, to_layout, dr, di)
        _write_lanes(
            first, B, dr, di, resr, resi, change_num, change_den, ok, cr, ci,
            refine_tol, refine_steps, theta[o], rss[o], cvar[o], fast[o],
        )


def _solve_refined_py(
    sr, si, Hr, Hi, gr, gi, xr, xi, dr, di, scale2, weights, col_base,
    data_index, F, polyr, polyi, resr, resi, change_num, change_den,
    refine_steps, p,
):
    """``x`` from the factor, ``refine_steps`` refinement steps with the
    explicit residual (left in ``resr/resi``) and the scaled size of the last
    correction (``change_num / change_den``)."""
    _chol_solve(Hr, Hi, gr, gi, xr, xi, p)
    for w in range(LANES):
        change_num[w] = 0.0
        change_den[w] = 0.0
    for step in range(refine_steps + 1):
        _residual(
            sr, si, xr, xi, weights, col_base, data_index, F, polyr, polyi,
            resr, resi,
        )
        if step == refine_steps:
            break
        _adjoint(sr, si, resr, resi, weights, col_base, data_index, F,
                 polyr, polyi, gr, gi)
        _chol_solve(Hr, Hi, gr, gi, dr, di, p)
        for w in range(LANES):
            change_num[w] = 0.0
            change_den[w] = 0.0
        for i in range(p):
            for w in range(LANES):
                change_num[w] += scale2[i, w] * (dr[i, w] ** 2 + di[i, w] ** 2)
                change_den[w] += scale2[i, w] * (xr[i, w] ** 2 + xi[i, w] ** 2)
                xr[i, w] += dr[i, w]
                xi[i, w] += di[i, w]


def _write_lanes_py(
    first, B, dr, di, resr, resi, change_num, change_den, ok, cr, ci,
    refine_tol, refine_steps, theta, rss, cvar, fast,
):
    """Rows ``first..`` of one output row's results from the real lanes
    (centre covariance ``cr/ci`` from :func:`_tail_cov`)."""
    p = dr.shape[0]
    L = resr.shape[1]
    n_centre = cr.shape[0]
    for w in range(LANES):
        row = first + w
        if row >= B:
            break
        total = 0.0
        for q in range(resr.shape[0]):
            for r in range(L):
                total += resr[q, r, w] ** 2 + resi[q, r, w] ** 2
        refined = refine_steps == 0 or (
            change_num[w] <= refine_tol * refine_tol * change_den[w]
        )
        if ok[w]:
            for j in range(p):
                theta[row, j, 0] = dr[j, w]
                theta[row, j, 1] = di[j, w]
            rss[row] = total
            for c in range(n_centre):
                for d in range(n_centre):
                    cvar[row, c, d, 0] = cr[c, d, w]
                    cvar[row, c, d, 1] = ci[c, d, w]
            fast[row] = refined
        else:
            for i in range(p):
                theta[row, i, 0] = np.nan
                theta[row, i, 1] = np.nan
            rss[row] = np.nan
            for c in range(n_centre):
                for d in range(n_centre):
                    cvar[row, c, d, 0] = np.nan
                    cvar[row, c, d, 1] = np.nan
            fast[row] = False


# steps of a lane group (each loops over the lanes innermost)


def _gather_py(U, Y, k, F, n, sr, si):
    """Window data of the lanes centred at ``k``: ``sr/si[f, q, r, w]`` the
    input bands ``f < F`` and ``-Y`` (``f = F``); band ``f`` is input ``f //
    fold`` at fast bin ``j + (f % fold) M`` (:func:`lrmfrf.windows.
    band_indices`), ``fold = N // M`` the downsampling factor."""
    _gather_inputs(U, Y.shape[1] // 2, k, F, n, sr, si)
    _gather_output(Y, k, F, n, sr, si)


def _gather_inputs_py(U, M, k, F, n, sr, si):
    """The input bands ``f < F`` of :func:`_gather` (slow length ``M``)."""
    P = U.shape[0]
    N = U.shape[2] // 2
    fold = N // M
    L = 2 * n + 1
    for f in range(F):
        i = f // fold
        shift = (f % fold) * M - n
        for q in range(P):
            for r in range(L):
                for w in range(LANES):
                    j = k[w] + r + shift
                    if j < 0 or j >= N:
                        j %= N
                    sr[f, q, r, w] = U[q, i, 2 * j]
                    si[f, q, r, w] = U[q, i, 2 * j + 1]


def _gather_output_py(Y, k, F, n, sr, si):
    """``-Y`` (``f = F``) of :func:`_gather`; ``Y`` of shape (P, 2M)."""
    P = Y.shape[0]
    M = Y.shape[1] // 2
    L = 2 * n + 1
    for q in range(P):
        for r in range(L):
            for w in range(LANES):
                jm = 2 * ((k[w] + r - n) % M)
                sr[F, q, r, w] = -Y[q, jm]
                si[F, q, r, w] = -Y[q, jm + 1]


def _pair_series_py(sr, si, kind, a, b, Sr, Si):
    """Pair series ``S_ab(r) = sum_q conj(s_a) s_b`` (or a data sequence
    against a transient constant, or ones) of one table pair."""
    P = sr.shape[1]
    L = sr.shape[2]
    for r in range(L):
        for w in range(LANES):
            Sr[r, w] = 0.0
            Si[r, w] = 0.0
    if kind == _DATA_DATA:
        for q in range(P):
            for r in range(L):
                for w in range(LANES):
                    ar = sr[a, q, r, w]
                    ai = si[a, q, r, w]
                    br = sr[b, q, r, w]
                    bi = si[b, q, r, w]
                    Sr[r, w] += ar * br + ai * bi
                    Si[r, w] += ar * bi - ai * br
    elif kind == _CONST_DATA:
        for r in range(L):
            for w in range(LANES):
                Sr[r, w] = sr[b, a, r, w]
                Si[r, w] = si[b, a, r, w]
    elif kind == _DATA_CONST:
        for r in range(L):
            for w in range(LANES):
                Sr[r, w] = sr[a, b, r, w]
                Si[r, w] = -si[a, b, r, w]
    else:  # _ONES: the transient-transient series (weighted tables only)
        for r in range(L):
            for w in range(LANES):
                Sr[r, w] = 1.0


def _moments_py(Sr, Si, q_basis, off, nd, Er, Ei, Or, Oi, mr, mi):
    """``m[off+d] = sum_r q_d(r) S(r)``, ``d < nd``, by parity: even ``q_d``
    see ``S(r) + S(-r)``, odd ones ``S(r) - S(-r)``, ``r > 0``."""
    n = Sr.shape[0] // 2
    for h in range(1, n + 1):
        for w in range(LANES):
            Er[h, w] = Sr[n + h, w] + Sr[n - h, w]
            Ei[h, w] = Si[n + h, w] + Si[n - h, w]
            Or[h, w] = Sr[n + h, w] - Sr[n - h, w]
            Oi[h, w] = Si[n + h, w] - Si[n - h, w]
    for d in range(nd):
        if d % 2 == 0:
            c0 = q_basis[n, d]
            for w in range(LANES):
                mr[off + d, w] = c0 * Sr[n, w]
                mi[off + d, w] = c0 * Si[n, w]
            for h in range(1, n + 1):
                c = q_basis[n + h, d]
                for w in range(LANES):
                    mr[off + d, w] += c * Er[h, w]
                    mi[off + d, w] += c * Ei[h, w]
        else:
            for w in range(LANES):
                mr[off + d, w] = 0.0
                mi[off + d, w] = 0.0
            for h in range(1, n + 1):
                c = q_basis[n + h, d]
                for w in range(LANES):
                    mr[off + d, w] += c * Or[h, w]
                    mi[off + d, w] += c * Oi[h, w]


def _gram_py(mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr,
             rhs_mom, rhs_coef, Hr, Hi, gr, gi):
    """Packed lower Gram ``Hr/Hi`` and ``A^H b`` (``gr/gi``) from the moments."""
    _gram_entries(mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, 0,
                  ent_const.shape[0], Hr, Hi)
    _rhs(mr, mi, rhs_ptr, rhs_mom, rhs_coef, gr, gi)


def _gram_entries_py(mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
                     e_lo, e_hi, Hr, Hi):
    """Packed lower Gram entries ``e_lo..e_hi-1`` from the moments."""
    for e in range(e_lo, e_hi):
        c0 = ent_const[e]
        for w in range(LANES):
            Hr[e, w] = c0
            Hi[e, w] = 0.0
        for z in range(ent_ptr[e], ent_ptr[e + 1]):
            c = ent_coef[z]
            m = ent_mom[z]
            for w in range(LANES):
                Hr[e, w] += c * mr[m, w]
                Hi[e, w] += c * mi[m, w]
        if ent_conj[e]:
            for w in range(LANES):
                Hi[e, w] = -Hi[e, w]


def _rhs_py(mr, mi, rhs_ptr, rhs_mom, rhs_coef, gr, gi):
    """``A^H b`` (``gr/gi``) from the moments."""
    for i in range(rhs_ptr.shape[0] - 1):
        for w in range(LANES):
            gr[i, w] = 0.0
            gi[i, w] = 0.0
        for z in range(rhs_ptr[i], rhs_ptr[i + 1]):
            c = rhs_coef[z]
            m = rhs_mom[z]
            for w in range(LANES):
                gr[i, w] -= c * mr[m, w]
                gi[i, w] += c * mi[m, w]


def _cholesky_py(Hr, Hi, scale2, ok, tol2, p):
    """In-place packed Cholesky ``L`` of every lane, inverse pivots kept in
    ``Hi`` at the diagonal; ``ok[w]`` False where an equilibrated squared
    pivot ``L_jj^2 / G_jj`` is not above ``tol2`` (van der Sluis).

    Left-looking (column m from the finished columns 0..m-1, dot-product
    form): each step writes one entry, which stays in L1, instead of the
    whole trailing matrix (measured 30 % faster than right-looking)."""
    for w in range(LANES):
        ok[w] = True
    _cholesky_rows(Hr, Hi, scale2, ok, tol2, 0, p)


def _cholesky_rows_py(Hr, Hi, scale2, ok, tol2, lo, hi):
    """Rows ``lo..hi-1`` of the factor of :func:`_cholesky`, rows ``0..lo-1``
    finished (row ``i`` of ``L`` needs only rows ``<= i``): ``lo = 0`` and
    ``hi = p`` is the whole factor; ``ok`` is and-ed with the new pivots."""
    for j in range(lo, hi):
        jj = j * (j + 1) // 2 + j
        for w in range(LANES):
            scale2[j, w] = abs(Hr[jj, w])
            ok[w] = ok[w] and scale2[j, w] > 2.2250738585072014e-308
    for m in range(hi):
        rm = m * (m + 1) // 2
        mm = rm + m
        for i in range(max(m, lo), hi):
            ri = i * (i + 1) // 2
            im = ri + m
            for j in range(m):
                mj = rm + j
                ij = ri + j
                for w in range(LANES):
                    cr = Hr[mj, w]
                    ci = Hi[mj, w]
                    ar = Hr[ij, w]
                    ai = Hi[ij, w]
                    Hr[im, w] -= ar * cr + ai * ci
                    Hi[im, w] -= ai * cr - ar * ci
            if i == m:  # the pivot; its inverse is kept in Hi[mm]
                for w in range(LANES):
                    d = Hr[mm, w]
                    good = d > tol2 * scale2[m, w]
                    ok[w] = ok[w] and good
                    if not good:
                        d = 1.0
                    ljj = np.sqrt(d)
                    Hr[mm, w] = ljj
                    Hi[mm, w] = 1.0 / ljj
            else:
                for w in range(LANES):
                    inv = Hi[mm, w]
                    Hr[im, w] *= inv
                    Hi[im, w] *= inv


def _tail_inverse_py(Hr, Hi, n_centre, p, tr, ti):
    """``T = `` inverse of the trailing ``n_centre`` block of ``L`` (lower);
    ``(L L^H)^-1`` at the trailing columns is ``T^H T``."""
    off = p - n_centre
    for c in range(n_centre):
        cc = (off + c) * (off + c + 1) // 2 + off + c
        for i in range(n_centre):
            for w in range(LANES):
                tr[i, c, w] = 0.0
                ti[i, c, w] = 0.0
        for w in range(LANES):
            tr[c, c, w] = Hi[cc, w]
        for i in range(c + 1, n_centre):
            ri = (off + i) * (off + i + 1) // 2 + off
            ii = ri + i
            for m in range(c, i):
                for w in range(LANES):
                    lr = Hr[ri + m, w]
                    li = Hi[ri + m, w]
                    tr[i, c, w] -= lr * tr[m, c, w] - li * ti[m, c, w]
                    ti[i, c, w] -= lr * ti[m, c, w] + li * tr[m, c, w]
            for w in range(LANES):
                tr[i, c, w] *= Hi[ii, w]
                ti[i, c, w] *= Hi[ii, w]


def _write_tail_cov_py(tr, ti, w, cvar, row):
    """``cvar[row] = T^H T`` of lane ``w`` (see :func:`_tail_inverse`) at the
    leading ``cvar.shape[1]`` columns of the tail."""
    n_centre = cvar.shape[1]
    n_tail = tr.shape[0]
    for c in range(n_centre):
        for d in range(n_centre):
            ar = 0.0
            ai = 0.0
            for i in range(max(c, d), n_tail):
                ar += tr[i, c, w] * tr[i, d, w] + ti[i, c, w] * ti[i, d, w]
                ai += tr[i, c, w] * ti[i, d, w] - ti[i, c, w] * tr[i, d, w]
            cvar[row, c, d, 0] = ar
            cvar[row, c, d, 1] = ai


def _tail_cov_py(tr, ti, n_centre, cr, ci):
    """``c = T^H T`` at the leading ``n_centre`` columns of the tail (see
    :func:`_tail_inverse`) for every lane; the sums of
    :func:`_write_tail_cov`, in the same order."""
    n_tail = tr.shape[0]
    for c in range(n_centre):
        for d in range(n_centre):
            for w in range(LANES):
                cr[c, d, w] = 0.0
                ci[c, d, w] = 0.0
            for i in range(max(c, d), n_tail):
                for w in range(LANES):
                    cr[c, d, w] += tr[i, c, w] * tr[i, d, w] + ti[i, c, w] * ti[i, d, w]
                    ci[c, d, w] += tr[i, c, w] * ti[i, d, w] - ti[i, c, w] * tr[i, d, w]


def _to_layout_py(xr, xi, to_layout, dr, di):
    """``d = x @ to_layout`` (real map) for every lane."""
    p = xr.shape[0]
    for j in range(p):
        for w in range(LANES):
            dr[j, w] = 0.0
            di[j, w] = 0.0
        for i in range(p):
            c = to_layout[i, j]
            if c != 0.0:
                for w in range(LANES):
                    dr[j, w] += xr[i, w] * c
                    di[j, w] += xi[i, w] * c


def _chol_solve_py(Hr, Hi, gr, gi, xr, xi, p):
    """Solve ``L L^H x = g`` for every lane; ``L`` packed lower in ``Hr/Hi``
    with the inverse pivots in ``Hi`` at the diagonal. The lane loop is
    innermost everywhere (a reduction over ``i`` inside would not vectorise)."""
    for j in range(p):
        rj = j * (j + 1) // 2
        for w in range(LANES):
            xr[j, w] = gr[j, w]
            xi[j, w] = gi[j, w]
        for i in range(j):
            for w in range(LANES):
                lr = Hr[rj + i, w]
                li = Hi[rj + i, w]
                xr[j, w] -= lr * xr[i, w] - li * xi[i, w]
                xi[j, w] -= lr * xi[i, w] + li * xr[i, w]
        for w in range(LANES):
            inv = Hi[rj + j, w]
            xr[j, w] *= inv
            xi[j, w] *= inv
    for j in range(p - 1, -1, -1):
        for i in range(j + 1, p):
            e = i * (i + 1) // 2 + j
            for w in range(LANES):
                lr = Hr[e, w]
                li = Hi[e, w]
                xr[j, w] -= lr * xr[i, w] + li * xi[i, w]
                xi[j, w] -= lr * xi[i, w] - li * xr[i, w]
        jj = j * (j + 1) // 2 + j
        for w in range(LANES):
            inv = Hi[jj, w]
            xr[j, w] *= inv
            xi[j, w] *= inv


def _residual_py(
    sr, si, xr, xi, weights, col_base, data_index, F, polyr, polyi, resr, resi
):
    """``res = b - A x`` on the window of every lane, shape (P, 2n+1, LANES)."""
    L, p = weights.shape
    P = resr.shape[0]
    n_base = polyr.shape[0]
    for c in range(n_base):
        for r in range(L):
            for w in range(LANES):
                polyr[c, r, w] = 0.0
                polyi[c, r, w] = 0.0
    for i in range(p):
        c = col_base[i]
        for r in range(L):
            wt = weights[r, i]
            for w in range(LANES):
                polyr[c, r, w] += wt * xr[i, w]
                polyi[c, r, w] += wt * xi[i, w]
    for q in range(P):
        for r in range(L):
            for w in range(LANES):
                resr[q, r, w] = -sr[F, q, r, w] - polyr[F + q, r, w]
                resi[q, r, w] = -si[F, q, r, w] - polyi[F + q, r, w]
        for c in range(n_base):
            a = data_index[c]
            if a < 0:
                continue
            for r in range(L):
                for w in range(LANES):
                    pr = polyr[c, r, w]
                    pi = polyi[c, r, w]
                    br = sr[a, q, r, w]
                    bi = si[a, q, r, w]
                    resr[q, r, w] -= pr * br - pi * bi
                    resi[q, r, w] -= pr * bi + pi * br


def _adjoint_py(
    sr, si, resr, resi, weights, col_base, data_index, F, polyr, polyi, gr, gi
):
    """``g = A^H res`` of every lane (``polyr/polyi`` reused as work space)."""
    L, p = weights.shape
    P = resr.shape[0]
    n_base = polyr.shape[0]
    for c in range(n_base):
        a = data_index[c]
        for r in range(L):
            for w in range(LANES):
                polyr[c, r, w] = 0.0
                polyi[c, r, w] = 0.0
        if a < 0:
            q = c - F
            for r in range(L):
                for w in range(LANES):
                    polyr[c, r, w] = resr[q, r, w]
                    polyi[c, r, w] = resi[q, r, w]
            continue
        for q in range(P):
            for r in range(L):
                for w in range(LANES):
                    br = sr[a, q, r, w]
                    bi = si[a, q, r, w]
                    rr = resr[q, r, w]
                    ri = resi[q, r, w]
                    polyr[c, r, w] += br * rr + bi * ri
                    polyi[c, r, w] += br * ri - bi * rr
    for i in range(p):
        c = col_base[i]
        for w in range(LANES):
            gr[i, w] = 0.0
            gi[i, w] = 0.0
        for r in range(L):
            wt = weights[r, i]
            for w in range(LANES):
                gr[i, w] += wt * polyr[c, r, w]
                gi[i, w] += wt * polyi[c, r, w]


if AVAILABLE:  # pragma: no branch
    _opts = {
        "cache": True, "fastmath": {"contract"}, "nogil": True,
        "error_model": "numpy",
    }
    _scratch = njit(**_opts)(_scratch_py)
    _gather_inputs = njit(**_opts)(_gather_inputs_py)
    _gather_output = njit(**_opts)(_gather_output_py)
    _gather = njit(**_opts)(_gather_py)
    _pair_series = njit(**_opts)(_pair_series_py)
    _moments = njit(**_opts)(_moments_py)
    _gram_entries = njit(**_opts)(_gram_entries_py)
    _rhs = njit(**_opts)(_rhs_py)
    _gram = njit(**_opts)(_gram_py)
    _cholesky_rows = njit(**_opts)(_cholesky_rows_py)
    _cholesky = njit(**_opts)(_cholesky_py)
    _tail_inverse = njit(**_opts)(_tail_inverse_py)
    _write_tail_cov = njit(**_opts)(_write_tail_cov_py)
    _tail_cov = njit(**_opts)(_tail_cov_py)
    _to_layout = njit(**_opts)(_to_layout_py)
    _chol_solve = njit(**_opts)(_chol_solve_py)
    _residual = njit(**_opts)(_residual_py)
    _adjoint = njit(**_opts)(_adjoint_py)
    _solve_refined = njit(**_opts)(_solve_refined_py)
    _write_lanes = njit(**_opts)(_write_lanes_py)
    _lane_group = njit(**_opts)(_lane_group)
    _solve_range = njit(**_opts)(_solve_range_py)


def solve_windows(
    U: np.ndarray,
    Y: np.ndarray,
    slow_bins: np.ndarray,
    weights: np.ndarray,
    col_base: np.ndarray,
    F: int,
    n_centre: int,
    *,
    fallback_tol: float,
    refine_tol: float,
    refine_steps: int,
    tables: dict | None = None,
    to_layout: np.ndarray | None = None,
    n_threads: int | None = None,
    return_cov: bool = False,
):
    """Solve the local normal equations of every window (compiled, threaded).

    Several output rows (each its own local problem with its own denominator)
    are solved in one pass: the Gram block of the input and transient columns,
    the same for every row, is built and factored once per window, and each
    row adds its denominator columns (a Schur complement).

    Parameters
    ----------
    U : ndarray of shape (P, N) or (P, n_u, N), complex
        Input DFTs; band ``f`` is input ``f // (N // M)`` (see
        :func:`lrmfrf.windows.band_indices`).
    Y : ndarray of shape (P, M) or (P, n_rows, M), complex
        Output DFTs: one output row, or ``n_rows`` rows solved together.
    slow_bins : ndarray of shape (B,), int
    weights : ndarray of shape (2n+1, p), float
        Basis polynomial of each column on the window (internal order).
    col_base : ndarray of shape (p,), int
        Base sequence of each column (see :func:`moment_tables`); the columns
        of ``-Y`` (code ``F + P``, the denominator) come last.
    F : int
        Number of input bands (``F n_u``).
    n_centre : int
        The ``n_centre`` columns before the denominator columns get their
        ``(A^H A)^-1`` block.
    fallback_tol, refine_tol : float
        Equilibrated-pivot and refinement-change thresholds.
    refine_steps : int
    tables : dict, optional
        :func:`moment_tables` of ``weights`` and ``col_base`` (computed when
        not given; they depend on the layout only).
    to_layout : ndarray of shape (p, p), optional
        Real ``T``: ``theta`` is returned as ``theta_internal @ T`` (e.g.
        :attr:`lrmfrf.windows.StructuredWindows.to_layout_matrix` with its
        rows in the internal order of ``weights``); default the identity.
    n_threads : int, optional
        Threads sharing the windows; default ``numba.config.NUMBA_NUM_THREADS``
        (the number of cores unless the ``NUMBA_NUM_THREADS`` environment
        variable says otherwise).

    Returns
    -------
    theta : ndarray of shape (B, p), complex
        ``theta_internal @ to_layout``; NaN where the factorisation failed.
    rss : ndarray of shape (B,)
    centre_var : ndarray of shape (B, n_centre)
        In the internal order of the centre columns; with ``return_cov=True``
        the complex block of shape (B, n_centre, n_centre) instead.
    fast : ndarray of shape (B,), bool
        False where the window must be re-solved by QR.

    With ``Y`` of shape (P, n_rows, M) every result has a leading axis of
    length ``n_rows``.
    """
    if not AVAILABLE:
        raise ImportError("the compiled kernel needs numba (pip install numba)")
    args, outputs, one_row = _solve_arguments(
        U, Y, slow_bins, weights, col_base, F, n_centre, fallback_tol,
        refine_tol, refine_steps, tables, to_layout,
    )
    run_lane_groups(_solve_range, args, slow_bins.size, n_threads)
    return _solve_results(outputs, one_row, return_cov)


def _solve_arguments(U, Y, slow_bins, weights, col_base, F, n_centre,
                     fallback_tol, refine_tol, refine_steps, tables, to_layout):
    """Arguments of :func:`_solve_range` (without the group range), its output
    arrays ``(theta, rss, centre_cov, fast)`` and whether ``Y`` is one row."""
    B, p = slow_bins.size, weights.shape[1]
    weights = np.ascontiguousarray(weights, dtype=np.float64)
    col_base = np.ascontiguousarray(col_base, dtype=np.int64)
    P = U.shape[0]
    if U.ndim == 2:
        U = U[:, None, :]
    one_row = Y.ndim == 2
    rows_first = np.moveaxis(Y[:, None, :] if one_row else Y, 1, 0)  # (R, P, M)
    R = rows_first.shape[0]
    is_den = col_base == F + P
    n_shared = p - int(np.count_nonzero(is_den))
    if is_den[:n_shared].any():
        raise ValueError(
            "the denominator columns (col_base == F + P) must come last; reorder "
            "weights and col_base"
        )
    if tables is None:
        tables = moment_tables(weights, col_base, F, P)
    t = tables
    # the pairs with -Y (data index F first, or against a transient) come last
    with_y = (
        ((t["pair_kind"] == _DATA_DATA) & (t["pair_a"] == F))
        | (t["pair_kind"] == _DATA_CONST)
    )
    n_shared_pairs = int(np.argmax(with_y)) if with_y.any() else with_y.size
    theta = np.empty((R, B, p, 2))
    rss = np.empty((R, B))
    centre_cov = np.empty((R, B, n_centre, n_centre, 2))
    fast = np.empty((R, B), dtype=np.bool_)
    if to_layout is None:
        to_layout = np.eye(p)
    args = (
        _as_interleaved(U), _as_interleaved(rows_first),
        np.ascontiguousarray(slow_bins, dtype=np.int64), weights, col_base,
        t["data_index"], int(F), int(n_centre), int(n_centre + p - n_shared),
        n_shared, n_shared_pairs, t["q_basis"], t["pair_kind"],
        t["pair_a"], t["pair_b"], t["pair_nd"], t["pair_off"], t["ent_ptr"],
        t["ent_mom"], t["ent_coef"], t["ent_conj"], t["ent_const"], t["rhs_ptr"],
        t["rhs_mom"], t["rhs_coef"], int(t["n_moments"]),
        np.ascontiguousarray(to_layout, dtype=np.float64), float(fallback_tol),
        float(refine_tol), int(refine_steps), theta, rss, centre_cov, fast,
    )
    return args, (theta, rss, centre_cov, fast), one_row


def run_lane_groups(kernel, args, B: int, n_threads: int | None = None) -> None:
    """Run ``kernel(*args, first_group, stop_group)`` over the lane groups of
    ``B`` windows, shared by ``n_threads`` threads (default
    ``numba.config.NUMBA_NUM_THREADS``)."""
    n_groups = (B + LANES - 1) // LANES
    threads = n_threads or numba.config.NUMBA_NUM_THREADS
    tasks = _balanced_tasks(n_groups, threads)
    if min(threads, len(tasks)) <= 1:
        if n_groups:
            kernel(*args, 0, n_groups)
    else:  # the kernel releases the GIL: threads share the lane groups
        # (fewer tasks than threads run on as many of the pool's threads)
        list(thread_pool(threads).map(lambda task: kernel(*args, *task), tasks))


_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def thread_pool(threads: int) -> ThreadPoolExecutor:
    """The process's pool of ``threads`` kernel threads, made at first use.

    Callers pass the threads asked for, not a call's task count: a call with
    fewer tasks uses as many of the pool's threads (a pool per task count
    kept up to ``threads**2 / 2`` idle threads: 65 with 16 threads and
    records of 2 to 15 lane groups).

    Kept for the process: starting the threads anew took 0.3-0.6 ms each
    per call on a quiet 2-core machine (several ms under load), most of a
    short record's kernel time. Calls from several threads share it (each
    waits for its own tasks; kernels never submit tasks themselves); a forked
    child makes its own (the parent's threads do not exist there).
    """
    with _POOLS_LOCK:
        pool = _POOLS.get(threads)
        if pool is None:
            pool = _POOLS[threads] = ThreadPoolExecutor(
                threads, thread_name_prefix=f"lrmfrf-kernel-{threads}"
            )
        return pool


def _forget_pools_after_fork() -> None:
    global _POOLS_LOCK
    _POOLS.clear()
    _POOLS_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):  # pragma: no branch (POSIX)
    os.register_at_fork(after_in_child=_forget_pools_after_fork)


def _balanced_tasks(n_groups: int, threads: int) -> list[tuple[int, int]]:
    """Lane-group ranges ``(start, stop)`` for ``threads`` threads taking
    tasks from a shared queue.

    At most :data:`_GROUPS_PER_TASK` groups a task and at least 4 tasks a
    thread when the groups allow; the number of tasks is a multiple of
    ``threads`` (or, with fewer groups than that, one task a group) and their
    sizes differ by at most one group (larger first), so threads of equal
    speed end within one group of each other (fixed-size tasks left one
    thread idle for up to a whole task at the end of every call: 53 groups in
    tasks of 6 went 29 and 24).
    """
    if n_groups <= 0:
        return []
    per_task = max(1, min(_GROUPS_PER_TASK, n_groups // (4 * threads)))
    n_tasks = -(-n_groups // per_task)
    n_tasks = min(n_groups, threads * -(-n_tasks // threads))
    base, extra = divmod(n_groups, n_tasks)
    tasks, start = [], 0
    for t in range(n_tasks):
        stop = start + base + (t < extra)
        tasks.append((start, stop))
        start = stop
    return tasks


def chunk_quantum() -> int:
    """Windows a streamed chunk is a multiple of when the memory budget holds
    that many (:func:`lrmfrf.local_models.stream_chunk_size`): the lanes
    times the kernel's threads, so that every thread gets as many lane
    groups."""
    threads = numba.config.NUMBA_NUM_THREADS if AVAILABLE else 1
    return LANES * max(1, int(threads))


def _solve_results(outputs, one_row, return_cov):
    """The results of :func:`solve_windows` from the kernel's output arrays."""
    theta, rss, centre_cov, fast = outputs
    centre_cov = centre_cov.view(np.complex128)[..., 0]
    if not return_cov:
        centre_cov = np.real(np.diagonal(centre_cov, axis1=-2, axis2=-1)).copy()
    theta = theta.view(np.complex128)[..., 0]
    if one_row:
        return theta[0], rss[0], centre_cov[0], fast[0]
    return theta, rss, centre_cov, fast


def _as_interleaved(values: np.ndarray) -> np.ndarray:
    """Complex (P, K) as a float (P, 2K) view, real and imaginary interleaved
    (no copy for a C-contiguous complex128 array such as an FFT output)."""
    values = np.ascontiguousarray(values, dtype=np.complex128)
    return values.view(np.float64)
