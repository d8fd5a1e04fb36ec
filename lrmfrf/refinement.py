"""Iterative refinement of the local rational models (SK and guarded LM).

The closed form eq. (linearSolution) minimises the *weighted* cost
eq. (LinearCostFunction): the output error of each window multiplied by the
common denominator ``e(x)``. This module refines it, for all slow bins at
once, toward the original least-squares cost eq. (CostFunction),

.. math::

    J_{LS}(\\theta) = \\sum_r |Y_l(k+r) - \\hat Y_l(k+r, \\theta)|^2,
    \\qquad \\hat Y_l = \\frac{\\theta_{num} K_{num}(x)}{e(x)},
    \\qquad e(x) = 1 + \\sum_{s=1}^{R_e} e_s x^s,

with ``x = r/n`` the scaled window offset (see :mod:`lrmfrf.windows`). The
output-error residual is the linear residual divided by ``e(x)``:
``Y_l - \\hat Y_l = (b - A \\theta) / e``, with ``A, b`` from
:func:`lrmfrf.windows.local_regressor`.

Two methods of the paper's section "Iterative Reweighted Solutions":

- **Sanathanan-Koerner** (eq. LinearizedCostFunctionSK): re-solve the linear
  problem with the rows of ``A`` and ``b`` divided by ``e_prev(x)`` of the
  previous iterate, starting from the closed form.
- **Levenberg-Marquardt** on ``J_LS`` itself, starting from the SK (or
  closed-form) result. The residual is holomorphic in the complex parameters,
  so the Gauss-Newton model uses the complex Jacobian ``J = d res / d theta =
  -Ahat / e`` (``Ahat`` is ``A`` with ``Y_l`` replaced by ``Yhat`` in the
  denominator columns) and the normal matrix ``J^H J``, with Marquardt's
  diagonal damping.

Both loop over iterations and chunks of windows only; every window of a chunk
is updated in array operations, and windows that have converged drop out of
the active set.

**Guard.** A local model whose denominator has a root close to the window
centre can interpolate the noise of the centre bin (only ``q`` spare
equations), which blows that bin up by orders of magnitude (``docs/method.md``).
An iterate of a window is rejected when ``e(x)`` gets a root within
``guard / n`` of ``x = 0`` (``guard`` in slow bins) closer than the closest
root of the closed-form model, or when its FRF at the centre moves away from
the closed-form estimate by more than ``jump`` closed-form standard
deviations (a "jump": refinement is a correction within the noise, not a
move to another model). A rejected SK iterate stops the window at its best
estimate so far; a rejected LM step returns the window to the estimate LM
started from (the SK or closed-form result) and stops it. Windows where the
guard acted are counted.
"""

from __future__ import annotations

import functools
import os
import sys
import warnings
from dataclasses import dataclass, replace

import numpy as np
from sklearn.exceptions import ConvergenceWarning

from . import _compiled, _compiled_refine
from .local_models import (
    LocalModelFit,
    normalise_spectra,
    rescale_local_fit,
    scale_by_power_of_two,
)
from .progress import progress
from .solvers import (
    _compiled_tables,
    lemma2_variance,
    noise_variance,
    qr_chunk_size,
    resolve_backend,
    solve_local_least_squares,
)
from .windows import (
    LocalModelLayout,
    StructuredWindows,
    local_regressor,
    window_offsets,
)

__all__ = [
    "RefinementGuardWarning",
    "RefinementResult",
    "refine_local_models",
    "emit_refinement_warnings",
    "denominator_values",
    "denominator_roots",
    "output_error_cost",
]

#: Initial Marquardt damping (relative to the unit diagonal of the
#: equilibrated normal matrix).
LM_INITIAL_DAMPING = 1e-3

#: Damping above which a window whose steps keep failing is declared stuck.
LM_MAX_DAMPING = 1e12

#: A window whose cost is below this fraction of ``sum |Y_l|^2`` of the window
#: is fitted exactly (noise-free in-class data): nothing left to refine.
EXACT_FIT_TOL = 1e-26


@dataclass
class RefinementResult:
    """Refined local models and the history of the refinement.

    Attributes
    ----------
    local_fit : LocalModelFit
        The refined models: ``theta``, ``system``, ``system_var`` (linearised
        at the final estimate), ``transient``, ``noise_var`` (``J_LS / q``) and
        ``rss`` (``J_LS``) updated.
    cost_history : ndarray of shape (1 + sk_iterations + lm_iterations,)
        Mean over the well-posed windows of the original cost ``J_LS``
        (eq. meanCosts, ``mu_OE``) after the closed form and after each SK,
        then each LM iteration actually run.
    sk_cost_history : ndarray of shape (1 + sk_iterations,)
        Mean SK cost ``mu_SK``: the closed form's weighted cost ``J_W``, then
        the reweighted cost ``J_SK`` minimised by each SK iteration.
    sk_iterations, lm_iterations : int
        Iterations run (at most the requested counts; fewer on convergence).
    guarded : ndarray of shape (B,), bool
        Windows where the guard rejected an iterate.
    converged : ndarray of shape (B,), bool
        Windows whose last stage stopped on its tolerance (or fitted exactly)
        rather than on the iteration count.
    stopped_far : tuple of (bool, bool)
        Whether SK, LM used all their iterations far from convergence.
    """

    local_fit: LocalModelFit
    cost_history: np.ndarray
    sk_cost_history: np.ndarray
    sk_iterations: int
    lm_iterations: int
    guarded: np.ndarray
    converged: np.ndarray
    stopped_far: tuple[bool, bool] = (False, False)

    @property
    def n_guarded(self) -> int:
        """Number of windows where the guard acted."""
        return int(np.count_nonzero(self.guarded))


