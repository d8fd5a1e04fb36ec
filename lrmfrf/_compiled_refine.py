"""Compiled Sanathanan-Koerner refinement (optional, needs numba).

:func:`sk_windows` runs, for every window, what
:func:`lrmfrf.refinement._sanathanan_koerner` does with array operations,
with the lanes and steps of the closed-form kernel (:mod:`lrmfrf._compiled`).

The SK weight of row ``r`` of a window is ``W(r) = 1 / |e_prev(x_r)|^2``: real
and the same for every experiment. Every Gram entry of the reweighted problem
is therefore ``sum_r w_i(r) w_j(r) W(r) S_ab(r)``: the moment form of the
closed form with the pair series ``S_ab`` replaced by ``W S_ab`` (the parity
fold holds for any series), and the transient-transient block given by the
moments of ``W`` itself (``moment_tables(..., weighted=True)``). A lane group
gathers its windows and forms the pair series once; each iteration then costs
the weighted moments, the Gram matrix, a Cholesky factorisation, a solve with
one step of iterative refinement on the weighted residual (as
:func:`lrmfrf.refinement._weighted_solve`), the output-error cost and the
guard. The pole guard counts roots in a disk with the Schur-Cohn recursion
(:func:`_root_in_unit_disk`) instead of eigenvalues.

Guarded LM (:func:`_lm_phase`) damps in the layout basis, as numpy does. Its
Gauss-Newton model (:func:`_lm_model`) is formed there directly: with the
layout moment tables (monomial columns, ``moment_tables`` of ``weights @
S^T``) the moments of ``W S_ab`` give ``J^H J`` in that basis, so no change
of basis ``S H S^T`` is formed; ``J^H res`` is the adjoint with the layout
columns. The model is rebuilt only where a lane moved, from the residual kept
at the estimate (the accepted trial's), and each iteration then costs one
damped Cholesky solve (:func:`_lm_step`), one residual pass for the trial
cost (:func:`_oe_cost`) and the guard. A lane group would run until its
last lane stops, so a lane whose window stops takes the next window of its
task at once (:func:`_lm_refill_range`: the windows come from SK groups run
one at a time, their results are written a full group at a time); every lane
keeps its own iteration count. The iterates of a window do not depend on its
lane, so the results are bit for bit those of groups that run every
iteration. Without refill (``lm_refill=False``) the windows still active
after the iterations in ``_LM_STAGES`` are packed densely into new groups
instead (:func:`_lm_group`: gathered again, the model rebuilt from the
estimate), with the same results.
"""

from __future__ import annotations

import numpy as np

from . import _compiled
from ._compiled import AVAILABLE, LANES
from ._jit_cache import key_caches_on

__all__ = ["sk_windows", "root_in_disk"]

_GROUPS_PER_TASK = 4

# LM iterations after which the windows still active are packed densely into
# new lane groups: a group runs until its slowest lane stops, and on the
# benchmark's data (wafer stage, N = 1.2e5) windows stop from iteration 6 on,
# half by 26, 13 % still active at 49. Every 8 iterations from 12 on: 35x the
# closed form's CPU time for LM50 against 39x without (one thread, loaded
# machine; (8, 16, ..., 40), (10, 20, 30, 40), (12, 24, 35) within that noise)
_LM_STAGES = (12, 20, 28, 36, 44)

# LM refills a lane with the next window as soon as its window stops
# (_lm_refill_range), so a lane group runs full until the windows of its task
# are exhausted; tasks per thread (each task's group drains once at its end)
_LM_REFILL = True
_REFILL_TASKS_PER_THREAD = 1

_DATA_DATA_ = _compiled._DATA_DATA
_DATA_CONST_ = _compiled._DATA_CONST


def _root_in_unit_disk_py(cr, ci, nr, ni, d):
    """Whether ``sum_k (cr[k] + i ci[k]) z^k`` (degree ``d``) has a root with
    ``|z| <= 1`` (``cr``, ``ci`` are overwritten).

    Schur-Cohn: all roots lie outside the closed unit disk iff ``|a_0| >
    |a_d|`` and the same holds, recursively, for ``conj(a_0) p(z) - a_d
    p*(z)`` (degree ``d - 1``; ``p*`` the reversed conjugate), which has the
    same number of roots inside by Rouche's theorem. NaN coefficients count
    as a root inside.
    """
    while d >= 1:
        a0 = cr[0] * cr[0] + ci[0] * ci[0]
        ad = cr[d] * cr[d] + ci[d] * ci[d]
        if not a0 > ad:
            return True
        for k in range(d):
            r1 = cr[0] * cr[k] + ci[0] * ci[k]
            i1 = cr[0] * ci[k] - ci[0] * cr[k]
            r2 = cr[d] * cr[d - k] + ci[d] * ci[d - k]
            i2 = ci[d] * cr[d - k] - cr[d] * ci[d - k]
            nr[k] = r1 - r2
            ni[k] = i1 - i2
        inv = 1.0 / nr[0]  # |a_0|^2 - |a_d|^2 > 0
        for k in range(d):
            cr[k] = nr[k] * inv
            ci[k] = ni[k] * inv
        d -= 1
    return False


def root_in_disk(coef: np.ndarray, radius: float) -> bool:
    """Whether ``1 + sum_s coef[s-1] x^s`` has a root with ``|x| <= radius``.

    Parameters
    ----------
    coef : ndarray of shape (R_e,), complex
    radius : float

    Returns
    -------
    bool
    """
    d = coef.size
    scaled = np.concatenate([[1.0], coef * radius ** np.arange(1, d + 1)])
    cr, ci = scaled.real.copy(), scaled.imag.copy()
    return bool(_root_in_unit_disk(cr, ci, np.empty(d + 1), np.empty(d + 1), d))


