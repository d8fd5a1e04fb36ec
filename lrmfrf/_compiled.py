"""Compiled per-window kernel of the fast closed form (optional, needs numba).

:func:`solve_windows` does, for every window and in parallel over windows,
everything :func:`lrmfrf.solvers.solve_local_normal_equations` does with
array operations: gather the window data from the DFTs, build the Gram matrix
``A^H A`` and ``A^H b`` (in the basis and column order of
:class:`lrmfrf.windows.StructuredWindows`) from a few polynomial moments of
the products of the window sequences (:func:`moment_tables`), Cholesky-factorise
it with the equilibrated pivot check, solve, refine with the explicit residual
``b - A theta``, and compute the centre-column diagonal of ``(A^H A)^-1``.
Nothing of size ``(B, n_params, n_params)`` is ever stored. Compiled with
``cache=True`` (the first call in a fresh environment compiles for ~10-20 s,
later processes load the cache in well under a second) and
``fastmath=False``.

The columns of ``A`` are described by ``weights`` (L, p), real basis
polynomials on the window, and ``col_base`` (p,), the base sequence each
column multiplies: ``0..F-1`` the input band ``U(k+r+fM)``, ``F+q`` the
constant of experiment ``q`` (transient), ``F+P`` the sequence ``-Y(k+r)``
(denominator).

Use :data:`AVAILABLE` to know whether numba is importable; importing this
module never fails without it.
"""

from __future__ import annotations

import numpy as np

try:  # pragma: no cover - exercised when numba is installed
    import numba
    from numba import njit, prange

    AVAILABLE = True
except ImportError:  # pragma: no cover - exercised when numba is absent
    numba = None
    AVAILABLE = False

__all__ = ["AVAILABLE", "moment_tables", "solve_windows"]

#: Windows handled by one task of the parallel loop (scratch reused within it).
_TASK = 64


def _solve_windows_py(
    U, Y, bins, weights, col_base, tables, F, n_centre, fallback_tol, refine_tol,
    refine_steps, theta, rss, centre_var, fast,
):
    """Loop over windows in tasks; see :func:`solve_windows`."""
    B = bins.shape[0]
    n_tasks = (B + _TASK - 1) // _TASK
    for task in prange(n_tasks):
        scratch = _scratch_alloc(U.shape[0], weights.shape[0], weights.shape[1], F)
        stop = min(B, (task + 1) * _TASK)
        for w in range(task * _TASK, stop):
            _one_window(
                U, Y, bins[w], weights, col_base, tables, F, n_centre,
                fallback_tol, refine_tol, refine_steps, scratch, theta[w],
                centre_var[w], rss, fast, w,
            )


def _scratch_alloc_py(P, L, p, F):
    """Work arrays of one window (reused by all windows of a task)."""
    nb = F + P + 1
    base = np.zeros((nb, P, L), dtype=np.complex128)
    n_pairs = nb * (nb + 1) // 2
    mr = np.empty((n_pairs, L))
    mi = np.empty((n_pairs, L))
    accr = np.empty(p * p)
    acci = np.empty(p * p)
    gram = np.zeros((p, p), dtype=np.complex128)
    rhs = np.empty(p, dtype=np.complex128)
    delta = np.empty(p, dtype=np.complex128)
    res = np.empty((P, L), dtype=np.complex128)
    poly = np.empty((nb, L), dtype=np.complex128)
    tail = np.empty((p, p), dtype=np.complex128)
    scale = np.empty(p)
    return base, mr, mi, accr, acci, gram, rhs, delta, res, poly, tail, scale