def denominator_values(theta: np.ndarray, layout: LocalModelLayout) -> np.ndarray:
    """Common denominator ``e(x)`` of eq. (CommonDenominator) on every row.

    Parameters
    ----------
    theta : ndarray of shape (B, n_params), complex
    layout : LocalModelLayout

    Returns
    -------
    ndarray of shape (B, P*(2n+1)), complex
        ``1 + sum_s e_s x^s`` at the scaled offsets ``x = r/n`` of each row
        of :func:`lrmfrf.windows.local_regressor` (rows repeat per experiment).
    """
    powers = _den_powers(layout)
    return 1.0 + theta[:, layout.den_columns] @ powers.T


def denominator_roots(theta: np.ndarray, layout: LocalModelLayout) -> np.ndarray:
    """Smallest modulus of the roots of ``e(x)`` for each window.

    The roots are those of ``1 + e_1 x + ... + e_Re x^Re`` in the scaled
    offset ``x = r/n`` (complex coefficients), found as the reciprocals of
    the eigenvalues of the companion matrix of the reversed, monic polynomial
    ``z^Re + e_1 z^(Re-1) + ... + e_Re`` (robust when ``e_Re`` vanishes).

    Parameters
    ----------
    theta : ndarray of shape (B, n_params), complex
    layout : LocalModelLayout

    Returns
    -------
    ndarray of shape (B,), float
        ``min |x_root|``; ``inf`` without denominator (``R_e = 0``) and NaN
        where ``theta`` is not finite.
    """
    Re = layout.den_degree
    B = theta.shape[0]
    if Re == 0:
        return np.full(B, np.inf)
    coef = theta[:, layout.den_columns]
    finite = np.isfinite(coef).all(axis=1)
    companion = np.zeros((B, Re, Re), dtype=complex)
    companion[:, 0, :] = -np.where(finite[:, None], coef, 0.0)
    if Re > 1:
        companion[:, np.arange(1, Re), np.arange(Re - 1)] = 1.0
    z = np.linalg.eigvals(companion)
    largest = np.abs(z).max(axis=1)
    with np.errstate(divide="ignore"):
        closest = 1.0 / largest
    closest[~finite] = np.nan
    return closest


def output_error_cost(
    A: np.ndarray, b: np.ndarray, theta: np.ndarray, layout: LocalModelLayout
) -> np.ndarray:
    """Original least-squares cost eq. (CostFunction) of each window.

    Parameters
    ----------
    A : ndarray of shape (B, P*(2n+1), n_params)
    b : ndarray of shape (B, P*(2n+1))
        Regressor and data of :func:`lrmfrf.windows.local_regressor`.
    theta : ndarray of shape (B, n_params)
    layout : LocalModelLayout

    Returns
    -------
    ndarray of shape (B,)
        ``sum_r |Y_l(k+r) - Yhat(k+r)|^2`` (``inf`` where ``e`` vanishes).
    """
    residual = _output_error_residual(A, b, theta, layout)
    return np.sum(np.abs(residual) ** 2, axis=1)


