"""Fit candidate effects to the whitened discrepancy and choose between them.

The cost of a model is ``J = sum_k |w(k)|^2`` with the calibrated whitened
residual ``w = (G_meas - G_model - bias) / (kappa std)``. Because only about
``K / c`` bins are independent, ``J / c`` plays the role of a chi-square
(``-2 log L`` up to a constant), so that

- an effect with ``p`` fitted parameters is significant when the drop
  ``(J_0 - J) / c`` exceeds the chi-square ``1 - alpha_effect`` quantile with
  ``p`` degrees of freedom (likelihood-ratio test);
- candidates are ranked by ``BIC = J / c + p ln(K / c)`` and the best is only
  named when every other candidate is at least ``ic_margin`` worse; otherwise
  the step is reported as ambiguous.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import scipy.stats

from ._models import ContinuousPlant, discrete_response
from .effects import Effect

__all__ = ["FitProblem", "CandidateFit", "fit_candidate", "fit_joint", "apply_all",
           "closed_loop_response"]


@dataclass
class FitProblem:
    """The measured FRF and everything needed to evaluate a model against it.

    SISO arrays have shape ``(K,)``; a MIMO measurement puts its entries in
    front, ``(n_y, n_u, K)`` (python-control's layout), and every entry of
    every bin counts in the cost (the whitened residual is all entries' bins).

    Attributes
    ----------
    frequencies : ndarray of shape (K,)
        Compared bins in Hz.
    measured : ndarray of shape (K,) or (n_y, n_u, K), complex
        Estimated FRF of the measured system.
    std : ndarray of the shape of ``measured``
        Estimator standard deviation (raw).
    sample_time : float
    controller : ndarray of shape (K,) or (n_u, n_y, K), complex, or None
        Controller frequency response; the measured system is then
        ``P (I + C P)^-1`` (``P / (1 + C P)`` for SISO).
    bias : ndarray of the shape of ``measured``, complex
        Estimator bias expected under the model (from calibration).
    scale : ndarray of the shape of ``measured``
        ``kappa`` per bin and entry (from calibration).
    inflation : float
        Correlation inflation ``c``: the ``n_entries * K`` terms of the cost
        count as ``n_entries * K / c`` independent ones.
    """

    frequencies: np.ndarray
    measured: np.ndarray
    std: np.ndarray
    sample_time: float
    controller: np.ndarray | None
    bias: np.ndarray
    scale: np.ndarray
    inflation: float

    @property
    def n_bins(self) -> int:
        return self.frequencies.size

    @property
    def n_entries(self) -> int:
        """``n_y * n_u`` (1 for SISO)."""
        return self.measured.size // max(self.n_bins, 1)

    @property
    def n_effective(self) -> float:
        return max(self.n_bins * self.n_entries / self.inflation, 1.0)

    def plant_response(self, plant: ContinuousPlant) -> np.ndarray:
        return discrete_response(plant, self.frequencies, self.sample_time)

    def measured_response(self, plant_frf: np.ndarray) -> np.ndarray:
        if self.controller is None:
            return plant_frf
        if plant_frf.ndim == 1:
            return plant_frf / (1.0 + self.controller * plant_frf)
        return closed_loop_response(plant_frf, self.controller)

    def whitened(self, plant: ContinuousPlant) -> np.ndarray:
        model = self.measured_response(self.plant_response(plant))
        return (self.measured - model - self.bias) / (self.scale * self.std)

    def cost(self, plant: ContinuousPlant) -> float:
        return float(np.sum(np.abs(self.whitened(plant)) ** 2))


def closed_loop_response(plant_frf: np.ndarray, controller_frf: np.ndarray):
    """``P (I + C P)^-1`` per bin; ``P`` (n_y, n_u, K), ``C`` (n_u, n_y, K)."""
    P = np.moveaxis(plant_frf, -1, 0)  # (K, n_y, n_u)
    C = np.moveaxis(controller_frf, -1, 0)  # (K, n_u, n_y)
    loop = np.eye(P.shape[2]) + C @ P  # (K, n_u, n_u)
    # G = P loop^-1  <=>  loop^T G^T = P^T
    G = np.linalg.solve(np.swapaxes(loop, 1, 2), np.swapaxes(P, 1, 2))
    return np.moveaxis(np.swapaxes(G, 1, 2), 0, -1)


def real_residual(w: np.ndarray) -> np.ndarray:
    """Real and imaginary parts of all entries' bins, for least squares."""
    return np.concatenate([w.real.ravel(), w.imag.ravel()])


@dataclass
class CandidateFit:
    """One fitted candidate (or a joint fit of several effects).

    Attributes
    ----------
    effects : list of Effect
    params : list of dict
        Fitted parameters (reported and nuisance) per effect.
    cost : float
        ``J`` at the optimum.
    n_params : int
    covariance : ndarray of shape (n_params, n_params)
        Parameter covariance, inflation included (natural units).
    names : list of tuple
        ``(effect index, parameter name)`` per covariance row.
    plant : ContinuousPlant
        Base plant with the effects applied.
    success : bool
    """

    effects: list
    params: list
    cost: float
    n_params: int
    covariance: np.ndarray
    names: list
    plant: ContinuousPlant
    success: bool = True
    extra: dict = field(default_factory=dict)

    def bic(self, problem: FitProblem) -> float:
        return self.cost / problem.inflation + self.n_params * math.log(
            problem.n_effective
        )

    def std_of(self, effect_index: int, name: str) -> float:
        row = self.names.index((effect_index, name))
        value = self.covariance[row, row]
        if not (np.isfinite(value) and value >= 0):
            return math.nan
        return float(math.sqrt(value))


def apply_all(plant: ContinuousPlant, effects, params) -> ContinuousPlant:
    """Apply effects in their ``order`` (modal changes first, then series)."""
    order = sorted(range(len(effects)), key=lambda i: effects[i].order)
    for i in order:
        plant = effects[i].apply(plant, params[i])
    return plant


def fit_candidate(problem: FitProblem, base: ContinuousPlant, accepted: list,
                  accepted_params: list, effect: Effect, context,
                  *, n_refine: int = 2) -> CandidateFit | None:
    """Fit one candidate effect on top of the accepted ones (those held fixed).

    All initial guesses are evaluated; the best ``n_refine`` are refined with
    bounded nonlinear least squares.
    """
    guesses = effect.initial_guesses(context)
    if not guesses:
        return None
    bounds = effect.bounds(context)
    names = list(effect.all_names)
    lower = np.array([bounds[n][0] for n in names], dtype=float)
    upper = np.array([bounds[n][1] for n in names], dtype=float)

    def plant_of(x):
        params = dict(zip(names, x, strict=True))
        return apply_all(base, [*accepted, effect], [*accepted_params, params])

    def residual(x):
        try:
            w = problem.whitened(plant_of(x))
        except (np.linalg.LinAlgError, ValueError):
            return np.full(2 * problem.measured.size, 1e6)
        if not np.all(np.isfinite(w)):
            return np.full(2 * problem.measured.size, 1e6)
        return real_residual(w)

    starts = []
    for guess in guesses:
        x0 = np.clip(np.array([guess[n] for n in names], dtype=float), lower, upper)
        x0 = _inside(x0, lower, upper)
        starts.append((float(np.sum(residual(x0) ** 2)), x0))
    starts.sort(key=lambda item: item[0])
    # refine the best start, and the next ones only if they start nearly as well
    chosen = [x0 for cost, x0 in starts[:n_refine] if cost <= 2.0 * starts[0][0]]
    best = None
    for x0 in chosen:
        result = _least_squares(residual, x0, lower, upper)
        if best is None or result.cost < best.cost:
            best = result
    x = best.x
    try:
        plant = plant_of(x)
    except (np.linalg.LinAlgError, ValueError):
        # the effect cannot be applied to this base at all (e.g. a mode shift
        # aimed at a mode added by an accepted effect, whose nearest pole in
        # the base is a repeated pair): every start cost the 1e6 penalty
        return None
    cost = float(np.sum(best.fun**2))
    covariance = _covariance(best.jac, problem.inflation)
    return CandidateFit(
        effects=[effect],
        params=[dict(zip(names, map(float, x), strict=True))],
        cost=cost,
        n_params=len(names),
        covariance=covariance,
        names=[(0, n) for n in names],
        plant=plant,
        success=bool(best.success),
    )


def fit_joint(problem: FitProblem, base: ContinuousPlant, effects: list,
              params: list, context) -> CandidateFit:
    """Refit all accepted effects together, starting from their current values."""
    names, lower, upper, x0 = [], [], [], []
    for i, effect in enumerate(effects):
        bounds = effect.bounds(context)
        for n in effect.all_names:
            names.append((i, n))
            lower.append(bounds[n][0])
            upper.append(bounds[n][1])
            x0.append(params[i][n])
    lower, upper = np.array(lower, float), np.array(upper, float)
    x0 = _inside(np.clip(np.array(x0, float), lower, upper), lower, upper)

    def unpack(x):
        out = [dict() for _ in effects]
        for (i, n), value in zip(names, x, strict=True):
            out[i][n] = float(value)
        return out

    def residual(x):
        try:
            w = problem.whitened(apply_all(base, effects, unpack(x)))
        except (np.linalg.LinAlgError, ValueError):
            return np.full(2 * problem.measured.size, 1e6)
        if not np.all(np.isfinite(w)):
            return np.full(2 * problem.measured.size, 1e6)
        return real_residual(w)

    result = _least_squares(residual, x0, lower, upper)
    x = result.x
    fitted = unpack(x)
    return CandidateFit(
        effects=list(effects),
        params=fitted,
        cost=float(np.sum(result.fun**2)),
        n_params=len(names),
        covariance=_covariance(result.jac, problem.inflation),
        names=names,
        plant=apply_all(base, effects, fitted),
        success=bool(result.success),
    )


def likelihood_ratio_p(problem: FitProblem, cost_before: float, cost_after: float,
                       n_params: int) -> tuple[float, float]:
    """Statistic ``(J_0 - J) / c`` and its chi-square p-value."""
    statistic = max(cost_before - cost_after, 0.0) / problem.inflation
    return statistic, float(scipy.stats.chi2.sf(statistic, max(n_params, 1)))


# ---------------------------------------------------------------------------
# Private helpers
# ---------------------------------------------------------------------------


def _inside(x, lower, upper):
    """Move starting points strictly inside finite bounds."""
    span = np.where(np.isfinite(upper - lower), upper - lower, 1.0)
    eps = 1e-9 * np.maximum(span, 1e-300)
    return np.minimum(np.maximum(x, lower + eps), upper - eps)


def _least_squares(residual, x0, lower, upper):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return scipy.optimize.least_squares(
            residual, x0, bounds=(lower, upper), x_scale="jac", method="trf",
            max_nfev=50, xtol=1e-8, ftol=1e-8,
        )


def _covariance(jac: np.ndarray, inflation: float) -> np.ndarray:
    """``c (J^T J)^-1`` (pseudo-inverse if singular)."""
    jtj = jac.T @ jac
    try:
        inverse = np.linalg.pinv(jtj, rcond=1e-12)
    except np.linalg.LinAlgError:  # pragma: no cover
        return np.full(jtj.shape, np.nan)
    return inflation * inverse