def _one_window_py(
    U, Y, k, weights, col_base, tables, F, n_centre, fallback_tol, refine_tol,
    refine_steps, scratch, theta, cvar, rss, fast, w,
):
    """Window centred at slow bin ``k``: writes ``theta``, ``cvar``, ``rss[w]``
    and ``fast[w]`` (steps and order as in the numpy path)."""
    base, mr, mi, accr, acci, gram, rhs, delta, res, poly, tail, scale = scratch
    (q_basis, coef, pair_a, pair_b, pair_nd, pair_off, den_pair, perm, gstart,
     gbase, wcoef, wdeg) = tables
    P, N = U.shape
    M = Y.shape[1]
    L, p = weights.shape
    nb = F + P + 1
    n = L // 2
    # window data: inputs of each band, transient constants, -Y
    for q in range(P):
        for r in range(L):
            j = k + r - n
            for f in range(F):
                base[f, q, r] = U[q, (j + f * M) % N]
            base[F + q, q, r] = 1.0
            base[F + P, q, r] = -Y[q, j % M]
    # moments m_t[d] = sum_r Q[r, d] S_t(r) of the pair series
    # S_t = sum_q conj(base_a) base_b of every base pair t = (a >= b)
    n_pairs = pair_a.shape[0]
    for t in range(n_pairs):
        a = pair_a[t]
        b = pair_b[t]
        nd = pair_nd[t]
        for d in range(nd):
            mr[t, d] = 0.0
            mi[t, d] = 0.0
        for r in range(L):
            acc = 0j
            for q in range(P):
                acc += np.conj(base[a, q, r]) * base[b, q, r]
            s_re = acc.real
            s_im = acc.imag
            for d in range(nd):
                mr[t, d] += q_basis[r, d] * s_re
                mi[t, d] += q_basis[r, d] * s_im
        # Gram block: G[i, j] = sum_d C_t[d, i, j] m_t[d] (grouped order)
        ma = gstart[a + 1] - gstart[a]
        mb = gstart[b + 1] - gstart[b]
        size = ma * mb
        off = pair_off[t]
        for e in range(size):
            accr[e] = 0.0
            acci[e] = 0.0
        for d in range(nd):
            cr = mr[t, d]
            ci = mi[t, d]
            row = off + d * size
            for e in range(size):
                c = coef[row + e]
                accr[e] += c * cr
                acci[e] += c * ci
        for i in range(ma):
            ii = perm[gstart[a] + i]
            for j in range(mb):
                jc = perm[gstart[b] + j]
                e = i * mb + j
                if ii >= jc:
                    gram[jc, ii] = complex(accr[e], acci[e])
                else:
                    gram[ii, jc] = complex(accr[e], -acci[e])
    # A^H b = -sum_r w_i conj(base_a) base_den = -conj(sum_d c_i[d] m_(den,a)[d])
    for gi in range(p):
        t = den_pair[gbase[gi]]
        ar = 0.0
        ai = 0.0
        for d in range(wdeg[gi] + 1):
            ar += wcoef[gi, d] * mr[t, d]
            ai += wcoef[gi, d] * mi[t, d]
        rhs[perm[gi]] = complex(-ar, ai)
    # Cholesky with the equilibrated pivot check (van der Sluis); right-looking
    # on the transposed lower triangle (column j of L in row j of ``gram``)
    ok = True
    for j in range(p):
        scale[j] = np.sqrt(abs(gram[j, j].real))
        if not scale[j] > 2.2250738585072014e-308:
            ok = False
    for j in range(p):
        if not ok:
            break
        d = gram[j, j].real
        if not d > 0.0:
            ok = False
            break
        ljj = np.sqrt(d)
        if not ljj / scale[j] > fallback_tol:
            ok = False
            break
        gram[j, j] = ljj
        inv = 1.0 / ljj
        for i in range(j + 1, p):
            gram[j, i] *= inv
        for m in range(j + 1, p):
            c = np.conj(gram[j, m])
            for i in range(m, p):
                gram[m, i] -= gram[j, i] * c
    if not ok:
        fast[w] = False
        rss[w] = np.nan
        for i in range(p):
            theta[i] = np.nan
        for i in range(n_centre):
            cvar[i] = np.nan
        return
    _chol_solve(gram, rhs, theta)
    change = 0.0
    for step in range(refine_steps + 1):
        # residual b - A theta: per-base polynomial values, then the windows
        for a in range(nb):
            for r in range(L):
                poly[a, r] = 0.0
        for i in range(p):
            a = col_base[i]
            t = theta[i]
            for r in range(L):
                poly[a, r] += weights[r, i] * t
        total = 0.0
        for q in range(P):
            for r in range(L):
                acc = -base[F + P, q, r]
                for a in range(nb):
                    acc -= poly[a, r] * base[a, q, r]
                res[q, r] = acc
                total += acc.real ** 2 + acc.imag ** 2
        rss[w] = total
        if step == refine_steps:
            break
        # A^H r, the correction, its size
        for a in range(nb):
            for r in range(L):
                acc = 0j
                for q in range(P):
                    acc += np.conj(base[a, q, r]) * res[q, r]
                poly[a, r] = acc
        for i in range(p):
            s = poly[col_base[i]]
            acc = 0j
            for r in range(L):
                acc += weights[r, i] * s[r]
            rhs[i] = acc
        _chol_solve(gram, rhs, delta)
        num = 0.0
        den = 0.0
        for i in range(p):
            sd = delta[i] * scale[i]
            st = theta[i] * scale[i]
            num += sd.real**2 + sd.imag**2
            den += st.real**2 + st.imag**2
            theta[i] += delta[i]
        change = np.sqrt(num / den) if den > 0.0 else np.inf
    fast[w] = not (refine_steps > 0 and not change <= refine_tol)
    # diag of (L L^H)^-1 at the trailing columns: column norms of inv(L_tail)
    off = p - n_centre
    for c in range(n_centre):
        for i in range(n_centre):
            tail[i, c] = 0.0
        tail[c, c] = 1.0 / gram[off + c, off + c].real
        for i in range(c + 1, n_centre):
            acc = 0j
            for m in range(c, i):
                acc -= gram[off + m, off + i] * tail[m, c]
            tail[i, c] = acc / gram[off + i, off + i].real
    for c in range(n_centre):
        acc = 0.0
        for i in range(c, n_centre):
            acc += tail[i, c].real ** 2 + tail[i, c].imag ** 2
        cvar[c] = acc