def refine_local_models(
    U: np.ndarray,
    Y: np.ndarray,
    layout: LocalModelLayout,
    local_fit: LocalModelFit,
    *,
    sk_iterations: int = 0,
    lm_iterations: int = 0,
    tol: float = 1e-6,
    guard: float | None = 0.5,
    jump: float | None = 5.0,
    keep_best: bool = True,
    chunk_size: int | None = None,
    verbose: bool = False,
    backend: str = "auto",
    warn: bool = True,
) -> RefinementResult:
    """Refine closed-form local models with SK, then guarded LM iterations.

    Parameters
    ----------
    U : ndarray of shape (P, N), complex
        Unnormalised DFT of the fast inputs.
    Y : ndarray of shape (P, M), complex
        Unnormalised DFT of the slow outputs.
    layout : LocalModelLayout
    local_fit : LocalModelFit
        Closed-form result of :func:`lrmfrf.local_models.fit_local_models` on
        the same data (its ``slow_bins`` are refined).
    sk_iterations : int, default=0
        Maximum number of Sanathanan-Koerner iterations.
    lm_iterations : int, default=0
        Maximum number of Levenberg-Marquardt iterations (one damped
        Gauss-Newton solve each, accepted or not).
    tol : float, default=1e-6
        A window stops iterating when the relative change of its cost
        ``J_LS`` (SK) or the relative decrease of ``J_LS`` of an accepted step
        (LM) falls below ``tol``.
    guard : float or None, default=0.5
        Guard radius in slow bins: an iterate whose ``e(x)`` has a root within
        ``guard / n`` of the window centre (and closer than the closed form's
        closest root) is rejected. ``None`` or 0 disables it.
    jump : float or None, default=5.0
        An iterate whose FRF at the window centre moves away from the
        closed-form estimate by more than ``jump`` closed-form (Lemma 2)
        standard deviations in some band is rejected. ``None`` disables it.
    keep_best : bool, default=True
        Per window, keep the SK iterate with the lowest ``J_LS`` (SK is not a
        descent method for ``J_LS`` and can cycle, see Notes). With False, the
        last SK iterate is kept.
    chunk_size : int, optional
        Windows refined at once; default bounds a chunk's regressor to
        :data:`lrmfrf.solvers.CHUNK_BYTES` (64 MiB), as
        :func:`lrmfrf.local_models.fit_local_models`.
    verbose : bool, default=False
        Show a progress bar over the chunks (long records; needs tqdm).
    backend : {"auto", "numpy", "numba"}, default="auto"
        ``"numba"``: SK in the compiled kernel (:mod:`lrmfrf._compiled_refine`,
        the window moments reweighted per iteration, no regressor formed);
        ``"numpy"``: array operations on the regressors of chunks of windows.
        ``"auto"`` chooses as :func:`lrmfrf.solvers.resolve_backend` (SK and
        LM alike; the compiled LM builds ``J^H J`` from the moments too, in the
        layout basis where it damps, with the denominator pair series from
        ``yhat``). Both give
        the same results up to round-off, except on windows where a guard
        decision sits on its threshold.
    warn : bool, default=True
        Emit the warnings below. ``False`` leaves them to the caller, e.g.
        :func:`emit_refinement_warnings` once for the refinements of all the
        output rows of a MIMO fit.

    Returns
    -------
    RefinementResult

    Warns
    -----
    sklearn.exceptions.ConvergenceWarning
        When a stage uses all its iterations while its mean cost still drops
        by more than ``max(tol, 1e-3)`` (relative) per iteration.
    RefinementGuardWarning
        When the guard rejected iterates in some windows.

    Notes
    -----
    SK minimises, per iteration, the cost reweighted by the previous
    denominator; it is a fixed-point iteration, not a descent method for
    ``J_LS``. On windows where ``e(x)`` has a root close to the frequency axis
    between two window points, ``1 / e_prev`` concentrates the weight on one
    row and the iteration can cycle (period two) with ``J_LS`` alternating;
    ``keep_best`` returns the best iterate of each window, which makes the
    mean cost history non-increasing.

    LM minimises ``J_LS`` directly. With only ``q`` spare equations per
    window it can move a root of ``e(x)`` onto the window centre and fit the
    centre bin's noise; the guard (``guard``, ``jump``) rejects such steps
    and returns the window to the estimate LM started from.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.signal import lfilter
    >>> from lrmfrf.local_models import fit_local_models
    >>> from lrmfrf.refinement import refine_local_models
    >>> from lrmfrf.signals import multisine
    >>> from lrmfrf.windows import LocalModelLayout
    >>> rng = np.random.default_rng(0)
    >>> u = multisine(1200, rng=rng)
    >>> y = lfilter([0.2, 0.1], [1.0, -0.5], u)[::3]
    >>> y = y + 1e-3 * rng.standard_normal(y.size)
    >>> layout = LocalModelLayout(F=3, half_window=18, num_degree=4,
    ...                           transient_degree=4, den_degree=2)
    >>> U, Y = np.fft.fft(u)[None], np.fft.fft(y)[None]
    >>> closed = fit_local_models(U, Y, layout)
    >>> result = refine_local_models(U, Y, layout, closed, sk_iterations=40)
    >>> bool(result.cost_history[-1] <= result.cost_history[0])
    True
    """
    # any finite scale gives the same result (exact; nothing for ordinary data)
    U, Y, u_exponent, y_exponent = normalise_spectra(U, Y)
    local_fit = rescale_local_fit(local_fit, -u_exponent, -y_exponent)
    result = _refine(
        U,
        Y,
        layout,
        local_fit,
        sk_iterations=sk_iterations,
        lm_iterations=lm_iterations,
        tol=tol,
        guard=guard,
        jump=jump,
        keep_best=keep_best,
        chunk_size=chunk_size,
        verbose=verbose,
        backend=backend,
    )
    if u_exponent or y_exponent:
        result = replace(
            result,
            local_fit=rescale_local_fit(result.local_fit, u_exponent, y_exponent),
            cost_history=scale_by_power_of_two(result.cost_history, 2 * y_exponent),
            sk_cost_history=scale_by_power_of_two(
                result.sk_cost_history, 2 * y_exponent
            ),
        )
    if warn:
        emit_refinement_warnings([result])
    return result


class RefinementGuardWarning(UserWarning):
    """The refinement guard rejected degenerate iterates in some windows."""


# --------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------

#: A stage that ends on its iteration count while its mean cost still drops
#: by more than this (relative) per iteration is "far from convergence".
FAR_FROM_CONVERGENCE = 1e-3


