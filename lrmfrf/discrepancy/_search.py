"""The search of :func:`lrmfrf.diagnose`: greedy, prune, refit, debias.

Given the comparison (:class:`~lrmfrf.discrepancy.fit.FitProblem`) and the
nominal model, :func:`run_search` tests the model, accepts catalogue effects
greedily (revisiting earlier choices), refits them jointly, drops those the
joint model no longer needs, corrects the refit for the estimator bias, fits
an unnamed model error when nothing in the catalogue explains the gap, and
returns the :class:`~lrmfrf.discrepancy.report.DiagnosisReport`. Candidate
models whose loop with the controller is unstable are skipped
(:class:`LoopGuard`). The input checks are in :mod:`._inputs`.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ._inputs import SearchSettings, closed_loop, measured_system
from ._models import ContinuousPlant, resonances, to_discrete_ss
from .detect import (
    Calibration,
    bin_power,
    calibrate,
    discrepancy_spectrum,
    global_test,
    uncalibrated,
)
from .effects import EffectContext, MissingMode, ModelError
from .fit import FitProblem, apply_all, fit_candidate, fit_joint, likelihood_ratio_p
from .report import DiagnosisReport, Finding

__all__ = ["run_search", "Calibrator", "LoopGuard"]


def run_search(problem: FitProblem, nominal: ContinuousPlant, catalogue: list,
               calibrator: Calibrator, cal0: Calibration, settings: SearchSettings,
               *, controller, F: int) -> DiagnosisReport:
    """Test the nominal model, name what is missing, report before and after.

    Parameters
    ----------
    problem : FitProblem
        The measured FRF on the compared bins (changed in place: its bias,
        scale and inflation follow the calibration in use).
    nominal : ContinuousPlant
        The user's plant.
    catalogue : list of Effect
    calibrator : Calibrator
        Calibrates the tests at a given plant model.
    cal0 : Calibration
        Calibration at the nominal model.
    settings : SearchSettings
    controller : control.StateSpace or None
        Discrete controller (closed-loop data), or None.
    F : int
        Downsampling factor.

    Returns
    -------
    DiagnosisReport
    """
    alpha, effect_alpha = settings.alpha, settings.effect_alpha
    ic_margin, max_effects = settings.ic_margin, settings.max_effects
    debias_rounds = settings.debias_rounds
    guard = LoopGuard(controller, problem.sample_time)
    _set_calibration(problem, cal0)
    w0 = problem.whitened(nominal)
    test0 = global_test(bin_power(w0), cal0, alpha)
    before = {"test": test0, "model": _model_seen(problem, nominal), "cal": cal0}

    accepted, params, steps, findings = [], [], [], []
    current = nominal
    cal_final = cal0
    if test0.significant and max_effects > 0:
        current, ambiguous, cal_final = _greedy(
            problem, nominal, catalogue, accepted, params, steps, calibrator,
            alpha=alpha, effect_alpha=effect_alpha, ic_margin=ic_margin,
            max_effects=max_effects, cal=cal0, guard=guard,
        )
        joint = None
        if accepted:
            context = _context(problem, current, cal_final)
            joint = fit_joint(problem, nominal, accepted, params, context)
            if joint.cost <= problem.cost(current) and guard.admits(
                joint.plant, _joint_label(accepted)
            ):
                current, params = joint.plant, joint.params
            current, params, joint = _prune(problem, nominal, accepted, params,
                                            steps, current, joint, context,
                                            effect_alpha, guard=guard)
            current, params, joint, cal_final = _debias(
                problem, nominal, accepted, params, current, joint, context,
                calibrator, cal_final, debias_rounds, guard,
            )
        findings = [
            _finding(problem, nominal, accepted, params, i, steps[i], joint)
            for i in range(len(accepted))
        ]
        if ambiguous is not None:
            findings.append(ambiguous)
        test = global_test(bin_power(problem.whitened(current)), cal_final, alpha)
        if test.significant and ambiguous is None:
            extra = _unexplained(problem, nominal, accepted, params, current,
                                 cal_final, effect_alpha, guard)
            if extra is not None:
                current, finding = extra
                findings.append(finding)

    _set_calibration(problem, cal_final)
    test1 = global_test(bin_power(problem.whitened(current)), cal_final, alpha)
    # Both gaps use one yardstick, the measurement's calibrated std at the
    # updated model (the best description of the system that made the data).
    # The nominal calibration is the right null for *testing* the nominal
    # model, but as a yardstick it counts the estimator bias the nominal
    # model's sharp modes would cause as noise, also where the data have no
    # such mode (a shifted mode), and so understates the gap before.
    gap_before = float(np.sqrt(np.mean(np.abs(problem.whitened(nominal)) ** 2)))
    return DiagnosisReport(
        findings=findings,
        gap_before=gap_before,
        gap_after=test1.gap,
        updated_plant=to_discrete_ss(current, problem.sample_time),
        plant=to_discrete_ss(nominal, problem.sample_time),
        frequencies=problem.frequencies,
        measured=problem.measured,
        std=problem.std * cal_final.scale,
        model_before=before["model"],
        model_after=_model_seen(problem, current),
        spectrum_before=test0.spectrum,
        spectrum_after=test1.spectrum,
        threshold_before=test0.spectrum_threshold,
        threshold_after=test1.spectrum_threshold,
        p_value_before=test0.p_value,
        p_value_after=test1.p_value,
        slow_nyquist=0.5 / (F * problem.sample_time),
        closed_loop=controller is not None,
        calibration=cal0,
        calibration_after=cal_final,
        settings={"alpha": alpha, "effect_alpha": effect_alpha,
                  "ic_margin": ic_margin, "max_effects": max_effects,
                  "debias_rounds": debias_rounds,
                  "calibration_runs": cal0.n_runs,
                  "smoothing_bins": cal0.smoothing_bins},
        skipped_candidates=list(guard.skipped),
    )


def _debias(problem, nominal, accepted, params, current, joint, context,
            calibrator, cal, rounds, guard):
    """Bias-corrected joint refit (a fixed-point iteration).

    Local rational models are biased at sharp resonances by the noise (the
    estimated peak is flattened), so a fit to the raw FRF overestimates the
    damping of a lightly damped mode. The calibration at the updated model
    estimates that bias ``b``; the effects are refitted to ``G_meas - b``
    (weights: the noise part of the calibrated error only), and ``b`` is
    recalibrated at the refitted model, ``rounds`` times. The problem is left
    with the bias counted as error in the scale (the yardstick of the gaps).
    A refit whose closed loop with the controller is unstable ends the rounds.
    """
    for _ in range(rounds):
        if cal.noise_scale is None:
            break
        problem.bias = cal.bias
        problem.scale = cal.noise_scale
        refit = fit_joint(problem, nominal, accepted, params, context)
        if not refit.cost <= problem.cost(current):  # failed refit (or NaN)
            break
        if not guard.admits(refit.plant, _joint_label(accepted, "debiased ")):
            break
        current, params, joint = refit.plant, refit.params, refit
        cal = calibrator(current)
    _set_calibration(problem, cal)
    return current, params, joint, cal


def _greedy(problem, nominal, catalogue, accepted, params, steps, calibrator, *,
            alpha, effect_alpha, ic_margin, max_effects, cal, guard):
    """Accept the best significant, unambiguous candidate, up to max_effects.

    Each step fits every candidate on top of the accepted effects; the winner
    is accepted, all accepted effects are refitted jointly, earlier choices
    are revisited (:func:`_swap`), and the tests are recalibrated at the
    updated model (the null hypothesis of the next step). The search stops
    when the updated model passes the global test. A candidate whose closed
    loop with the controller is unstable cannot have made the data: it is
    skipped (and counted by ``guard``).
    """
    current = nominal
    for _ in range(max_effects):
        cost0 = problem.cost(current)
        # mode shifts act before the modes accepted missing modes add: their
        # targets are the modes of the nominal plant with the shifts only
        modal = None
        if any(isinstance(e, MissingMode) for e in accepted):
            modal = apply_all(nominal, [e for e in accepted if e.order == 0],
                              [p for e, p in zip(accepted, params, strict=True)
                               if e.order == 0])
        context = _context(problem, current, cal, modal_plant=modal)
        taken = {effect.label() for effect in accepted}
        fits = []
        for entry in catalogue:
            if not entry.named:
                continue
            for effect in entry.expand(context):
                if effect.label() in taken and not effect.repeatable:
                    continue
                fit = fit_candidate(problem, nominal, accepted, params, effect, context)
                if (fit is not None and np.isfinite(fit.cost)
                        and guard.admits(fit.plant, effect.label())):
                    fits.append((effect.label(), fit))
        if not fits:
            return current, None, cal
        fits.sort(key=lambda item: item[1].bic(problem))
        _prefer_parent(problem, fits, cost0, ic_margin, effect_alpha)
        label, best = fits[0]
        statistic, p_value = likelihood_ratio_p(problem, cost0, best.cost,
                                                best.n_params)
        ranked = [
            {"label": lab, "bic": fit.bic(problem), "cost": fit.cost,
             "parameters": _reported(fit.effects[0], fit.params[0])}
            for lab, fit in fits[:6]
        ]
        if p_value >= effect_alpha:
            return current, None, cal
        rivals = [
            (lab, fit) for lab, fit in fits[1:]
            if fit.bic(problem) - best.bic(problem) < ic_margin
            and fit.effects[0].parent != best.effects[0].name
            and likelihood_ratio_p(problem, cost0, fit.cost, fit.n_params)[1]
            < effect_alpha
        ]
        if rivals:
            ambiguous = Finding(
                effect="ambiguous",
                parameters=_reported(best.effects[0], best.params[0]),
                band=_band(problem.frequencies, problem.whitened(current),
                           problem.whitened(best.plant)),
                statistic=statistic,
                p_value=p_value,
                description=(
                    "several effects explain the discrepancy about equally well: "
                    + ", ".join([label] + [lab for lab, _ in rivals])
                    + "; nothing was added to the model"
                ),
                candidates=ranked,
            )
            return current, ambiguous, cal
        accepted.append(best.effects[0])
        params.append(best.params[0])
        steps.append({"candidates": ranked, "fits": fits[1:4]})
        current = best.plant
        if len(accepted) > 1:
            current = _refit_and_swap(problem, nominal, accepted, params, steps,
                                      context, current, guard, ic_margin=ic_margin)
        cal = calibrator(current)
        _set_calibration(problem, cal)
        w_after = problem.whitened(current)
        if not global_test(bin_power(w_after), cal, alpha).significant:
            break
    return current, None, cal


def _prefer_parent(problem, fits, cost0, ic_margin, effect_alpha) -> None:
    """Put the simpler parent effect first unless its refinement earns its place.

    When the best candidate refines another (``Effect.parent``: a per-channel
    gain refines the all-channel ``gain``) and that parent is significant and
    within ``ic_margin`` of it in BIC, the parent is named: a per-channel
    effect wins only when it is better by the margin. ``fits`` (sorted by
    BIC) is reordered in place; nothing changes without refining effects.
    """
    best = fits[0][1]
    parent = best.effects[0].parent
    if parent is None:
        return
    for index, (_, fit) in enumerate(fits[1:], 1):
        if fit.effects[0].name != parent:
            continue
        if (fit.bic(problem) - best.bic(problem) < ic_margin
                and likelihood_ratio_p(problem, cost0, fit.cost,
                                       fit.n_params)[1] < effect_alpha):
            fits.insert(0, fits.pop(index))
        return


def _swap_margin(current, alternative, ic_margin: float, others=()) -> float:
    """BIC by which ``alternative`` must beat ``current`` to replace it: the
    margin to refine a parent (``Effect.parent``), minus the margin to go
    back to it, else 0.

    Going back is not preferred while another accepted effect (``others``)
    refines the same parent: the parent with that sibling is no simpler than
    the two refinements (on two inputs the same model: ``gain`` 1.2 with
    input u0 0.75 is input u0 0.9 with input u1 1.2, their BIC ties), so it
    must win by the margin.
    """
    if alternative.parent is not None and alternative.parent == current.name:
        return ic_margin
    if current.parent is not None and current.parent == alternative.name:
        if any(other.parent == current.parent for other in others):
            return ic_margin
        return -ic_margin
    return 0.0


def _total_bic(problem, cost, effects) -> float:
    n_params = sum(len(e.all_names) for e in effects)
    return cost / problem.inflation + n_params * math.log(problem.n_effective)


def _refit_and_swap(problem, nominal, accepted, params, steps, context, current,
                    guard, *, ic_margin=0.0):
    """Joint refit, then try each accepted effect's runners-up in its place.

    A choice made early (e.g. delay or low-pass, while a missing mode was
    still unmodelled) is replaced when the joint fit with the alternative has
    a lower BIC (a per-channel refinement of the accepted effect: lower by
    ``ic_margin``; its parent in its place: within ``ic_margin``, unless
    another refinement of that parent is accepted, see :func:`_swap_margin`).
    Refits whose closed loop is unstable are not taken.
    """
    joint = fit_joint(problem, nominal, accepted, params, context)
    if joint.cost < problem.cost(current) and guard.admits(
        joint.plant, _joint_label(accepted)
    ):
        params[:] = joint.params
        current = joint.plant
    best_bic = _total_bic(problem, problem.cost(current), accepted)
    for i in range(len(accepted)):
        others = {e.label() for j, e in enumerate(accepted) if j != i}
        for label, alternative in steps[i]["fits"]:
            effect = alternative.effects[0]
            if label in others and not effect.repeatable:
                continue
            trial = list(accepted)
            trial[i] = effect
            trial_params = list(params)
            trial_params[i] = alternative.params[0]
            fit = fit_joint(problem, nominal, trial, trial_params, context)
            bic = _total_bic(problem, fit.cost, trial)
            margin = _swap_margin(accepted[i], effect, ic_margin,
                                  [e for j, e in enumerate(accepted) if j != i])
            if bic < best_bic - margin and guard.admits(fit.plant,
                                                        _joint_label(trial)):
                accepted[i] = effect
                params[:] = fit.params
                current, best_bic = fit.plant, bic
                others = {e.label() for j, e in enumerate(accepted) if j != i}
    return current


def _unexplained(problem, nominal, accepted, params, current, cal, effect_alpha,
                 guard):
    """Fit the unnamed low-order model error on top of the accepted effects."""
    context = _context(problem, current, cal)
    effect = ModelError()
    fit = fit_candidate(problem, nominal, accepted, params, effect, context)
    if fit is None or not guard.admits(fit.plant, effect.label()):
        return None
    cost0 = problem.cost(current)
    statistic, p_value = likelihood_ratio_p(problem, cost0, fit.cost, fit.n_params)
    if p_value >= effect_alpha:
        return None
    band = _band(problem.frequencies, problem.whitened(current),
                 problem.whitened(fit.plant))
    finding = Finding(
        effect=effect.name,
        parameters=_reported(effect, fit.params[0]),
        band=band,
        statistic=statistic,
        p_value=p_value,
        confidence_intervals=_intervals(fit, 0, effect),
        description=effect.describe(fit.params[0]),
    )
    return fit.plant, finding


def _prune(problem, nominal, accepted, params, steps, current, joint, context,
           effect_alpha, *, guard=None):
    """Drop accepted effects the joint model no longer needs.

    An effect accepted early can stand in for one found later (e.g. a gain
    absorbing part of a still unmodelled mode); after the joint refit it is
    then about the identity. Backward elimination: while some effect's
    drop-one likelihood-ratio p-value (the others held at their values, so it
    errs towards keeping) is at least ``effect_alpha``, the least significant
    is removed and the rest refitted. A single effect is always kept (it was
    accepted against the model without it). An effect whose removal leaves an
    unstable closed loop (after the refit) is kept, and pruning stops.
    """
    while len(accepted) > 1:
        p_values = [_drop_one(problem, nominal, accepted, params, i)[1]
                    for i in range(len(accepted))]
        worst = int(np.argmax(p_values))
        if p_values[worst] < effect_alpha:
            break
        kept = [i for i in range(len(accepted)) if i != worst]
        trial = [accepted[i] for i in kept]
        refit = fit_joint(problem, nominal, trial, [params[i] for i in kept],
                          context)
        if guard is not None and not guard.admits(refit.plant, _joint_label(trial)):
            break
        del accepted[worst], params[worst], steps[worst]
        joint = refit
        current, params = joint.plant, joint.params
    return current, params, joint


def _drop_one(problem, nominal, accepted, params, index):
    """LR statistic, p-value and whitened residuals without / with one effect."""
    full = apply_all(nominal, accepted, params)
    others = [e for j, e in enumerate(accepted) if j != index]
    other_params = [p for j, p in enumerate(params) if j != index]
    without = apply_all(nominal, others, other_params)
    w_full, w_without = problem.whitened(full), problem.whitened(without)
    statistic, p_value = likelihood_ratio_p(
        problem, float(np.sum(np.abs(w_without) ** 2)),
        float(np.sum(np.abs(w_full) ** 2)), len(accepted[index].all_names),
    )
    return statistic, p_value, w_without, w_full


def _finding(problem, nominal, accepted, params, index, step, joint) -> Finding:
    """Finding with drop-one evidence: the model without this effect vs with."""
    effect = accepted[index]
    statistic, p_value, w_without, w_full = _drop_one(problem, nominal, accepted,
                                                      params, index)
    intervals = _intervals(joint, index, effect) if joint is not None else {}
    return Finding(
        effect=effect.name,
        parameters=_reported(effect, params[index]),
        band=_band(problem.frequencies, w_without, w_full),
        statistic=statistic,
        p_value=p_value,
        confidence_intervals=intervals,
        description=effect.describe(params[index]),
        candidates=step["candidates"],
        nuisance={n: params[index][n] for n in effect.nuisance_names},
    )


def _reported(effect, params) -> dict:
    reported = dict(effect.fixed_parameters())  # e.g. the channel, first
    reported.update({n: float(params[n]) for n in effect.parameter_names})
    return reported


def _intervals(fit, index, effect) -> dict:
    out = {}
    for name in effect.parameter_names:
        value = fit.params[index][name]
        sd = fit.std_of(index, name)
        if np.isfinite(sd):
            out[name] = (value - 1.96 * sd, value + 1.96 * sd)
    return out


def _band(frequencies, w_before, w_after) -> tuple:
    gain = np.maximum(bin_power(w_before) - bin_power(w_after), 0.0)
    total = gain.sum()
    if total <= 0:
        return (float(frequencies[0]), float(frequencies[-1]))
    cumulative = np.cumsum(gain) / total
    low = frequencies[np.searchsorted(cumulative, 0.05)]
    high = frequencies[min(np.searchsorted(cumulative, 0.95), frequencies.size - 1)]
    return (float(low), float(high))


def _context(problem: FitProblem, plant: ContinuousPlant, cal, *,
             modal_plant: ContinuousPlant | None = None) -> EffectContext:
    plant_frf = problem.plant_response(plant)
    model = problem.measured_response(plant_frf)
    residual = problem.measured - model - problem.bias
    std = problem.scale * problem.std
    if plant_frf.ndim > 1:
        sensitivity, plant_meas = _plant_level(problem, plant_frf)
        plant_std = std  # the measured system's: weights of initial guesses only
    elif problem.controller is None:
        sensitivity = np.ones_like(plant_frf)
        plant_meas = problem.measured - problem.bias
        plant_std = std
    else:
        loop = 1.0 + problem.controller * plant_frf
        sensitivity = 1.0 / loop**2
        seen = problem.measured - problem.bias
        with np.errstate(divide="ignore", invalid="ignore"):
            plant_meas = seen / (1.0 - problem.controller * seen)
            plant_std = std / np.abs(1.0 - problem.controller * seen) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = plant_meas / plant_frf
        weight = np.abs(plant_frf) ** 2 / plant_std**2
    weight = np.where(np.isfinite(weight) & np.isfinite(ratio), weight, 0.0)
    ratio = np.where(np.isfinite(ratio), ratio, 1.0)
    w2 = bin_power(residual / std)
    return EffectContext(
        plant=plant,
        frequencies=problem.frequencies,
        sample_time=problem.sample_time,
        plant_ratio=ratio,
        plant_weight=weight,
        discrepancy=discrepancy_spectrum(w2, cal.smoothing_bins),
        resonances=resonances(plant),
        modal_resonances=(None if modal_plant is None or modal_plant is plant
                          else resonances(modal_plant)),
        sensitivity=sensitivity,
        residual=residual,
        std=std,
    )


def _plant_level(problem: FitProblem, plant_frf: np.ndarray):
    """MIMO: the sensitivities ``(S_o, S_i)`` and the measured plant.

    ``dG = S_o dP S_i`` with ``S_o = (I + P C)^-1`` (n_y, n_y, K) and
    ``S_i = (I + C P)^-1`` (n_u, n_u, K) at the model (identities without a
    controller); the measured plant is ``G (I - C G)^-1``.
    """
    n_y, n_u, K = plant_frf.shape
    seen = np.moveaxis(problem.measured - problem.bias, -1, 0)  # (K, n_y, n_u)
    if problem.controller is None:
        eye_y = np.broadcast_to(np.eye(n_y)[..., None], (n_y, n_y, K))
        eye_u = np.broadcast_to(np.eye(n_u)[..., None], (n_u, n_u, K))
        return (eye_y, eye_u), problem.measured - problem.bias
    P = np.moveaxis(plant_frf, -1, 0)
    C = np.moveaxis(problem.controller, -1, 0)  # (K, n_u, n_y)
    with np.errstate(divide="ignore", invalid="ignore"):
        S_o = np.linalg.inv(np.eye(n_y) + P @ C)
        S_i = np.linalg.inv(np.eye(n_u) + C @ P)
        try:
            inverse = np.linalg.inv(np.eye(n_u) - C @ seen)
            plant_meas = seen @ inverse
        except np.linalg.LinAlgError:
            plant_meas = np.full_like(seen, np.nan)
    return ((np.moveaxis(S_o, 0, -1), np.moveaxis(S_i, 0, -1)),
            np.moveaxis(plant_meas, 0, -1))


def _model_seen(problem: FitProblem, plant: ContinuousPlant) -> np.ndarray:
    return problem.measured_response(problem.plant_response(plant)) + problem.bias


def _set_calibration(problem: FitProblem, cal: Calibration) -> None:
    problem.bias = np.zeros_like(cal.bias)  # counted in the scale instead
    problem.scale = cal.scale
    problem.inflation = cal.inflation


def _joint_label(effects, prefix="") -> str:
    return f"{prefix}joint refit of " + " + ".join(e.label() for e in effects)


class LoopGuard:
    """Admit only plant models that close a stable loop with the controller.

    A candidate model whose closed loop is unstable cannot describe the
    measured (stable) system: the search skips it and records its label in
    ``skipped`` (reported as ``DiagnosisReport.skipped_candidates``).
    """

    def __init__(self, controller, sample_time: float):
        self.controller, self.sample_time = controller, sample_time
        self.skipped: list[str] = []

    def admits(self, plant: ContinuousPlant, label: str) -> bool:
        if self.controller is None:
            return True
        _, radius = closed_loop(plant, self.controller, self.sample_time)
        if radius < 1.0:
            return True
        self.skipped.append(label)
        return False


class Calibrator:
    """Calibrate at a given plant model (simulation, or the fallback)."""

    def __init__(self, template, fitted, u, F, sample_time, bins, controller,
                 problem, n_runs, smoothing_bins, rng, steady_state=False):
        self.template, self.fitted = template, fitted
        self.steady_state = steady_state
        self.u, self.F, self.sample_time = u, F, sample_time
        self.bins, self.controller, self.problem = bins, controller, problem
        self.n_runs, self.smoothing_bins, self.rng = n_runs, smoothing_bins, rng
        noise = getattr(fitted, "noise_variance_", None)
        self.noise = None if noise is None else np.asarray(noise, dtype=float)
        if self.n_runs and (self.noise is None or not np.any(np.isfinite(self.noise))):
            warnings.warn(
                f"{type(fitted).__name__} exposes no finite noise_variance_, so the "
                "tests cannot be calibrated by simulation; trusting its frf_std_ "
                "with a heuristic correlation inflation instead.",
                UserWarning, stacklevel=3,
            )
            self.n_runs = 0

    def __call__(self, plant: ContinuousPlant) -> Calibration:
        if self.n_runs == 0:
            half_window = getattr(self.template, "half_window", 4)
            inflation = max(float(half_window) / 4.0, 1.0)
            return uncalibrated(self.bins.size, self.smoothing_bins, inflation,
                                entry_shape=self.problem.measured.shape[:-1])
        system = measured_system(plant, self.controller, self.sample_time)
        model_frf = self.problem.measured_response(self.problem.plant_response(plant))
        return calibrate(
            self.template, system, self.u, self.F, self.sample_time, self.noise,
            self.bins, model_frf, n_runs=self.n_runs,
            smoothing_bins=self.smoothing_bins,
            rng=self.rng, steady_state=self.steady_state,
        )