def _chol_solve_py(chol, rhs, out):
    """Solve ``L L^H out = rhs``; column ``j`` of ``L`` is row ``j`` of ``chol``."""
    p = rhs.shape[0]
    for j in range(p):
        out[j] = rhs[j]
    for j in range(p):
        zj = out[j] / chol[j, j].real
        out[j] = zj
        for i in range(j + 1, p):
            out[i] -= chol[j, i] * zj
    for j in range(p - 1, -1, -1):
        acc = out[j]
        for m in range(j + 1, p):
            acc -= np.conj(chol[j, m]) * out[m]
        out[j] = acc / chol[j, j].real


if AVAILABLE:  # pragma: no branch
    _opts = {"cache": True, "fastmath": False, "nogil": True, "error_model": "numpy"}
    _chol_solve = njit(**_opts)(_chol_solve_py)
    _scratch_alloc = njit(**_opts)(_scratch_alloc_py)
    _one_window = njit(**_opts)(_one_window_py)
    _solve_windows = njit(parallel=True, **_opts)(_solve_windows_py)


def moment_tables(weights, col_base, F, P):
    """Per-layout tables of the moment form of the Gram matrix.

    Columns are grouped by base sequence (``perm``: grouped position ->
    internal column; group ``a`` spans ``gstart[a]:gstart[a+1]``). For every
    base pair ``t = (a, b)``, ``a >= b``, the products ``w_i(r) w_j(r)`` of
    the two groups' basis polynomials have degree ``<= D_t``; they are
    expanded exactly in the first ``D_t + 1`` columns of ``q_basis``, an
    orthonormal polynomial basis on the window (QR of a Chebyshev
    Vandermonde matrix, condition number ~3), with coefficients ``coef``.
    Then the Gram block is ``sum_d C_t[d] m_t[d]`` with the moments
    ``m_t[d] = sum_r q_basis[r, d] S_t(r)`` of the pair series: ``D_t + 1``
    sums over the window instead of one per Gram entry.
    """
    L, p = weights.shape
    n_base = F + P + 1
    perm = np.argsort(col_base, kind="stable").astype(np.int64)
    gbase = col_base[perm]
    gstart = np.searchsorted(gbase, np.arange(n_base + 1)).astype(np.int64)
    wg = weights[:, perm]
    n = L // 2
    x = (np.arange(L) - n) / max(n, 1)
    # polynomial degree of each column (exact: weights are polynomials in x)
    deg = np.array([_degree(x, wg[:, g]) for g in range(p)], dtype=np.int64)
    top = [int(deg[gstart[a]:gstart[a + 1]].max(initial=0)) for a in range(n_base)]
    d_max = min(L - 1, 2 * max(top))
    q_basis, _ = np.linalg.qr(np.polynomial.chebyshev.chebvander(x, d_max))
    pair_a, pair_b, pair_nd, pair_off, coef = [], [], [], [], []
    den_pair = np.zeros(n_base, dtype=np.int64)
    offset = 0
    for a in range(n_base):
        for b in range(a + 1):
            nd = min(L, top[a] + top[b] + 1)
            wa = wg[:, gstart[a]:gstart[a + 1]]
            wb = wg[:, gstart[b]:gstart[b + 1]]
            block = np.einsum("rd,ri,rj->dij", q_basis[:, :nd], wa, wb)
            if a == n_base - 1:
                den_pair[b] = len(pair_a)
            pair_a.append(a)
            pair_b.append(b)
            pair_nd.append(nd)
            pair_off.append(offset)
            coef.append(block.ravel())
            offset += block.size
    wcoef = np.ascontiguousarray(q_basis.T @ wg).T.copy()  # (p, d_max + 1)
    as_int = lambda v: np.asarray(v, dtype=np.int64)  # noqa: E731
    return (
        np.ascontiguousarray(q_basis), np.concatenate(coef), as_int(pair_a),
        as_int(pair_b), as_int(pair_nd), as_int(pair_off), den_pair, perm, gstart,
        as_int(gbase), np.ascontiguousarray(wcoef), np.minimum(deg, d_max),
    )