def _refine(
    U, Y, layout, local_fit, *, sk_iterations, lm_iterations, tol, guard, jump,
    keep_best, chunk_size, verbose=False, backend="auto",
) -> RefinementResult:
    """Kernel of :func:`refine_local_models` (no warnings)."""
    nb = layout.n_bands
    slow_bins = np.asarray(local_fit.slow_bins, dtype=int)
    B = slow_bins.size
    if chunk_size is None:
        chunk_size = qr_chunk_size(layout)
    guard_radius = 0.0 if not guard else float(guard) / max(layout.half_window, 1)
    jump_limit = np.full((B, nb), np.inf)
    if jump is not None:
        jump_limit = jump * np.nan_to_num(np.sqrt(local_fit.system_var), nan=np.inf)
    n_ok = int(np.count_nonzero(local_fit.well_posed))
    work = n_ok * max(sk_iterations + lm_iterations, 1)
    backend = resolve_backend(backend, work, layout.n_params)
    if backend == "numba" and (sk_iterations or lm_iterations):
        return _refine_compiled(
            U, Y, layout, local_fit, sk_iterations=sk_iterations,
            lm_iterations=lm_iterations, tol=tol, guard_radius=guard_radius,
            jump_limit=jump_limit, keep_best=keep_best,
        )

    theta = local_fit.theta.copy()
    gram = np.full((B, layout.n_params), np.nan)
    lead = np.full((B, nb, nb), np.nan, dtype=complex)
    cost = np.full(B, np.nan)
    guarded = np.zeros(B, dtype=bool)
    converged = np.zeros(B, dtype=bool)
    oe_sk, oe_lm, weighted_sk = [], [], []
    starts = range(0, B, chunk_size)
    for start in progress(starts, enabled=verbose, desc="refinement (chunks)"):
        sl = slice(start, start + chunk_size)
        ok = local_fit.well_posed[sl]
        if not ok.any():
            continue
        A, b = local_regressor(U, Y, slow_bins[sl][ok], layout)
        state = _ChunkState(
            A=A,
            b=b,
            layout=layout,
            theta=local_fit.theta[sl][ok].copy(),
            start_system=local_fit.system[sl][ok],
            jump_limit=jump_limit[sl][ok],
            guard_radius=guard_radius,
            tol=tol,
        )
        wsk, sk = _sanathanan_koerner(
            state, sk_iterations, local_fit.rss[sl][ok], keep_best
        )
        oe_sk.append(sk)
        weighted_sk.append(wsk)
        oe_lm.append(_levenberg_marquardt(state, lm_iterations))
        idx = np.flatnonzero(ok) + start
        theta[idx] = state.theta
        cost[idx] = state.cost
        guarded[idx] = state.guarded
        converged[idx] = state.converged
        if sk_iterations or lm_iterations:
            gram[idx], lead[idx] = _final_gram_inv_diag(
                state, use_lm=lm_iterations > 0
            )

    n_ok = max(int(np.count_nonzero(local_fit.well_posed)), 1)
    n_sk = max((s.size for s in oe_sk), default=1) - 1
    n_lm = max((s.size for s in oe_lm), default=0)
    sk_history = _pad_sum(oe_sk, n_sk + 1) / n_ok
    lm_history = _pad_sum(oe_lm, n_lm) / n_ok
    cost_history = np.concatenate([sk_history, lm_history])
    far_sk = n_sk == sk_iterations and _still_dropping(sk_history, tol)
    far_lm = n_lm == lm_iterations and _still_dropping(cost_history[n_sk:], tol)

    if sk_iterations or lm_iterations:
        refined = _refined_fit(local_fit, layout, theta, cost, gram, lead)
    else:
        refined = local_fit
    return RefinementResult(
        local_fit=refined,
        cost_history=cost_history,
        sk_cost_history=_pad_sum(weighted_sk, n_sk + 1) / n_ok,
        sk_iterations=n_sk,
        lm_iterations=n_lm,
        guarded=guarded,
        converged=converged,
        stopped_far=(far_sk, far_lm),
    )


def _still_dropping(history, tol) -> bool:
    if history.size < 2 or not history[-2] > 0:
        return False
    drop = (history[-2] - history[-1]) / history[-2]
    return bool(drop > max(tol, FAR_FROM_CONVERGENCE))


def _caller_stacklevel() -> int:
    """``stacklevel`` of the first frame outside the package, as seen from the
    function that calls ``warnings.warn`` (so that a warning points at user
    code whether it came through an estimator's ``fit`` or
    :func:`refine_local_models`)."""
    package = os.path.dirname(os.path.abspath(__file__)) + os.sep
    frame = sys._getframe(1)  # the caller of this function: level 1
    level = 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(
        package
    ):
        frame = frame.f_back
        level += 1
    return level


def emit_refinement_warnings(results: list[RefinementResult]) -> None:
    """Warn once for the refinements of one fit, at the first caller outside
    the package.

    ``results`` holds one refinement per output row (one for SISO). Each kind
    of warning is emitted at most once, naming the rows it concerns when
    there are several, e.g. ``in 601 of 602 windows (output row 0: 301 of
    301, row 1: 300 of 301)``.

    Warns
    -----
    sklearn.exceptions.ConvergenceWarning
        When a stage of some row used all its iterations far from convergence.
    RefinementGuardWarning
        When the guard rejected iterates in some windows.
    """
    stacklevel = _caller_stacklevel()
    several = len(results) > 1
    names = (
        ("Sanathanan-Koerner", "sk_iterations"),
        ("Levenberg-Marquardt", "lm_iterations"),
    )
    for stage, (method, parameter) in enumerate(names):
        rows = [o for o, r in enumerate(results) if r.stopped_far[stage]]
        if not rows:
            continue
        count = max((r.sk_iterations, r.lm_iterations)[stage]
                    for r in (results[o] for o in rows))
        where = (f" (output row{'s' if len(rows) > 1 else ''} "
                 f"{', '.join(map(str, rows))})" if several else "")
        warnings.warn(
            f"{method} used all {count} iterations while the mean cost was "
            f"still dropping by more than {FAR_FROM_CONVERGENCE:.0e} per "
            f"iteration{where}. Increase `{parameter}` for a converged estimate.",
            ConvergenceWarning,
            stacklevel=stacklevel,
        )
    n_guarded = sum(r.n_guarded for r in results)
    if n_guarded:
        total = sum(r.guarded.size for r in results)
        where = ""
        if several:
            where = " (" + ", ".join(
                f"{'output row' if o == 0 else 'row'} {o}: "
                f"{r.n_guarded} of {r.guarded.size}"
                for o, r in enumerate(results)) + ")"
        warnings.warn(
            f"The refinement guard rejected degenerate iterates (a denominator "
            f"root near the window centre, or an FRF jump) in "
            f"{n_guarded} of {total} windows{where}; they keep "
            "their last good estimate. See `n_guarded_` / `guarded`.",
            RefinementGuardWarning,
            stacklevel=stacklevel,
        )