def _sk_scratch_py(F, P, L, p, n_moments, n_centre, n_pairs, n_den):
    n_base = F + P + 1
    n = L // 2
    f64 = np.float64
    return (
        np.empty((F + 1, P, L, LANES), f64), np.empty((F + 1, P, L, LANES), f64),
        np.empty((n_pairs, L, LANES), f64), np.empty((n_pairs, L, LANES), f64),
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
        np.empty((L, LANES), f64),
        np.empty((L, LANES), f64), np.empty((L, LANES), f64),
        np.empty((L, LANES), f64), np.empty((L, LANES), f64),
        np.empty((p, LANES), f64), np.empty((p, LANES), f64),
        np.empty((p, LANES), f64), np.empty((p, LANES), f64),
        np.empty(LANES, np.bool_), np.empty(LANES, np.int64),
        np.empty((8, LANES), f64), np.empty((4, LANES), np.bool_),
        np.empty((n_centre, n_centre, LANES), f64),
        np.empty((n_centre, n_centre, LANES), f64),
        np.empty((4, n_den + 1), f64),
        np.empty((F + 1, P, L, LANES), f64), np.empty((F + 1, P, L, LANES), f64),
        np.empty((p * (p + 1) // 2, LANES), f64),
        np.empty((p * (p + 1) // 2, LANES), f64),
        np.empty((p, LANES), f64), np.empty((p, LANES), f64),
        np.empty((p, LANES), f64), np.empty((p, LANES), f64),
        np.empty((p, LANES), f64), np.empty((3, LANES), f64),
        np.empty((2, LANES), np.bool_),
        np.empty((p * (p + 1) // 2, LANES), f64),
        np.empty((p * (p + 1) // 2, LANES), f64),
        np.empty((P, L, LANES), f64), np.empty((P, L, LANES), f64),
        np.empty((L, LANES), f64), np.empty((L, LANES), f64),
        np.empty(LANES, np.int64),
    )


def _denominator_py(polyr, polyi, den, er, ei):
    """``e(x_r) = 1 + `` the denominator polynomial (base ``den``)."""
    L = er.shape[0]
    for r in range(L):
        for w in range(LANES):
            er[r, w] = 1.0 + polyr[den, r, w]
            ei[r, w] = polyi[den, r, w]


def _weighted_gram_py(
    Sar, Sai, Wt, Tr, Ti, q_basis, pair_off, pair_nd, Er, Ei, Or, Oi, mr, mi,
    ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef,
    Hr, Hi, gr, gi,
):
    """Gram and ``A^H W b`` of the row-weighted problem from the stored pair
    series: the moments of ``W S_ab``."""
    L = Wt.shape[0]
    for t in range(Sar.shape[0]):
        for r in range(L):
            for w in range(LANES):
                Tr[r, w] = Wt[r, w] * Sar[t, r, w]
                Ti[r, w] = Wt[r, w] * Sai[t, r, w]
        _compiled._moments(
            Tr, Ti, q_basis, pair_off[t], pair_nd[t], Er, Ei, Or, Oi, mr, mi
        )
    _compiled._gram(mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
                    rhs_ptr, rhs_mom, rhs_coef, Hr, Hi, gr, gi)


def _rejected_py(
    xr, xi, w, row, band_int, system_factor, start_system, jump_limit, den_int,
    den_map, guard_radius, radius, work,
):
    """The guard of :meth:`lrmfrf.refinement._ChunkState.rejected` for lane
    ``w`` (window ``row``): an FRF jump, or a root of ``e(x)`` (monomial
    coefficients ``x[den_int] @ den_map``) with ``|x| < radius[row]`` when
    the Rouche bound ``sum |e_s| guard^s < 1`` does not exclude one."""
    for f in range(band_int.shape[0]):
        vr = system_factor * xr[band_int[f], w] - start_system[row, f, 0]
        vi = system_factor * xi[band_int[f], w] - start_system[row, f, 1]
        if np.sqrt(vr * vr + vi * vi) > jump_limit[row, f]:
            return True
    n_den = den_int.shape[0]
    if guard_radius > 0.0 and n_den > 0:
        work[0, 0] = 1.0
        work[1, 0] = 0.0
        bound = 0.0
        power = 1.0
        for s in range(n_den):
            er = 0.0
            ei = 0.0
            for j in range(n_den):
                c = den_map[j, s]
                er += xr[den_int[j], w] * c
                ei += xi[den_int[j], w] * c
            power *= guard_radius
            bound += np.sqrt(er * er + ei * ei) * power
            work[0, s + 1] = er
            work[1, s + 1] = ei
        if not bound < 1.0:
            R = radius[row]
            if R > 0.0:
                power = 1.0
                for s in range(1, n_den + 1):
                    power *= R
                    work[0, s] *= power
                    work[1, s] *= power
                if _root_in_unit_disk(work[0], work[1], work[2], work[3], n_den):
                    return True
    return False


def _sk_range_py(
    U, Y, bins, theta0, closed_rss, start_system, jump_limit, radius,
    weights, col_base, data_index, F, n_centre, q_basis, pair_kind, pair_a,
    pair_b, pair_nd, pair_off, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
    rhs_ptr, rhs_mom, rhs_coef, n_moments, band_int, den_int, den_map,
    system_factor, guard_radius, iterations, lm_iterations, tol, keep_best,
    exact_tol, theta_out, cost_out, flags_out, cvar_out, history, n_run,
    lm_history, n_run_lm, lay, lm_stop, lm_state, lm_start, pend, first_group,
    stop_group,
):
    """SK on the lane groups ``first_group..stop_group-1`` (and LM up to
    iteration ``lm_stop``)."""
    P = U.shape[0]
    L, p = weights.shape
    s = _sk_scratch(
        F, P, L, p, n_moments, n_centre, pair_kind.shape[0], den_int.shape[0]
    )
    for group in range(first_group, stop_group):
        _sk_group(
            U, Y, bins, theta0, closed_rss, start_system, jump_limit, radius,
            weights, col_base, data_index, F, n_centre, q_basis, pair_kind,
            pair_a, pair_b, pair_nd, pair_off, ent_ptr, ent_mom, ent_coef,
            ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef, band_int, den_int,
            den_map, system_factor, guard_radius, iterations, lm_iterations,
            tol, keep_best, exact_tol, theta_out, cost_out, flags_out, cvar_out,
            history, n_run, lm_history, n_run_lm, lay, lm_stop, lm_state,
            lm_start, pend, group, s,
        )


def _sk_part_py(
    U, Y, bins, theta0, closed_rss, start_system, jump_limit, radius,
    weights, col_base, data_index, F, q_basis, pair_kind, pair_a, pair_b,
    pair_nd, pair_off, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
    rhs_ptr, rhs_mom, rhs_coef, band_int, den_int, den_map, system_factor,
    guard_radius, iterations, tol, keep_best, exact_tol, history, n_run, group,
    s,
):
    """SK for the windows ``bins[group*LANES:(group+1)*LANES]`` (lane group
    ``group``): the best estimate in ``bsr/bsi``, its cost in ``lane[1]``, the
    flags in ``flag`` and the window rows in ``rowix`` of the scratch ``s``;
    returns the number of windows in the group."""
    (sr, si, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr, gi, xr, xi,
     dr, di, scale2, polyr, polyi, resr, resi, Wt, er, ei, etr, eti, thr, thi,
     bsr, bsi, ok, k, lane, flag, tr, ti, work, hr, hi, Hsr, Hsi, gsr, gsi,
     str_, sti, ds, lm_lane, need, Gtr, Gti, rbr, rbi, ebr, ebi, rowix) = s
    # lane[0..5]: trajectory cost, best cost, SK cost, trial cost, trial rss,
    # |b|^2; flag[0..3]: active, converged, guarded, exact
    L, p = weights.shape
    n = L // 2
    P = U.shape[0]
    den = F + P
    B = bins.shape[0]
    first = group * LANES
    count = min(LANES, B - first)
    for w in range(LANES):
        rowix[w] = min(first + w, B - 1)
        k[w] = bins[rowix[w]]
    _compiled._gather(U, Y, k, F, n, sr, si)
    for t in range(pair_kind.shape[0]):
        _compiled._pair_series(
            sr, si, pair_kind[t], pair_a[t], pair_b[t], Sar[t], Sai[t]
        )
    for i in range(p):
        for w in range(LANES):
            row = min(first + w, B - 1)
            thr[i, w] = theta0[row, i, 0]
            thi[i, w] = theta0[row, i, 1]
            bsr[i, w] = thr[i, w]
            bsi[i, w] = thi[i, w]
    _compiled._residual(sr, si, thr, thi, weights, col_base, data_index, F,
                        polyr, polyi, resr, resi)
    _denominator(polyr, polyi, den, er, ei)
    total_sk = 0.0
    total_oe = 0.0
    for w in range(LANES):
        cost = 0.0
        bb = 0.0
        for q in range(P):
            for r in range(L):
                cost += (resr[q, r, w] ** 2 + resi[q, r, w] ** 2) / (
                    er[r, w] ** 2 + ei[r, w] ** 2
                )
                bb += sr[F, q, r, w] ** 2 + si[F, q, r, w] ** 2
        lane[0, w] = cost
        lane[1, w] = cost
        lane[2, w] = closed_rss[min(first + w, B - 1)]
        exact = cost <= exact_tol * bb
        flag[0, w] = not exact
        flag[1, w] = exact
        flag[2, w] = False
        flag[3, w] = exact
        if w < count:
            total_sk += lane[2, w]
            total_oe += cost
    history[group, 0, 0] = total_sk
    history[group, 0, 1] = total_oe
    run = 0
    for it in range(1, iterations + 1):
        busy = False
        for w in range(count):
            busy = busy or flag[0, w]
        if not busy:
            for later in range(it, iterations + 1):
                history[group, later, 0] = history[group, it - 1, 0]
                history[group, later, 1] = history[group, it - 1, 1]
            break
        run = it
        for r in range(L):
            for w in range(LANES):
                Wt[r, w] = 1.0 / (er[r, w] ** 2 + ei[r, w] ** 2)
        _weighted_gram(
            Sar, Sai, Wt, Tr, Ti, q_basis, pair_off, pair_nd, Er, Ei, Or, Oi,
            mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr,
            rhs_mom, rhs_coef, Hr, Hi, gr, gi,
        )
        _compiled._cholesky(Hr, Hi, scale2, ok, 0.0, p)
        _compiled._chol_solve(Hr, Hi, gr, gi, xr, xi, p)
        # one step of refinement on the weighted residual (_weighted_solve)
        _compiled._residual(sr, si, xr, xi, weights, col_base, data_index, F,
                            polyr, polyi, resr, resi)
        for q in range(P):
            for r in range(L):
                for w in range(LANES):
                    resr[q, r, w] *= Wt[r, w]
                    resi[q, r, w] *= Wt[r, w]
        _compiled._adjoint(sr, si, resr, resi, weights, col_base, data_index, F,
                           polyr, polyi, gr, gi)
        _compiled._chol_solve(Hr, Hi, gr, gi, dr, di, p)
        for i in range(p):
            for w in range(LANES):
                xr[i, w] += dr[i, w]
                xi[i, w] += di[i, w]
        _compiled._residual(sr, si, xr, xi, weights, col_base, data_index, F,
                            polyr, polyi, resr, resi)
        _denominator(polyr, polyi, den, etr, eti)
        for w in range(LANES):
            cost = 0.0
            rss = 0.0
            for q in range(P):
                for r in range(L):
                    sq = resr[q, r, w] ** 2 + resi[q, r, w] ** 2
                    rss += Wt[r, w] * sq
                    cost += sq / (etr[r, w] ** 2 + eti[r, w] ** 2)
            lane[3, w] = cost
            lane[4, w] = rss
        total_sk = 0.0
        total_oe = 0.0
        for w in range(count):
            row = first + w
            if flag[0, w]:
                finite = np.isfinite(lane[3, w])
                for i in range(p):
                    finite = finite and np.isfinite(xr[i, w])
                    finite = finite and np.isfinite(xi[i, w])
                if not (ok[w] and finite):
                    flag[0, w] = False
                elif _rejected(
                    xr, xi, w, row, band_int, system_factor, start_system,
                    jump_limit, den_int, den_map, guard_radius, radius, work,
                ):
                    flag[0, w] = False
                    flag[2, w] = True
                else:
                    change = abs(lane[3, w] - lane[0, w]) / lane[0, w]
                    lane[0, w] = lane[3, w]
                    for i in range(p):
                        thr[i, w] = xr[i, w]
                        thi[i, w] = xi[i, w]
                    for r in range(L):
                        er[r, w] = etr[r, w]
                        ei[r, w] = eti[r, w]
                    if not keep_best or lane[3, w] < lane[1, w]:
                        lane[1, w] = lane[3, w]
                        for i in range(p):
                            bsr[i, w] = xr[i, w]
                            bsi[i, w] = xi[i, w]
                    lane[2, w] = lane[4, w]
                    if change < tol:
                        flag[0, w] = False
                        flag[1, w] = True
            total_sk += lane[2, w]
            total_oe += lane[1, w]
        history[group, it, 0] = total_sk
        history[group, it, 1] = total_oe
    n_run[group] = run
    return count


def _sk_group_py(
    U, Y, bins, theta0, closed_rss, start_system, jump_limit, radius,
    weights, col_base, data_index, F, n_centre, q_basis, pair_kind, pair_a,
    pair_b, pair_nd, pair_off, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
    rhs_ptr, rhs_mom, rhs_coef, band_int, den_int, den_map,
    system_factor, guard_radius, iterations, lm_iterations, tol, keep_best,
    exact_tol, theta_out, cost_out, flags_out, cvar_out, history, n_run,
    lm_history, n_run_lm, lay, lm_stop, lm_state, lm_start, pend, group, s,
):
    """SK for the windows ``bins[group*LANES:(group+1)*LANES]``, then LM up
    to iteration ``lm_stop``; windows still active there are left in
    ``pend`` for :func:`_lm_group`."""
    (sr, si, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr, gi, xr, xi,
     dr, di, scale2, polyr, polyi, resr, resi, Wt, er, ei, etr, eti, thr, thi,
     bsr, bsi, ok, k, lane, flag, tr, ti, work, hr, hi, Hsr, Hsi, gsr, gsi,
     str_, sti, ds, lm_lane, need, Gtr, Gti, rbr, rbi, ebr, ebi, rowix) = s
    count = _sk_part(
        U, Y, bins, theta0, closed_rss, start_system, jump_limit, radius,
        weights, col_base, data_index, F, q_basis, pair_kind, pair_a, pair_b,
        pair_nd, pair_off, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
        rhs_ptr, rhs_mom, rhs_coef, band_int, den_int, den_map, system_factor,
        guard_radius, iterations, tol, keep_best, exact_tol, history, n_run,
        group, s,
    )
    lm_run = 0
    if lm_iterations > 0:
        lm_run = _lm_phase(
            sr, si, hr, hi, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi,
            gr, gi, xr, xi, scale2, polyr, polyi, resr, resi, Wt, etr, eti,
            bsr, bsi, ok, lane, flag, work, Hsr, Hsi, gsr, gsi, str_, sti, ds,
            lm_lane, need, Gtr, Gti, rbr, rbi, ebr, ebi, weights, col_base,
            data_index, F, q_basis, pair_kind, pair_a, pair_b, pair_nd,
            pair_off, band_int, den_int, den_map, system_factor, guard_radius,
            start_system, jump_limit, radius, 0, lm_stop, True, tol,
            lm_history, group, rowix, count, lay,
        )
        n_run_lm[group] = lm_run
    _finish_group(
        sr, si, hr, hi, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr,
        gi, scale2, polyr, polyi, resr, resi, Wt, er, ei, bsr, bsi, ok, lane,
        flag, tr, ti, str_, sti, lm_lane, rowix, count, weights, col_base,
        data_index, F, n_centre, q_basis, pair_kind, pair_a, pair_b, pair_nd,
        pair_off, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr,
        rhs_mom, rhs_coef, lm_iterations, 0, lm_run, lm_stop, lm_history,
        group, theta_out, cost_out, flags_out, cvar_out, lm_state, lm_start,
        pend,
    )


def _finish_group_py(
    sr, si, hr, hi, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr, gi,
    scale2, polyr, polyi, resr, resi, Wt, er, ei, bsr, bsi, ok, lane, flag, tr,
    ti, str_, sti, lm_lane, rowix, count, weights, col_base, data_index, F,
    n_centre, q_basis, pair_kind, pair_a, pair_b, pair_nd, pair_off, ent_ptr,
    ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef,
    lm_iterations, start, run, stop, lm_history, group, theta_out, cost_out,
    flags_out, cvar_out, lm_state, lm_start, pend,
):
    """End of a lane group's LM iterations ``start..stop-1`` (``run``: one
    past the last run): the LM cost sums of the iterations not run, the state
    of the windows still active at ``stop < lm_iterations`` saved for the
    next stage (``pend``, ``lm_state``, ``lm_start``, the estimate in
    ``theta_out``, the guard flag in ``flags_out``), and the results of the
    others: estimate, cost, flags and the Lemma 2 covariance."""
    p = weights.shape[1]
    n_done = count
    if lm_iterations > 0:
        total = 0.0  # every window: the sums of the iterations not run
        done = 0.0  # the finished windows: their sums in the later stages
        for w in range(count):
            total += lane[1, w]
            if flag[0, w] and stop < lm_iterations:
                row = rowix[w]
                pend[row] = True
                lm_state[row, 0] = lane[1, w]
                lm_state[row, 1] = lm_lane[0, w]
                lm_state[row, 2] = lm_lane[1, w]
                flags_out[row, 1] = flag[2, w]
                for i in range(p):
                    theta_out[row, i, 0] = bsr[i, w]
                    theta_out[row, i, 1] = bsi[i, w]
                    lm_start[row, i, 0] = str_[i, w]
                    lm_start[row, i, 1] = sti[i, w]
                n_done -= 1
            else:
                done += lane[1, w]
        for it in range(max(run, start), stop):
            lm_history[group, it] = total
        for it in range(stop, lm_iterations):
            lm_history[group, it] = done
    if n_done == 0:
        return
    lm = lm_iterations > 0
    skip_active = lm and stop < lm_iterations
    _write_results(
        sr, si, hr, hi, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr,
        gi, scale2, polyr, polyi, resr, resi, Wt, er, ei, bsr, bsi, ok, lane,
        flag, tr, ti, rowix, count, weights, col_base, data_index, F, n_centre,
        q_basis, pair_kind, pair_a, pair_b, pair_nd, pair_off, ent_ptr, ent_mom,
        ent_coef, ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef,
        lm, skip_active,
        theta_out, cost_out, flags_out, cvar_out,
    )


def _write_results_py(
    sr, si, hr, hi, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr, gi,
    scale2, polyr, polyi, resr, resi, Wt, er, ei, bsr, bsi, ok, lane, flag, tr,
    ti, rowix, count, weights, col_base, data_index, F, n_centre, q_basis,
    pair_kind, pair_a, pair_b, pair_nd, pair_off, ent_ptr, ent_mom, ent_coef,
    ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef, lm, skip_active,
    theta_out, cost_out, flags_out, cvar_out,
):
    """Results of the lanes ``0..count-1`` (``skip_active``: not of those
    still active): the estimate ``bsr/bsi``, its cost ``lane[1]``, the flags
    ``flag[1:3]`` and the Lemma 2 covariance at the estimate (``lm``: of
    ``J^H J``; ``hr/hi[:F]`` hold the window's inputs)."""
    P = sr.shape[1]
    L, p = weights.shape
    den = F + P
    # Lemma 2 on the problem reweighted by the final estimate (LM: J^H J, the
    # denominator columns built from yhat)
    _compiled._residual(sr, si, bsr, bsi, weights, col_base, data_index, F,
                        polyr, polyi, resr, resi)
    _denominator(polyr, polyi, den, er, ei)
    for r in range(L):
        for w in range(LANES):
            Wt[r, w] = 1.0 / (er[r, w] ** 2 + ei[r, w] ** 2)
    if lm:
        _hat_series(sr, si, resr, resi, er, ei, F, hr, hi, pair_kind, pair_a,
                    pair_b, Sar, Sai)
    _weighted_gram(
        Sar, Sai, Wt, Tr, Ti, q_basis, pair_off, pair_nd, Er, Ei, Or, Oi,
        mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr,
        rhs_mom, rhs_coef, Hr, Hi, gr, gi,
    )
    _compiled._cholesky(Hr, Hi, scale2, ok, 0.0, p)
    _compiled._tail_inverse(Hr, Hi, n_centre, p, tr, ti)
    for w in range(count):
        if skip_active and flag[0, w]:
            continue
        row = rowix[w]
        for i in range(p):
            theta_out[row, i, 0] = bsr[i, w]
            theta_out[row, i, 1] = bsi[i, w]
        cost_out[row] = lane[1, w]
        flags_out[row, 0] = flag[1, w]
        flags_out[row, 1] = flag[2, w]
        if ok[w]:
            _compiled._write_tail_cov(tr, ti, w, cvar_out, row)
        else:
            for c in range(n_centre):
                for d in range(n_centre):
                    cvar_out[row, c, d, 0] = np.nan
                    cvar_out[row, c, d, 1] = np.nan


def _lm_range_py(
    U, Y, bins, rows, start_system, jump_limit, radius, weights, col_base,
    data_index, F, n_centre, q_basis, pair_kind, pair_a, pair_b, pair_nd,
    pair_off, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr,
    rhs_mom, rhs_coef, n_moments, band_int, den_int, den_map, system_factor,
    guard_radius, lm_iterations, tol, theta_out, cost_out, flags_out, cvar_out,
    lm_history, n_run_lm, lay, start, stop, lm_state, lm_start, pend,
    first_group, stop_group,
):
    """LM iterations ``start..stop-1`` of the windows ``rows`` (packed
    densely into lane groups), groups ``first_group..stop_group-1``."""
    P = U.shape[0]
    L, p = weights.shape
    s = _sk_scratch(
        F, P, L, p, n_moments, n_centre, pair_kind.shape[0], den_int.shape[0]
    )
    for group in range(first_group, stop_group):
        _lm_group(
            U, Y, bins, rows, start_system, jump_limit, radius, weights,
            col_base, data_index, F, n_centre, q_basis, pair_kind, pair_a,
            pair_b, pair_nd, pair_off, ent_ptr, ent_mom, ent_coef, ent_conj,
            ent_const, rhs_ptr, rhs_mom, rhs_coef, band_int, den_int, den_map,
            system_factor, guard_radius, lm_iterations, tol, theta_out,
            cost_out, flags_out, cvar_out, lm_history, n_run_lm, lay, start,
            stop, lm_state, lm_start, pend, group, s,
        )


def _lm_group_py(
    U, Y, bins, rows, start_system, jump_limit, radius, weights, col_base,
    data_index, F, n_centre, q_basis, pair_kind, pair_a, pair_b, pair_nd,
    pair_off, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr,
    rhs_mom, rhs_coef, band_int, den_int, den_map, system_factor,
    guard_radius, lm_iterations, tol, theta_out, cost_out, flags_out, cvar_out,
    lm_history, n_run_lm, lay, start, stop, lm_state, lm_start, pend, group, s,
):
    """LM from iteration ``start`` for the windows
    ``rows[group*LANES:(group+1)*LANES]``, each resumed from the state
    :func:`_finish_group` saved: its data gathered again, its model rebuilt
    from the estimate (the model of an estimate is a function of it alone,
    so the iterates are those of an uninterrupted run)."""
    (sr, si, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr, gi, xr, xi,
     dr, di, scale2, polyr, polyi, resr, resi, Wt, er, ei, etr, eti, thr, thi,
     bsr, bsi, ok, k, lane, flag, tr, ti, work, hr, hi, Hsr, Hsi, gsr, gsi,
     str_, sti, ds, lm_lane, need, Gtr, Gti, rbr, rbi, ebr, ebi, rowix) = s
    L, p = weights.shape
    n = L // 2
    R = rows.shape[0]
    first = group * LANES
    count = min(LANES, R - first)
    for w in range(LANES):
        row = rows[min(first + w, R - 1)]
        rowix[w] = row
        k[w] = bins[row]
        pend[row] = False
        for i in range(p):
            bsr[i, w] = theta_out[row, i, 0]
            bsi[i, w] = theta_out[row, i, 1]
            str_[i, w] = lm_start[row, i, 0]
            sti[i, w] = lm_start[row, i, 1]
        lane[1, w] = lm_state[row, 0]
        lm_lane[0, w] = lm_state[row, 1]
        lm_lane[1, w] = lm_state[row, 2]
        flag[0, w] = True
        flag[1, w] = False
        flag[2, w] = flags_out[row, 1]
        flag[3, w] = False
        need[0, w] = True
    _compiled._gather(U, Y, k, F, n, sr, si)
    for t in range(pair_kind.shape[0]):
        _compiled._pair_series(
            sr, si, pair_kind[t], pair_a[t], pair_b[t], Sar[t], Sai[t]
        )
    run = _lm_phase(
        sr, si, hr, hi, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi,
        gr, gi, xr, xi, scale2, polyr, polyi, resr, resi, Wt, etr, eti,
        bsr, bsi, ok, lane, flag, work, Hsr, Hsi, gsr, gsi, str_, sti, ds,
        lm_lane, need, Gtr, Gti, rbr, rbi, ebr, ebi, weights, col_base,
        data_index, F, q_basis, pair_kind, pair_a, pair_b, pair_nd,
        pair_off, band_int, den_int, den_map, system_factor, guard_radius,
        start_system, jump_limit, radius, start, stop, False, tol,
        lm_history, group, rowix, count, lay,
    )
    n_run_lm[group] = run
    _finish_group(
        sr, si, hr, hi, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr,
        gi, scale2, polyr, polyi, resr, resi, Wt, er, ei, bsr, bsi, ok, lane,
        flag, tr, ti, str_, sti, lm_lane, rowix, count, weights, col_base,
        data_index, F, n_centre, q_basis, pair_kind, pair_a, pair_b, pair_nd,
        pair_off, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr,
        rhs_mom, rhs_coef, lm_iterations, start, run, stop, lm_history,
        group, theta_out, cost_out, flags_out, cvar_out, lm_state, lm_start,
        pend,
    )


def _hat_series_py(sr, si, resr, resi, er, ei, F, hr, hi, pair_kind, pair_a,
                   pair_b, Sar, Sai):
    """Denominator base ``-yhat = -(Y - res / e)`` in ``hr/hi[F]`` and the
    pair series that involve it (the other bases ``hr/hi[:F]`` are the
    window's inputs, copied from ``sr/si`` once by :func:`_lm_phase`)."""
    P = sr.shape[1]
    L = sr.shape[2]
    for q in range(P):
        for r in range(L):
            for w in range(LANES):
                inv = 1.0 / (er[r, w] ** 2 + ei[r, w] ** 2)
                rr = resr[q, r, w]
                ri = resi[q, r, w]
                hr[F, q, r, w] = sr[F, q, r, w] + (rr * er[r, w] + ri * ei[r, w]) * inv
                hi[F, q, r, w] = si[F, q, r, w] + (ri * er[r, w] - rr * ei[r, w]) * inv
    for t in range(pair_kind.shape[0]):
        kind = pair_kind[t]
        a = pair_a[t]
        b = pair_b[t]
        uses = (kind == _DATA_DATA_ and (a == F or b == F)) or kind == _DATA_CONST_
        if uses:
            _compiled._pair_series(hr, hi, kind, a, b, Sar[t], Sai[t])


def _lm_model_py(
    sr, si, hr, hi, rbr, rbi, ebr, ebi, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi,
    Gr, Gi, gr, gi, polyr, polyi, resr, resi, Wt, F, data_index, q_basis,
    pair_kind, pair_a, pair_b, pair_nd, pair_off, lay, ds, Hsr, Hsi, gsr, gsi,
):
    """The Gauss-Newton model of every lane at the estimate (residual
    ``rbr/rbi``, denominator ``ebr/ebi``): equilibrated ``J^H J`` (packed
    lower, ``Hsr/Hsi``), ``J^H res`` (``gsr/gsi``) and the column scale
    ``ds``, all in the layout basis (docs/method.md, section 7; module
    docstring of :mod:`lrmfrf.refinement`).

    ``J = -Ahat / e``: the Gram matrix is the row-weighted one (``W = 1 /
    |e|^2``) of ``Ahat``, whose denominator base is ``-yhat``. It is formed
    from the moments of ``W S_ab`` with the layout tables ``lay`` (monomial
    columns), so no change of basis ``S H S^T`` is needed; only the pair
    series of the denominator base change with the estimate
    (:func:`_hat_series`), the others are the window's own."""
    (lweights, lcol_base, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
     rhs_ptr, rhs_mom, rhs_coef) = lay[:10]
    P = rbr.shape[0]
    L = rbr.shape[1]
    p = ds.shape[0]
    for r in range(L):
        for w in range(LANES):
            Wt[r, w] = 1.0 / (ebr[r, w] ** 2 + ebi[r, w] ** 2)
    _hat_series(sr, si, rbr, rbi, ebr, ebi, F, hr, hi, pair_kind, pair_a,
                pair_b, Sar, Sai)
    _weighted_gram(
        Sar, Sai, Wt, Tr, Ti, q_basis, pair_off, pair_nd, Er, Ei, Or, Oi,
        mr, mi, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr,
        rhs_mom, rhs_coef, Gr, Gi, gr, gi,
    )
    for q in range(P):
        for r in range(L):
            for w in range(LANES):
                resr[q, r, w] = rbr[q, r, w] * Wt[r, w]
                resi[q, r, w] = rbi[q, r, w] * Wt[r, w]
    _compiled._adjoint(hr, hi, resr, resi, lweights, lcol_base, data_index, F,
                       polyr, polyi, gr, gi)
    # equilibrate: unit diagonal; J^H r = -Ahat^H W res
    for i in range(p):
        ii = i * (i + 1) // 2 + i
        for w in range(LANES):
            d = Gr[ii, w]
            d = np.sqrt(d) if d > 0.0 else 0.0
            ds[i, w] = d if d > 0.0 else 1.0
    for i in range(p):
        ri = i * (i + 1) // 2
        for j in range(i + 1):
            for w in range(LANES):
                c = 1.0 / (ds[i, w] * ds[j, w])
                Hsr[ri + j, w] = Gr[ri + j, w] * c
                Hsi[ri + j, w] = Gi[ri + j, w] * c
        for w in range(LANES):
            gsr[i, w] = -gr[i, w] / ds[i, w]
            gsi[i, w] = -gi[i, w] / ds[i, w]


def _lm_step_py(Hsr, Hsi, gsr, gsi, ds, damping, bsr, bsi, s_ptr, s_col, s_val,
                Hr, Hi, gr, gi, scale2, ok, xr, xi):
    """Trial estimate ``x = theta + S^T (z / ds)`` of every lane, ``z`` the
    solution of the damped equilibrated system ``(Hs + lambda I) z = -gs``
    (Marquardt's damping on the unit diagonal, layout basis; ``S`` real with
    sparse rows ``s_ptr/s_col/s_val`` maps a layout step to the internal
    basis). ``ok[w]`` False where the Cholesky factorisation failed."""
    p = ds.shape[0]
    for e in range(Hsr.shape[0]):
        for w in range(LANES):
            Hr[e, w] = Hsr[e, w]
            Hi[e, w] = Hsi[e, w]
    for i in range(p):
        ii = i * (i + 1) // 2 + i
        for w in range(LANES):
            Hr[ii, w] += damping[w]
            gr[i, w] = -gsr[i, w]
            gi[i, w] = -gsi[i, w]
    _compiled._cholesky(Hr, Hi, scale2, ok, 0.0, p)
    _compiled._chol_solve(Hr, Hi, gr, gi, xr, xi, p)
    for i in range(p):  # the layout step, scaled back
        for w in range(LANES):
            xr[i, w] /= ds[i, w]
            xi[i, w] /= ds[i, w]
    for i in range(p):  # internal step S^T step: gr/gi as work space
        for w in range(LANES):
            gr[i, w] = bsr[i, w]
            gi[i, w] = bsi[i, w]
    for a in range(p):
        for z in range(s_ptr[a], s_ptr[a + 1]):
            c = s_val[z]
            i = s_col[z]
            for w in range(LANES):
                gr[i, w] += c * xr[a, w]
                gi[i, w] += c * xi[a, w]
    for i in range(p):
        for w in range(LANES):
            xr[i, w] = gr[i, w]
            xi[i, w] = gi[i, w]


def _oe_cost_py(resr, resi, er, ei, out):
    """Output-error cost ``J_LS = sum_q sum_r |res / e|^2`` of every lane
    (eq. CostFunction; summed in the order of the numpy path)."""
    P = resr.shape[0]
    L = resr.shape[1]
    for w in range(LANES):
        out[w] = 0.0
    for q in range(P):
        for r in range(L):
            for w in range(LANES):
                out[w] += (resr[q, r, w] ** 2 + resi[q, r, w] ** 2) / (
                    er[r, w] ** 2 + ei[r, w] ** 2
                )


def _keep_accepted_py(accepted, resr, resi, er, ei, rbr, rbi, ebr, ebi):
    """Residual and denominator of the lanes whose trial was accepted become
    those at the estimate (the next model is built from them)."""
    P = resr.shape[0]
    L = resr.shape[1]
    for q in range(P):
        for r in range(L):
            for w in range(LANES):
                if accepted[w]:
                    rbr[q, r, w] = resr[q, r, w]
                    rbi[q, r, w] = resi[q, r, w]
    for r in range(L):
        for w in range(LANES):
            if accepted[w]:
                ebr[r, w] = er[r, w]
                ebi[r, w] = ei[r, w]


def _lm_decide_py(
    w, row, p, tol, ok, xr, xi, bsr, bsi, str_, sti, lane, lm_lane, flag, need,
    band_int, system_factor, start_system, jump_limit, den_int, den_map,
    guard_radius, radius, work,
):
    """Accept or reject lane ``w``'s LM step (shared by :func:`_lm_phase_py`
    and :func:`_lm_refill_range_py`): a decrease of the cost that the guard
    does not reject becomes the lane's estimate (``bs``) with the damping
    divided by 10, and stops the lane when the relative change is below
    ``tol``; a guard hit restores the estimate LM started from (``st``) and
    stops; otherwise the damping grows 10x (the lane stops above 1e12)."""
    cost = lm_lane[2, w]
    decrease = ok[w] and np.isfinite(cost) and cost < lane[1, w]
    hit = decrease and _rejected(
        xr, xi, w, row, band_int, system_factor, start_system,
        jump_limit, den_int, den_map, guard_radius, radius, work,
    )
    if hit:  # back to the estimate LM started from, stop
        flag[2, w] = True
        flag[0, w] = False
        lane[1, w] = lm_lane[1, w]
        for i in range(p):
            bsr[i, w] = str_[i, w]
            bsi[i, w] = sti[i, w]
    if decrease and not hit:
        change = (lane[1, w] - cost) / lane[1, w]
        lane[1, w] = cost
        need[1, w] = True
        for i in range(p):
            bsr[i, w] = xr[i, w]
            bsi[i, w] = xi[i, w]
        lm_lane[0, w] = max(lm_lane[0, w] / 10.0, 1e-12)
        if change < tol:
            flag[0, w] = False
            flag[1, w] = True
        else:
            need[0, w] = True
    else:
        lm_lane[0, w] *= 10.0
        if lm_lane[0, w] > 1e12:
            flag[0, w] = False
            flag[1, w] = True


def _lm_phase_py(
    sr, si, hr, hi, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi,
    gr, gi, xr, xi, scale2, polyr, polyi, resr, resi, Wt, etr, eti,
    bsr, bsi, ok, lane, flag, work, Hsr, Hsi, gsr, gsi, str_, sti, ds,
    lm_lane, need, Gtr, Gti, rbr, rbi, ebr, ebi, weights, col_base,
    data_index, F, q_basis, pair_kind, pair_a, pair_b, pair_nd, pair_off,
    band_int, den_int, den_map, system_factor, guard_radius, start_system,
    jump_limit, radius, start, stop, fresh, tol, lm_history, group, rowix,
    count, lay,
):
    """Guarded LM of :func:`lrmfrf.refinement._levenberg_marquardt` from the
    estimate in ``bsr/bsi`` (cost ``lane[1]``), iterations ``start..stop-1``;
    returns one past the last iteration run (``start`` if none). ``fresh``:
    LM starts here (else the caller set the lanes' flags, damping, start
    estimate and ``need[0]``).
    ``lm_lane[0..2]``: damping, start cost, trial cost; ``need[0]``: the
    Gauss-Newton model must be rebuilt, ``need[1]``: the trial was accepted.
    The model is damped in the layout basis (``theta_internal = theta_layout
    S``), as numpy does: Marquardt's damping is not invariant to a change of
    basis. Per iteration: the model where some lane moved
    (:func:`_lm_model`, from the residual kept at the estimate), the damped
    solve (:func:`_lm_step`), one residual pass for the trial cost
    (:func:`_oe_cost`) and the guard of the lanes whose cost decreased."""
    s_ptr, s_col, s_val = lay[10], lay[11], lay[12]
    L, p = weights.shape
    P = sr.shape[1]
    den = F + P
    for w in range(LANES):
        if fresh:
            flag[0, w] = not flag[3, w]  # active: not an exact fit
            flag[1, w] = flag[3, w]  # converged
            need[0, w] = flag[0, w]
            lm_lane[0, w] = 1e-3
            lm_lane[1, w] = lane[1, w]
            for i in range(p):
                str_[i, w] = bsr[i, w]
                sti[i, w] = bsi[i, w]
    for f in range(F):  # the input bases of Ahat are the window's own
        for q in range(P):
            for r in range(L):
                for w in range(LANES):
                    hr[f, q, r, w] = sr[f, q, r, w]
                    hi[f, q, r, w] = si[f, q, r, w]
    _compiled._residual(sr, si, bsr, bsi, weights, col_base, data_index, F,
                        polyr, polyi, rbr, rbi)
    _denominator(polyr, polyi, den, ebr, ebi)
    run = start
    for it in range(start, stop):
        rebuild = False
        for w in range(count):
            rebuild = rebuild or need[0, w]
        if rebuild:  # lanes without a new estimate get the model they had
            _lm_model(
                sr, si, hr, hi, rbr, rbi, ebr, ebi, Sar, Sai, Tr, Ti, Er, Ei,
                Or, Oi, mr, mi, Gtr, Gti, gr, gi, polyr, polyi, resr, resi, Wt,
                F, data_index, q_basis, pair_kind, pair_a, pair_b, pair_nd,
                pair_off, lay, ds, Hsr, Hsi, gsr, gsi,
            )
        busy = False
        for w in range(count):
            busy = busy or flag[0, w]
        if not busy:
            break
        run = it + 1
        _lm_step(Hsr, Hsi, gsr, gsi, ds, lm_lane[0], bsr, bsi, s_ptr, s_col,
                 s_val, Hr, Hi, gr, gi, scale2, ok, xr, xi)
        _compiled._residual(sr, si, xr, xi, weights, col_base, data_index, F,
                            polyr, polyi, resr, resi)
        _denominator(polyr, polyi, den, etr, eti)
        _oe_cost(resr, resi, etr, eti, lm_lane[2])
        total = 0.0
        for w in range(LANES):
            need[1, w] = False
        for w in range(count):
            need[0, w] = False
            row = rowix[w]
            if flag[0, w]:
                _lm_decide(
                    w, row, p, tol, ok, xr, xi, bsr, bsi, str_, sti, lane, lm_lane,
                    flag, need, band_int, system_factor, start_system, jump_limit,
                    den_int, den_map, guard_radius, radius, work,
                )
            total += lane[1, w]
        _keep_accepted(need[1], resr, resi, etr, eti, rbr, rbi, ebr, ebi)
        lm_history[group, it] = total
    return run


def _load_lane_py(src, v, s, w, F):
    """Window of lane ``v`` of the SK group ``src`` into lane ``w`` of the LM
    group ``s``, starting LM (the state :func:`_lm_phase` sets when
    ``fresh``): data, pair series, estimate with its residual and
    denominator, cost, damping and flags; its model is to be built."""
    (sr, si, Sar, Sai, _, _, _, _, _, _, _, _, _, _, _, _, _, _, _, _, _, _, _,
     _, _, _, _, _, _, _, _, _, bsr, bsi, _, k, lane, flag, _, _, _, _, _, _, _,
     _, _, _, _, _, _, _, _, _, rbr, rbi, ebr, ebi, rowix) = src
    (tsr, tsi, tSar, tSai, _, _, _, _, _, _, _, _, _, _, _, _, _, _, _, _, _, _,
     _, _, _, _, _, _, _, _, _, _, tbsr, tbsi, _, tk, tlane, tflag, _, _, _, thr,
     thi, _, _, _, _, tstr, tsti, _, tlm, tneed, _, _, trbr, trbi, tebr, tebi,
     trowix) = s
    for a in range(sr.shape[0]):
        for q in range(sr.shape[1]):
            for r in range(sr.shape[2]):
                tsr[a, q, r, w] = sr[a, q, r, v]
                tsi[a, q, r, w] = si[a, q, r, v]
                if a < F:  # the input bases of Ahat are the window's own
                    thr[a, q, r, w] = sr[a, q, r, v]
                    thi[a, q, r, w] = si[a, q, r, v]
    for t in range(Sar.shape[0]):
        for r in range(Sar.shape[1]):
            tSar[t, r, w] = Sar[t, r, v]
            tSai[t, r, w] = Sai[t, r, v]
    for q in range(rbr.shape[0]):
        for r in range(rbr.shape[1]):
            trbr[q, r, w] = rbr[q, r, v]
            trbi[q, r, w] = rbi[q, r, v]
    for r in range(ebr.shape[0]):
        tebr[r, w] = ebr[r, v]
        tebi[r, w] = ebi[r, v]
    for i in range(bsr.shape[0]):
        tbsr[i, w] = bsr[i, v]
        tbsi[i, w] = bsi[i, v]
        tstr[i, w] = bsr[i, v]
        tsti[i, w] = bsi[i, v]
    tlane[1, w] = lane[1, v]
    tlm[0, w] = 1e-3
    tlm[1, w] = lane[1, v]
    tflag[0, w] = True
    tflag[1, w] = False
    tflag[2, w] = flag[2, v]
    tflag[3, w] = False
    tneed[0, w] = True
    tneed[1, w] = False
    tk[w] = k[v]
    trowix[w] = rowix[v]


def _push_result_py(fin, n_fin, row, kbin, bsr, bsi, v, cost, converged, guarded):
    """Queue a finished window (row ``row``, bin ``kbin``; estimate lane
    ``v`` of ``bsr/bsi``, its cost and flags) in lane ``n_fin`` of the result
    group ``fin``; returns the number queued."""
    fbsr, fbsi, fk, flane, fflag, frowix = (
        fin[32], fin[33], fin[35], fin[36], fin[37], fin[58]
    )
    for i in range(bsr.shape[0]):
        fbsr[i, n_fin] = bsr[i, v]
        fbsi[i, n_fin] = bsi[i, v]
    fk[n_fin] = kbin
    frowix[n_fin] = row
    flane[1, n_fin] = cost
    fflag[0, n_fin] = False
    fflag[1, n_fin] = converged
    fflag[2, n_fin] = guarded
    return n_fin + 1


def _flush_results_py(
    U, Y, fin, count, weights, col_base, data_index, F, n_centre, q_basis,
    pair_kind, pair_a, pair_b, pair_nd, pair_off, ent_ptr, ent_mom, ent_coef,
    ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef, theta_out, cost_out,
    flags_out, cvar_out,
):
    """Results of the ``count`` windows queued in ``fin`` (their data
    gathered again): :func:`_write_results` after LM."""
    (sr, si, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr, gi, xr, xi,
     dr, di, scale2, polyr, polyi, resr, resi, Wt, er, ei, etr, eti, thr, thi,
     bsr, bsi, ok, k, lane, flag, tr, ti, work, hr, hi, Hsr, Hsi, gsr, gsi,
     str_, sti, ds, lm_lane, need, Gtr, Gti, rbr, rbi, ebr, ebi, rowix) = fin
    n = weights.shape[0] // 2
    for w in range(count, LANES):  # pad with the last window
        k[w] = k[count - 1]
        for i in range(bsr.shape[0]):
            bsr[i, w] = bsr[i, count - 1]
            bsi[i, w] = bsi[i, count - 1]
    _compiled._gather(U, Y, k, F, n, sr, si)
    for t in range(pair_kind.shape[0]):
        _compiled._pair_series(
            sr, si, pair_kind[t], pair_a[t], pair_b[t], Sar[t], Sai[t]
        )
    for f in range(F):
        for q in range(sr.shape[1]):
            for r in range(sr.shape[2]):
                for w in range(LANES):
                    hr[f, q, r, w] = sr[f, q, r, w]
                    hi[f, q, r, w] = si[f, q, r, w]
    _write_results(
        sr, si, hr, hi, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr,
        gi, scale2, polyr, polyi, resr, resi, Wt, er, ei, bsr, bsi, ok, lane,
        flag, tr, ti, rowix, count, weights, col_base, data_index, F, n_centre,
        q_basis, pair_kind, pair_a, pair_b, pair_nd, pair_off, ent_ptr, ent_mom,
        ent_coef, ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef, True, False,
        theta_out, cost_out, flags_out, cvar_out,
    )


def _lm_refill_range_py(
    U, Y, bins, theta0, closed_rss, start_system, jump_limit, radius,
    weights, col_base, data_index, F, n_centre, q_basis, pair_kind, pair_a,
    pair_b, pair_nd, pair_off, ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
    rhs_ptr, rhs_mom, rhs_coef, n_moments, band_int, den_int, den_map,
    system_factor, guard_radius, iterations, lm_iterations, tol, keep_best,
    exact_tol, theta_out, cost_out, flags_out, cvar_out, history, n_run,
    lm_history, n_run_lm, lay, task, first_group, stop_group, stride,
):
    """SK on the lane groups ``range(first_group, stop_group, stride)`` and
    guarded LM of their windows with continuous lane refill (task ``task``).

    The SK groups run one at a time (:func:`_sk_part`, as :func:`_sk_group`);
    their windows enter the LM group lane by lane (:func:`_load_lane`): a
    lane whose window stops takes the next window at once, so the LM group
    runs full until the task's windows are exhausted. Every lane keeps its own
    iteration count; the iteration body is :func:`_lm_phase`'s. Finished
    windows (and exact fits, which skip LM) are queued and their results
    written a full group at a time (:func:`_flush_results`). The iterates of
    a window depend neither on its lane nor on its neighbours, so the results
    are bit for bit those of :func:`_sk_group`. ``lm_history[task, it]``: the
    sum of the windows' LM costs after iteration ``it`` (the final cost after
    a window's last); ``n_run_lm[task]``: the most iterations a window ran."""
    P = U.shape[0]
    L, p = weights.shape
    den = F + P
    n_pairs = pair_kind.shape[0]
    n_den = den_int.shape[0]
    src = _sk_scratch(F, P, L, p, n_moments, n_centre, n_pairs, n_den)
    fin = _sk_scratch(F, P, L, p, n_moments, n_centre, n_pairs, n_den)
    s = _sk_scratch(F, P, L, p, n_moments, n_centre, n_pairs, n_den)
    (sr, si, Sar, Sai, Tr, Ti, Er, Ei, Or, Oi, mr, mi, Hr, Hi, gr, gi, xr, xi,
     dr, di, scale2, polyr, polyi, resr, resi, Wt, er, ei, etr, eti, thr, thi,
     bsr, bsi, ok, k, lane, flag, tr, ti, work, hr, hi, Hsr, Hsi, gsr, gsi,
     str_, sti, ds, lm_lane, need, Gtr, Gti, rbr, rbi, ebr, ebi, rowix) = s
    s_ptr, s_col, s_val = lay[10], lay[11], lay[12]
    src_bsr, src_bsi, src_k, src_lane, src_flag, src_rowix = (
        src[32], src[33], src[35], src[36], src[37], src[58]
    )
    hist = lm_history[task]
    lane_it = np.zeros(LANES, np.int64)
    held = np.zeros(LANES, np.bool_)  # the lane holds a window
    for w in range(LANES):
        flag[0, w] = False
        need[0, w] = False
    group = first_group
    src_count = 0
    src_next = 0
    n_fin = 0
    most = 0
    filled = False  # every lane has held a window (valid data)
    while True:
        for w in range(LANES):
            if flag[0, w]:
                continue
            if held[w]:  # its window stopped after lane_it[w] iterations
                held[w] = False
                need[0, w] = False
                for it in range(lane_it[w], lm_iterations):
                    hist[it] += lane[1, w]
                most = max(most, lane_it[w])
                n_fin = _push_result(fin, n_fin, rowix[w], k[w], bsr, bsi, w,
                                     lane[1, w], flag[1, w], flag[2, w])
                if n_fin == LANES:
                    _flush_results(
                        U, Y, fin, n_fin, weights, col_base, data_index, F,
                        n_centre, q_basis, pair_kind, pair_a, pair_b, pair_nd,
                        pair_off, ent_ptr, ent_mom, ent_coef, ent_conj,
                        ent_const, rhs_ptr, rhs_mom, rhs_coef, theta_out,
                        cost_out, flags_out, cvar_out,
                    )
                    n_fin = 0
            while not held[w]:  # the next window of the task that needs LM
                if src_next == src_count:
                    if group >= stop_group:
                        break
                    src_count = _sk_part(
                        U, Y, bins, theta0, closed_rss, start_system,
                        jump_limit, radius, weights, col_base, data_index, F,
                        q_basis, pair_kind, pair_a, pair_b, pair_nd, pair_off,
                        ent_ptr, ent_mom, ent_coef, ent_conj, ent_const,
                        rhs_ptr, rhs_mom, rhs_coef, band_int, den_int,
                        den_map, system_factor, guard_radius, iterations, tol,
                        keep_best, exact_tol, history, n_run, group, src,
                    )
                    _compiled._residual(
                        src[0], src[1], src_bsr, src_bsi, weights, col_base,
                        data_index, F, src[21], src[22], src[54], src[55],
                    )
                    _denominator(src[21], src[22], den, src[56], src[57])
                    group += stride
                    src_next = 0
                v = src_next
                src_next += 1
                if src_flag[3, v]:  # an exact fit: no LM
                    for it in range(lm_iterations):
                        hist[it] += src_lane[1, v]
                    n_fin = _push_result(
                        fin, n_fin, src_rowix[v], src_k[v], src_bsr, src_bsi,
                        v, src_lane[1, v], True, src_flag[2, v],
                    )
                    if n_fin == LANES:
                        _flush_results(
                            U, Y, fin, n_fin, weights, col_base, data_index, F,
                            n_centre, q_basis, pair_kind, pair_a, pair_b,
                            pair_nd, pair_off, ent_ptr, ent_mom, ent_coef,
                            ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef,
                            theta_out, cost_out, flags_out, cvar_out,
                        )
                        n_fin = 0
                    continue
                _load_lane(src, v, s, w, F)
                lane_it[w] = 0
                held[w] = True
        if not filled:  # lanes that never held a window copy one that does
            filled = True
            for w in range(1, LANES):
                if not held[w] and held[0]:
                    _load_lane(s, 0, s, w, F)
                    flag[0, w] = False
                    need[0, w] = False
        busy = False
        rebuild = False
        for w in range(LANES):
            busy = busy or flag[0, w]
            rebuild = rebuild or need[0, w]
        if not busy:
            break
        if rebuild:  # lanes without a new estimate get the model they had
            _lm_model(
                sr, si, hr, hi, rbr, rbi, ebr, ebi, Sar, Sai, Tr, Ti, Er, Ei,
                Or, Oi, mr, mi, Gtr, Gti, gr, gi, polyr, polyi, resr, resi, Wt,
                F, data_index, q_basis, pair_kind, pair_a, pair_b, pair_nd,
                pair_off, lay, ds, Hsr, Hsi, gsr, gsi,
            )
        _lm_step(Hsr, Hsi, gsr, gsi, ds, lm_lane[0], bsr, bsi, s_ptr, s_col,
                 s_val, Hr, Hi, gr, gi, scale2, ok, xr, xi)
        _compiled._residual(sr, si, xr, xi, weights, col_base, data_index, F,
                            polyr, polyi, resr, resi)
        _denominator(polyr, polyi, den, etr, eti)
        _oe_cost(resr, resi, etr, eti, lm_lane[2])
        for w in range(LANES):
            need[1, w] = False
            if not flag[0, w]:
                continue
            need[0, w] = False
            row = rowix[w]
            _lm_decide(
                w, row, p, tol, ok, xr, xi, bsr, bsi, str_, sti, lane, lm_lane,
                flag, need, band_int, system_factor, start_system, jump_limit,
                den_int, den_map, guard_radius, radius, work,
            )
            hist[lane_it[w]] += lane[1, w]
            lane_it[w] += 1
            if lane_it[w] == lm_iterations:
                flag[0, w] = False
        _keep_accepted(need[1], resr, resi, etr, eti, rbr, rbi, ebr, ebi)
    if n_fin > 0:
        _flush_results(
            U, Y, fin, n_fin, weights, col_base, data_index, F, n_centre,
            q_basis, pair_kind, pair_a, pair_b, pair_nd, pair_off, ent_ptr,
            ent_mom, ent_coef, ent_conj, ent_const, rhs_ptr, rhs_mom, rhs_coef,
            theta_out, cost_out, flags_out, cvar_out,
        )
    n_run_lm[task] = most


if AVAILABLE:  # pragma: no branch
    from numba import njit

    _opts = _compiled._opts
    _root_in_unit_disk = njit(**_opts)(_root_in_unit_disk_py)
    _sk_scratch = njit(**_opts)(_sk_scratch_py)
    _denominator = njit(**_opts)(_denominator_py)
    _weighted_gram = njit(**_opts)(_weighted_gram_py)
    _rejected = njit(**_opts)(_rejected_py)
    _hat_series = njit(**_opts)(_hat_series_py)
    _lm_model = njit(**_opts)(_lm_model_py)
    _lm_step = njit(**_opts)(_lm_step_py)
    _oe_cost = njit(**_opts)(_oe_cost_py)
    _keep_accepted = njit(**_opts)(_keep_accepted_py)
    _lm_decide = njit(**_opts)(_lm_decide_py)
    _lm_phase = njit(**_opts)(_lm_phase_py)
    _write_results = njit(**_opts)(_write_results_py)
    _finish_group = njit(**_opts)(_finish_group_py)
    _sk_part = njit(**_opts)(_sk_part_py)
    _sk_group = njit(**_opts)(_sk_group_py)
    _sk_range = njit(**_opts)(_sk_range_py)
    _lm_group = njit(**_opts)(_lm_group_py)
    _lm_range = njit(**_opts)(_lm_range_py)
    _load_lane = njit(**_opts)(_load_lane_py)
    _push_result = njit(**_opts)(_push_result_py)
    _flush_results = njit(**_opts)(_flush_results_py)
    _lm_refill_range = njit(**_opts)(_lm_refill_range_py)
    # these kernels inline _compiled's steps and LANES: numba's cache does not
    # see that file change (lrmfrf._jit_cache)
    key_caches_on(globals(), [_compiled.__file__])
else:  # pragma: no cover
    _root_in_unit_disk = _root_in_unit_disk_py


def sk_windows(
    U: np.ndarray,
    Y: np.ndarray,
    slow_bins: np.ndarray,
    theta0: np.ndarray,
    closed_rss: np.ndarray,
    start_system: np.ndarray,
    jump_limit: np.ndarray,
    radius: np.ndarray,
    *,
    weights: np.ndarray,
    col_base: np.ndarray,
    tables: dict,
    n_bands: int,
    n_centre: int,
    band_int: np.ndarray,
    den_int: np.ndarray,
    den_map: np.ndarray,
    system_factor: float,
    guard_radius: float,
    iterations: int,
    tol: float,
    keep_best: bool,
    exact_tol: float,
    lm_iterations: int = 0,
    from_layout: np.ndarray | None = None,
    layout_weights: np.ndarray | None = None,
    layout_col_base: np.ndarray | None = None,
    layout_tables: dict | None = None,
    n_threads: int | None = None,
    lm_stages: tuple | None = None,
    lm_refill: bool | None = None,
):
    """Sanathanan-Koerner iterations of every window (compiled, threaded).

    Parameters
    ----------
    U : ndarray of shape (P, n_u, N), complex
    Y : ndarray of shape (P, M), complex
    slow_bins : ndarray of shape (B,), int
    theta0 : ndarray of shape (B, p), complex
        Closed-form parameters, internal basis and order.
    closed_rss : ndarray of shape (B,)
        Closed-form weighted cost (the first SK cost).
    start_system : ndarray of shape (B, n_bands), complex
    jump_limit : ndarray of shape (B, n_bands)
    radius : ndarray of shape (B,)
        ``min(guard_radius, closest closed-form root)``; 0 disables the root
        test of a window.
    weights, col_base, tables
        Column weights, bases and ``moment_tables(..., weighted=True)``.
    n_bands, n_centre : int
    band_int : ndarray of shape (n_bands,), int
        Internal column of the window-centre value of each band.
    den_int : ndarray of shape (R_e,), int
        Internal denominator columns.
    den_map : ndarray of shape (R_e, R_e)
        Their map to monomial coefficients.
    system_factor : float
        ``F`` (the system is ``F`` times the centre value).
    guard_radius : float
    iterations : int
        SK iterations.
    tol : float
    keep_best : bool
    exact_tol : float
    lm_iterations : int, default=0
        Guarded LM iterations after SK (:func:`lrmfrf.refinement.
        _levenberg_marquardt`); ``centre_cov`` is then ``(J^H J)^-1``.
    from_layout : ndarray of shape (p, p), optional
        Real ``S`` with ``theta_internal = theta_layout @ S`` (LM damps in the
        layout basis); needed with ``lm_iterations``.
    layout_weights, layout_col_base, layout_tables : optional
        Column weights, bases and ``moment_tables(..., weighted=True)`` of the
        layout basis (``weights @ from_layout.T``): LM forms its ``J^H J`` in
        that basis from the moments. Default: those of the internal basis
        (right when ``from_layout`` is the identity).
    n_threads : int, optional
    lm_stages : tuple of int, optional
        LM iterations after which the windows still active are packed into
        new lane groups (default ``_LM_STAGES``; ``()``: never), when LM
        does not refill lanes. The results do not depend on it.
    lm_refill : bool, optional
        LM refills a lane as soon as its window stops (:func:`_lm_refill_range`)
        instead of packing at ``lm_stages`` (default ``_LM_REFILL``). The
        results do not depend on it (the sums of the LM costs to round-off:
        they are summed in another order).

    Returns
    -------
    theta : ndarray of shape (B, p), complex
        Internal basis and order.
    cost : ndarray of shape (B,)
        Output-error cost ``J_LS``.
    converged, guarded : ndarray of shape (B,), bool
    centre_cov : ndarray of shape (B, n_centre, n_centre), complex
        ``(A^H W A)^-1`` at the trailing internal columns, ``W`` from the
        final estimate.
    sk_sums, oe_sums : ndarray of shape (n_run + 1,)
        Sums over the windows of the SK cost and of ``J_LS`` per iteration.
    lm_sums : ndarray of shape (n_lm_run,)
        Sums of ``J_LS`` after each LM iteration run.
    """
    B, p = theta0.shape
    t = tables
    theta_out = np.empty((B, p, 2))
    cost = np.empty(B)
    flags = np.empty((B, 2), dtype=np.bool_)
    cvar = np.empty((B, n_centre, n_centre, 2))
    n_groups = (B + LANES - 1) // LANES
    history = np.zeros((n_groups, iterations + 1, 2))
    n_run = np.zeros(n_groups, dtype=np.int64)
    lm_history = np.zeros((n_groups, lm_iterations))
    n_run_lm = np.zeros(n_groups, dtype=np.int64)
    stages = sorted(
        {int(i) for i in (_LM_STAGES if lm_stages is None else lm_stages)
         if 0 < i < lm_iterations} | {int(lm_iterations)}
    )
    lm_state = np.empty((B, 3))
    lm_start = np.empty((B, p, 2))
    pend = np.zeros(B, dtype=np.bool_)
    as_ri = lambda z: np.ascontiguousarray(  # noqa: E731
        np.asarray(z, dtype=np.complex128)).view(np.float64).reshape(*z.shape, 2)
    args = (
        _compiled._as_interleaved(U), _compiled._as_interleaved(Y),
        np.ascontiguousarray(slow_bins, dtype=np.int64), as_ri(theta0),
        np.ascontiguousarray(closed_rss, dtype=np.float64), as_ri(start_system),
        np.ascontiguousarray(jump_limit, dtype=np.float64),
        np.ascontiguousarray(radius, dtype=np.float64),
        np.ascontiguousarray(weights, dtype=np.float64),
        np.ascontiguousarray(col_base, dtype=np.int64), t["data_index"],
        int(n_bands), int(n_centre), t["q_basis"], t["pair_kind"], t["pair_a"],
        t["pair_b"], t["pair_nd"], t["pair_off"], t["ent_ptr"], t["ent_mom"],
        t["ent_coef"], t["ent_conj"], t["ent_const"], t["rhs_ptr"],
        t["rhs_mom"], t["rhs_coef"], int(t["n_moments"]),
        np.ascontiguousarray(band_int, dtype=np.int64),
        np.ascontiguousarray(den_int, dtype=np.int64),
        np.ascontiguousarray(den_map, dtype=np.float64).reshape(
            len(den_int), len(den_int)
        ),
        float(system_factor), float(guard_radius), int(iterations),
        int(lm_iterations), float(tol), bool(keep_best), float(exact_tol),
        theta_out, cost, flags, cvar, history, n_run, lm_history, n_run_lm,
    )
    lay = _layout_tuple(
        weights if layout_weights is None else layout_weights,
        col_base if layout_col_base is None else layout_col_base,
        t if layout_tables is None else layout_tables,
        np.eye(p) if from_layout is None else from_layout,
    )
    n_threads = n_threads or _compiled.numba.config.NUMBA_NUM_THREADS
    if lm_iterations > 0 and (_LM_REFILL if lm_refill is None else lm_refill):
        return _refill_windows(args, lay, n_groups, n_threads, lm_iterations)
    _run_groups(
        lambda first, stop: _sk_range(
            *args, lay, stages[0], lm_state, lm_start, pend, first, stop
        ),
        n_groups, n_threads,
    )
    n = int(n_run.max(initial=0))
    sums = history[:, : n + 1].sum(axis=0)
    n_lm = int(n_run_lm.max(initial=0))
    lm_sums = lm_history.sum(axis=0)
    for begin, stop in zip(stages[:-1], stages[1:], strict=True):
        rows = np.flatnonzero(pend)
        if rows.size == 0:
            break
        groups = (rows.size + LANES - 1) // LANES
        stage_history = np.zeros((groups, lm_iterations))
        stage_run = np.zeros(groups, dtype=np.int64)
        stage_args = (
            args[0], args[1], args[2], rows, *args[5:8], *args[8:28],
            *args[28:33], int(lm_iterations), float(tol), theta_out, cost, flags,
            cvar, stage_history, stage_run, lay, begin, stop, lm_state, lm_start,
            pend,
        )
        _run_groups(
            lambda first, last, a=stage_args: _lm_range(*a, first, last),
            groups, n_threads,
        )
        lm_sums += stage_history.sum(axis=0)
        n_lm = max(n_lm, int(stage_run.max(initial=0)))
    return (
        theta_out.view(np.complex128)[..., 0], cost, flags[:, 0].copy(),
        flags[:, 1].copy(), cvar.view(np.complex128)[..., 0], sums[:, 0],
        sums[:, 1], lm_sums[:n_lm],
    )


def _refill_windows(args, lay, n_groups: int, n_threads: int, lm_iterations: int):
    """:func:`sk_windows` with LM lane refill (:func:`_lm_refill_range`): one
    task per thread, task ``t`` of ``T`` taking the lane groups ``t, t + T,
    ...`` (interleaved, so that the tasks get windows from every part of the
    band and about equal work; a task's LM group drains once, when its
    windows are exhausted)."""
    theta_out, cost, flags, cvar, history, n_run = args[-8:-2]
    n_tasks = max(1, min(n_threads * _REFILL_TASKS_PER_THREAD, n_groups))
    lm_history = np.zeros((n_tasks, lm_iterations))
    n_run_lm = np.zeros(n_tasks, dtype=np.int64)
    _run_tasks(
        lambda task: _lm_refill_range(
            *args[:-2], lm_history, n_run_lm, lay, task, task, n_groups, n_tasks,
        ),
        [(task,) for task in range(n_tasks)], n_threads,
    )
    sums = history[:, : int(n_run.max(initial=0)) + 1].sum(axis=0)
    lm_sums = lm_history.sum(axis=0)[: int(n_run_lm.max(initial=0))]
    return (
        theta_out.view(np.complex128)[..., 0], cost, flags[:, 0].copy(),
        flags[:, 1].copy(), cvar.view(np.complex128)[..., 0], sums[:, 0],
        sums[:, 1], lm_sums,
    )


def _run_groups(run, n_groups: int, n_threads: int) -> None:
    """``run(first, stop)`` over the lane groups in tasks of
    ``_GROUPS_PER_TASK``, on up to ``n_threads`` threads."""
    tasks = [
        (start, min(n_groups, start + _GROUPS_PER_TASK))
        for start in range(0, n_groups, _GROUPS_PER_TASK)
    ]
    if n_threads <= 1 or len(tasks) <= 1:
        run(0, n_groups)
    else:
        _run_tasks(run, tasks, n_threads)


def _run_tasks(run, tasks: list, n_threads: int) -> None:
    """``run(task)`` for every task, on up to ``n_threads`` threads."""
    if min(n_threads, len(tasks)) <= 1:
        for task in tasks:
            run(*task)
    else:  # the pool of n_threads (lrmfrf._compiled.thread_pool)
        list(_compiled.thread_pool(n_threads).map(lambda task: run(*task), tasks))


def _layout_tuple(weights, col_base, tables, from_layout):
    """What LM needs of the layout basis, as one argument of the kernel:
    column weights and bases, the Gram and right-hand-side tables, and the
    sparse rows of ``from_layout``."""
    t = tables
    return (
        np.ascontiguousarray(weights, dtype=np.float64),
        np.ascontiguousarray(col_base, dtype=np.int64), t["ent_ptr"],
        t["ent_mom"], t["ent_coef"], t["ent_conj"], t["ent_const"],
        t["rhs_ptr"], t["rhs_mom"], t["rhs_coef"], *_sparse_rows(from_layout),
    )


def _sparse_rows(matrix: np.ndarray):
    """Row pointers, columns and values of the nonzeros of a real matrix."""
    rows, cols = np.nonzero(matrix)
    ptr = np.searchsorted(rows, np.arange(matrix.shape[0] + 1))
    return (
        ptr.astype(np.int64), cols.astype(np.int64),
        np.ascontiguousarray(matrix[rows, cols], dtype=np.float64),
    )