def _degree(x, values):
    """Degree of the polynomial taking ``values`` on the grid ``x``."""
    if not np.any(values):
        return 0
    for d in range(x.size):
        fit = np.polynomial.chebyshev.chebfit(x, values, d)
        residual = values - np.polynomial.chebyshev.chebval(x, fit)
        if np.max(np.abs(residual)) <= 1e-12 * np.max(np.abs(values)):
            return d
    return x.size - 1


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
    tables: tuple | None = None,
):
    """Solve the local normal equations of every window (compiled, parallel).

    Parameters
    ----------
    U : ndarray of shape (P, N), complex
    Y : ndarray of shape (P, M), complex
    slow_bins : ndarray of shape (B,), int
    weights : ndarray of shape (2n+1, p), float
        Basis polynomial of each column on the window (internal order).
    col_base : ndarray of shape (p,), int
        Base sequence of each column (see the module docstring).
    F : int
    n_centre : int
        The last ``n_centre`` columns get their ``(A^H A)^-1`` diagonal.
    fallback_tol, refine_tol : float
        Equilibrated-pivot and refinement-change thresholds.
    refine_steps : int
    tables : tuple, optional
        :func:`moment_tables` of ``weights`` and ``col_base`` (computed when
        not given; they depend on the layout only).

    Returns
    -------
    theta : ndarray of shape (B, p), complex
        Internal basis and order; NaN where the factorisation failed.
    rss : ndarray of shape (B,)
    centre_var : ndarray of shape (B, n_centre)
    fast : ndarray of shape (B,), bool
        False where the window must be re-solved by QR.
    """
    if not AVAILABLE:
        raise ImportError("the compiled kernel needs numba (pip install numba)")
    B, p = slow_bins.size, weights.shape[1]
    theta = np.empty((B, p), dtype=np.complex128)
    rss = np.empty(B)
    centre_var = np.empty((B, n_centre))
    fast = np.empty(B, dtype=np.bool_)
    weights = np.ascontiguousarray(weights, dtype=np.float64)
    col_base = np.ascontiguousarray(col_base, dtype=np.int64)
    if tables is None:
        tables = moment_tables(weights, col_base, F, U.shape[0])
    _solve_windows(
        np.ascontiguousarray(U, dtype=np.complex128),
        np.ascontiguousarray(Y, dtype=np.complex128),
        np.ascontiguousarray(slow_bins, dtype=np.int64),
        weights, col_base, tables, int(F), int(n_centre), float(fallback_tol),
        float(refine_tol), int(refine_steps), theta, rss, centre_var, fast,
    )
    return theta, rss, centre_var, fast