@dataclass
class _ChunkState:
    """Current estimate of a chunk of well-posed windows."""

    A: np.ndarray
    b: np.ndarray
    layout: LocalModelLayout
    theta: np.ndarray
    start_system: np.ndarray
    jump_limit: np.ndarray
    guard_radius: float
    tol: float
    cost: np.ndarray = None
    start_root: np.ndarray = None
    guarded: np.ndarray = None
    converged: np.ndarray = None
    exact: np.ndarray = None

    def __post_init__(self):
        self.cost = output_error_cost(self.A, self.b, self.theta, self.layout)
        self.start_root = denominator_roots(self.theta, self.layout)
        self.guarded = np.zeros(self.theta.shape[0], dtype=bool)
        self.converged = np.zeros(self.theta.shape[0], dtype=bool)
        scale = np.sum(np.abs(self.b) ** 2, axis=1)
        self.exact = self.cost <= EXACT_FIT_TOL * scale

    def rejected(self, idx: np.ndarray, trial: np.ndarray) -> np.ndarray:
        """Guard of the module docstring for the windows ``idx``."""
        F, nb = self.layout.F, self.layout.n_bands
        bad = ~np.isfinite(trial).all(axis=1)
        if self.guard_radius > 0:
            coef = np.abs(trial[:, self.layout.den_columns])
            powers = self.guard_radius ** np.arange(1, self.layout.den_degree + 1)
            # Rouche: sum_s |e_s| rho^s < 1 leaves no root in |x| <= rho.
            check = np.flatnonzero(~bad & ~(coef @ powers < 1.0))
            root = denominator_roots(trial[check], self.layout)
            near = (root < self.guard_radius) & (root < self.start_root[idx[check]])
            bad[check] |= near | np.isnan(root)
        move = np.abs(F * trial[:, :nb] - self.start_system[idx])
        bad |= (move > self.jump_limit[idx]).any(axis=1)
        return bad


def _den_powers(layout: LocalModelLayout) -> np.ndarray:
    """``x^s``, ``s = 1..R_e``, on each row (P*(2n+1), R_e)."""
    _, x = window_offsets(layout.half_window)
    x_rows = np.tile(x, layout.n_experiments)
    return x_rows[:, None] ** np.arange(1, layout.den_degree + 1)


def _linear_residual(A, b, theta):
    return b - (A @ theta[:, :, None])[:, :, 0]


def _output_error_residual(A, b, theta, layout):
    e = denominator_values(theta, layout)
    with np.errstate(divide="ignore", invalid="ignore"):
        residual = _linear_residual(A, b, theta) / e
    return np.where(np.isfinite(residual), residual, np.inf)


def _sanathanan_koerner(state: _ChunkState, iterations: int, closed_rss, keep_best):
    """Run SK on a chunk in place; return the per-iteration cost sums."""
    layout = state.layout
    theta = state.theta.copy()  # the SK trajectory
    e_prev = denominator_values(theta, layout)
    traj_cost = state.cost.copy()
    active = ~state.exact
    state.converged = state.exact.copy()
    sk_cost = closed_rss.copy()
    sk_sums = [float(np.sum(sk_cost))]
    oe_sums = [float(np.sum(state.cost))]
    A_adjoint = np.ascontiguousarray(state.A.conj().transpose(0, 2, 1))
    for _ in range(iterations):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        A, b = _take(state.A, idx), _take(state.b, idx)
        w = 1.0 / e_prev[idx]
        trial, rss, solved = _weighted_solve(A, _take(A_adjoint, idx), b, w)
        trial_cost = output_error_cost(A, b, trial, layout)
        failed = ~solved | ~np.isfinite(trial_cost)
        rejected = ~failed & state.rejected(idx, trial)
        bad = failed | rejected
        good = idx[~bad]
        with np.errstate(divide="ignore", invalid="ignore"):
            change = np.abs(trial_cost[~bad] - traj_cost[good]) / traj_cost[good]
        theta[good] = trial[~bad]
        traj_cost[good] = trial_cost[~bad]
        e_prev[good] = denominator_values(trial[~bad], layout)
        better = traj_cost[good] < state.cost[good] if keep_best else slice(None)
        state.theta[good[better]] = theta[good[better]]
        state.cost[good[better]] = traj_cost[good[better]]
        state.guarded[idx[rejected]] = True
        active[idx[bad]] = False
        done = good[change < state.tol]
        active[done] = False
        state.converged[done] = True
        sk_cost[good] = rss[~bad]
        sk_sums.append(float(np.sum(sk_cost)))
        oe_sums.append(float(np.sum(state.cost)))
    return np.array(sk_sums), np.array(oe_sums)


def _take(array, idx):
    """``array[idx]`` without a copy when ``idx`` is every window."""
    return array if idx.size == array.shape[0] else array[idx]


def _weighted_solve(A, A_adjoint, b, w):
    """SK step: ``argmin ||w (b - A theta)||`` for well-posed windows, fast.

    Equilibrated normal equations with one step of iterative refinement on
    the explicit residual (semi-normal equations): the reweighted problem
    has the rank of the closed-form one (the weights are finite and
    nonzero), so no rank test is needed, and refinement recovers the digits
    lost to squaring the condition number (about 4e5 after equilibration).
    The weights enter the normal equations directly (``A^H |w|^2 A``), and
    the column norms of ``w A`` are the square roots of its diagonal.
    Windows whose normal matrix cannot be factorised are solved by QR
    (:func:`lrmfrf.solvers.solve_local_least_squares`).

    Parameters
    ----------
    A : ndarray of shape (B, n_equations, n_params)
    A_adjoint : ndarray of shape (B, n_params, n_equations)
        ``conj(A)`` transposed (the same for every iteration).
    b : ndarray of shape (B, n_equations)
    w : ndarray of shape (B, n_equations)
        Row weights ``1 / e_prev(r)``.

    Returns
    -------
    theta : ndarray of shape (B, n_params)
    rss : ndarray of shape (B,)
        Weighted residual sum of squares.
    solved : ndarray of shape (B,), bool
    """
    weighted_adjoint = A_adjoint * (w.real**2 + w.imag**2)[:, None, :]
    gram = weighted_adjoint @ A
    scale = np.sqrt(np.abs(np.diagonal(gram, axis1=1, axis2=2).real))
    scale = np.where(scale > 0, scale, 1.0)[:, :, None]
    gram /= scale
    gram /= scale.transpose(0, 2, 1)
    try:
        z = np.linalg.solve(gram, (weighted_adjoint @ b[:, :, None]) / scale)
        residual = b[:, :, None] - A @ (z / scale)
        z += np.linalg.solve(gram, (weighted_adjoint @ residual) / scale)
    except np.linalg.LinAlgError:
        sol = solve_local_least_squares(A * w[:, :, None], b * w)
        return sol.theta, sol.rss, sol.well_posed
    theta = (z / scale)[:, :, 0]
    residual = w * (b - (A @ theta[:, :, None])[:, :, 0])
    rss = np.sum(residual.real**2 + residual.imag**2, axis=1)
    return theta, rss, np.isfinite(theta).all(axis=1)


def _levenberg_marquardt(state: _ChunkState, iterations: int):
    """Run guarded LM on a chunk in place; return the per-iteration cost sums."""
    layout = state.layout
    n_win, p = state.theta.shape
    active = ~state.exact
    if iterations:
        state.converged = state.exact.copy()
    lam = np.full(n_win, LM_INITIAL_DAMPING)
    H = np.zeros((n_win, p, p), dtype=complex)
    g = np.zeros((n_win, p), dtype=complex)
    scale = np.ones((n_win, p))
    oe_sums = []
    need = np.flatnonzero(active) if iterations else np.array([], dtype=int)
    start_theta = state.theta.copy()
    start_cost = state.cost.copy()
    for _ in range(iterations):
        if need.size:
            H[need], g[need], scale[need] = _gauss_newton(
                state.A[need], state.b[need], state.theta[need], layout
            )
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        damped = H[idx] + lam[idx, None, None] * np.eye(p)
        try:
            step = np.linalg.solve(damped, -g[idx][..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = _safe_solve(damped, -g[idx])
        trial = state.theta[idx] + step / scale[idx]
        trial_cost = output_error_cost(state.A[idx], state.b[idx], trial, layout)
        decrease = np.isfinite(trial_cost) & (trial_cost < state.cost[idx])
        guard_hit = decrease & state.rejected(idx, trial)
        accept = decrease & ~guard_hit
        state.guarded[idx[guard_hit]] = True
        # Fall back to the estimate LM started from and stop the window.
        hit = idx[guard_hit]
        active[hit] = False
        state.theta[hit] = start_theta[hit]
        state.cost[hit] = start_cost[hit]
        good = idx[accept]
        change = (state.cost[good] - trial_cost[accept]) / state.cost[good]
        state.theta[good] = trial[accept]
        state.cost[good] = trial_cost[accept]
        lam[good] = np.maximum(lam[good] / 10.0, 1e-12)
        lam[idx[~accept]] *= 10.0
        done = good[change < state.tol]
        stuck = idx[~accept][lam[idx[~accept]] > LM_MAX_DAMPING]
        active[done] = False
        active[stuck] = False
        state.converged[done] = True
        state.converged[stuck] = True
        need = good[change >= state.tol]
        oe_sums.append(float(np.sum(state.cost)))
    return np.array(oe_sums)


def _gauss_newton(A, b, theta, layout):
    """Equilibrated ``J^H J``, ``J^H res`` and the column scale at ``theta``."""
    J, residual = _jacobian(A, b, theta, layout)
    J_H = J.conj().transpose(0, 2, 1)
    H = J_H @ J
    g = (J_H @ residual[:, :, None])[:, :, 0]
    d = np.sqrt(np.maximum(np.real(np.diagonal(H, axis1=1, axis2=2)), 0.0))
    d = np.where(d > 0, d, 1.0)
    H = H / (d[:, :, None] * d[:, None, :])
    return H, g / d, d


def _jacobian(A, b, theta, layout):
    """Output-error residual and its complex Jacobian ``-Ahat / e``."""
    e = denominator_values(theta, layout)
    residual = _linear_residual(A, b, theta) / e
    y_hat = b - residual
    A_hat = A.copy()
    A_hat[:, :, layout.den_columns] = -y_hat[:, :, None] * _den_powers(layout)
    return -A_hat / e[:, :, None], residual


def _safe_solve(matrix, rhs):
    out = np.zeros_like(rhs)
    for i in range(matrix.shape[0]):  # only on a singular batch (rare)
        out[i] = np.linalg.lstsq(matrix[i], rhs[i], rcond=None)[0]
    return out


def _final_gram_inv_diag(state: _ChunkState, *, use_lm: bool) -> np.ndarray:
    """Diagonal of the inverse normal matrix linearised at the final estimate.

    SK: Lemma 2 on the reweighted regressor ``A / e``. LM: ``(J^H J)^-1``.
    Also returns the block at the leading ``n_bands`` (system) columns.
    """
    nb = state.layout.n_bands
    if use_lm:
        J, residual = _jacobian(state.A, state.b, state.theta, state.layout)
        sol = solve_local_least_squares(J, residual, cov_columns=nb)
    else:
        e = denominator_values(state.theta, state.layout)
        sol = solve_local_least_squares(
            state.A / e[:, :, None], state.b / e, cov_columns=nb
        )
    return sol.gram_inv_diag, sol.lead_cov


def _refined_fit(local_fit, layout, theta, cost, gram, lead) -> LocalModelFit:
    F, nb = layout.F, layout.n_bands
    noise_var = noise_variance(cost, layout.dof)
    system = F * theta[:, :nb]
    system_var = lemma2_variance(gram[:, :nb], noise_var, F)
    system_cov = F**2 * lead * noise_var[:, None, None]
    cols = [layout.transient_column(p) for p in range(layout.n_experiments)]
    transient = theta[:, cols]
    bad = ~local_fit.well_posed
    for arr in (theta, system, system_var, system_cov, transient, noise_var, cost):
        arr[bad] = np.nan
    return replace(
        local_fit,
        theta=theta,
        system=system,
        system_var=system_var,
        system_cov=system_cov,
        transient=transient,
        noise_var=noise_var,
        rss=cost,
        leverage=None,
    )


def _refine_compiled(
    U, Y, layout, local_fit, *, sk_iterations, lm_iterations, tol, guard_radius,
    jump_limit, keep_best,
) -> RefinementResult:
    """SK and LM through the compiled kernel (:func:`lrmfrf._compiled_refine.
    sk_windows`); the same results as the numpy path of :func:`_refine`."""
    nb, P = layout.n_bands, layout.n_experiments
    ok = np.flatnonzero(local_fit.well_posed)
    B = local_fit.slow_bins.size
    n_ok = max(ok.size, 1)
    sk = _sk_layout(layout)
    theta0 = _real_map(local_fit.theta[ok], sk["from_layout"])
    start_root = np.full(ok.size, np.inf)
    if guard_radius > 0 and layout.den_degree:
        coef = np.abs(local_fit.theta[ok][:, layout.den_columns])
        powers = guard_radius ** np.arange(1, layout.den_degree + 1)
        check = np.flatnonzero(~(coef @ powers < 1.0))
        start_root[check] = denominator_roots(local_fit.theta[ok][check], layout)
    radius = np.minimum(guard_radius, start_root)
    radius[np.isnan(radius)] = 0.0
    theta_int, cost_ok, conv_ok, guard_ok, cov, sk_sums, oe_sums, lm_sums = (
        _compiled_refine.sk_windows(
            U.reshape(P, layout.n_inputs, -1), Y, local_fit.slow_bins[ok], theta0,
            local_fit.rss[ok], local_fit.system[ok], jump_limit[ok], radius,
            weights=sk["weights"], col_base=sk["col_base"], tables=sk["tables"],
            n_bands=nb, n_centre=nb + P, band_int=sk["band_int"],
            den_int=sk["den_int"], den_map=sk["den_map"], system_factor=layout.F,
            guard_radius=guard_radius, iterations=sk_iterations, tol=tol,
            keep_best=keep_best, exact_tol=EXACT_FIT_TOL,
            lm_iterations=lm_iterations, from_layout=sk["from_layout"],
            layout_weights=sk["layout_weights"],
            layout_col_base=sk["layout_col_base"],
            layout_tables=sk["layout_tables"],
        )
    )
    theta = local_fit.theta.copy()
    theta[ok] = _real_map(theta_int, sk["to_layout"])
    cost = np.full(B, np.nan)
    cost[ok] = cost_ok
    guarded = np.zeros(B, dtype=bool)
    guarded[ok] = guard_ok
    converged = np.zeros(B, dtype=bool)
    converged[ok] = conv_ok
    gram = np.full((B, layout.n_params), np.nan)
    gram[ok, :nb] = np.real(np.diagonal(cov[:, :nb, :nb], axis1=1, axis2=2))
    lead = np.full((B, nb, nb), np.nan, dtype=complex)
    lead[ok] = cov[:, :nb, :nb]
    n_sk, n_lm = sk_sums.size - 1, lm_sums.size
    cost_history = np.concatenate([oe_sums, lm_sums]) / n_ok
    return RefinementResult(
        local_fit=_refined_fit(local_fit, layout, theta, cost, gram, lead),
        cost_history=cost_history,
        sk_cost_history=sk_sums / n_ok,
        sk_iterations=n_sk,
        lm_iterations=n_lm,
        guarded=guarded,
        converged=converged,
        stopped_far=(
            n_sk == sk_iterations and _still_dropping(cost_history[: n_sk + 1], tol),
            n_lm == lm_iterations and _still_dropping(cost_history[n_sk:], tol),
        ),
    )


def _real_map(theta: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Complex ``theta @ matrix`` for a real ``matrix``."""
    return theta.real @ matrix + 1j * (theta.imag @ matrix)


@functools.lru_cache(maxsize=16)
def _sk_layout(layout: LocalModelLayout) -> dict:
    """Tables of the compiled SK of a layout (data-independent)."""
    weights, col_base, _ = _compiled_tables(layout)
    P, nb = layout.n_experiments, layout.n_bands
    tables = _compiled.moment_tables(weights, col_base, nb, P, weighted=True)
    empty = StructuredWindows(
        np.zeros((P, nb)), np.zeros((P, 1)), np.zeros(0, dtype=int), layout
    )
    T = empty.to_layout_matrix
    p = layout.n_params
    band_int = np.argmax(T[:, :nb] != 0, axis=0)
    # the window-centre band values are internal columns p - n_centre + f, as
    # they are (no change of basis) layout columns f
    expected = np.zeros((p, nb))
    expected[band_int, np.arange(nb)] = 1.0
    if not np.array_equal(T[:, :nb], expected) or not np.array_equal(
        band_int, p - nb - P + np.arange(nb)
    ):
        raise AssertionError("unexpected internal order of the centre columns")
    den_cols = np.arange(p)[layout.den_columns]
    den_int = np.flatnonzero(np.any(T[:, den_cols] != 0, axis=1))
    S = np.linalg.inv(T)
    layout_weights, layout_col_base = _layout_columns(weights, col_base, S)
    layout_tables = _compiled.moment_tables(
        layout_weights, layout_col_base, nb, P, weighted=True
    )
    for key in ("q_basis", "pair_kind", "pair_a", "pair_b", "pair_nd", "pair_off"):
        if not np.array_equal(layout_tables[key], tables[key]):
            raise AssertionError("layout and internal pair series differ")
    return {
        "weights": weights, "col_base": col_base, "tables": tables,
        "layout_weights": layout_weights, "layout_col_base": layout_col_base,
        "layout_tables": layout_tables,
        "to_layout": T, "from_layout": S, "band_int": band_int,
        "den_int": den_int, "den_map": T[np.ix_(den_int, den_cols)],
    }


def _layout_columns(weights, col_base, from_layout):
    """Column weights and bases of the layout basis: column ``j`` is
    ``sum_i S[j, i]`` times internal column ``i`` (``A_layout = A_int S^T``),
    the monomial ``x^d`` times one base sequence; the monomial is returned
    exact (the product ``weights @ S^T`` carries round-off)."""
    product = weights @ from_layout.T
    L = weights.shape[0]
    n = L // 2
    x = (np.arange(L) - n) / max(n, 1)
    out = np.empty_like(product)
    bases = np.empty(product.shape[1], dtype=np.int64)
    for j in range(product.shape[1]):
        base = np.unique(col_base[from_layout[j] != 0])
        errors = [np.max(np.abs(product[:, j] - x**d)) for d in range(L)]
        d = int(np.argmin(errors))
        if base.size != 1 or errors[d] > 1e-10:
            raise AssertionError("a layout column is no monomial of one base")
        out[:, j] = x**d
        bases[j] = base[0]
    return out, bases


def _pad_sum(parts, length):
    total = np.zeros(length)
    for part in parts:
        if part.size == 0:
            continue
        padded = np.concatenate([part, np.full(length - part.size, part[-1])])
        total += padded
    return total


def result_summary(result: RefinementResult) -> dict:
    """The history of one refinement, for :func:`pool_summaries`."""
    n_sk = result.sk_iterations
    return {
        "n_windows": int(np.count_nonzero(result.local_fit.well_posed)),
        "sk": result.cost_history[: n_sk + 1],
        "lm": result.cost_history[n_sk + 1 :],
        "sk_cost": result.sk_cost_history,
        "n_guarded": result.n_guarded,
    }


def pool_summaries(summaries: list[dict]) -> dict:
    """Histories of several refinements (the output rows of a MIMO fit) as
    one over all their windows: a refinement that stopped earlier keeps its
    last mean cost, the means are weighted by the numbers of windows.

    Parameters
    ----------
    summaries : list of dict
        :func:`result_summary` of each refinement.

    Returns
    -------
    dict
        ``cost_history``, ``sk_cost_history``, ``sk_iterations``,
        ``lm_iterations`` and ``n_guarded``, as in :class:`RefinementResult`.
    """
    n_sk = max(s["sk"].size for s in summaries) - 1
    n_lm = max(s["lm"].size for s in summaries)
    total = max(sum(s["n_windows"] for s in summaries), 1)
    sk = np.zeros(n_sk + 1)
    lm = np.zeros(n_lm)
    sk_cost = np.zeros(n_sk + 1)
    for s in summaries:
        weight = s["n_windows"] / total
        sk += weight * _padded(s["sk"], n_sk + 1)
        sk_cost += weight * _padded(s["sk_cost"], n_sk + 1)
        lm += weight * _padded(s["lm"] if s["lm"].size else s["sk"][-1:], n_lm)
    return {
        "cost_history": np.concatenate([sk, lm]),
        "sk_cost_history": sk_cost,
        "sk_iterations": n_sk,
        "lm_iterations": n_lm,
        "n_guarded": sum(s["n_guarded"] for s in summaries),
    }


def _padded(values: np.ndarray, length: int) -> np.ndarray:
    if length == 0:
        return values[:0]
    return np.concatenate([values, np.full(length - values.size, values[-1])])
