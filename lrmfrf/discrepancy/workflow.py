"""``diagnose``: where do model and measurement disagree, and why?"""

from __future__ import annotations

import math
import warnings

import control
import numpy as np
from sklearn.base import clone
from threadpoolctl import threadpool_limits

from .._validation import (
    check_nonnegative_float,
    check_nonnegative_int,
    check_probability,
    check_records,
    check_rng,
    check_sample_time,
    check_siso_system,
    renamed_keyword,
)
from ._models import (
    ContinuousPlant,
    as_continuous_plant,
    frequency_response,
    resonances,
    to_discrete_ss,
)
from .detect import (
    Calibration,
    calibrate,
    discrepancy_spectrum,
    global_test,
    uncalibrated,
)
from .effects import Effect, EffectContext, ModelError, default_effects
from .fit import FitProblem, apply_all, fit_candidate, fit_joint, likelihood_ratio_p
from .report import DiagnosisReport, Finding

__all__ = ["diagnose"]

#: Fewest compared bins for a meaningful diagnosis.
MIN_BINS = 20


def diagnose(
    plant,
    u_h,
    y_l,
    F: int,
    *,
    sample_time: float | None = None,
    controller=None,
    estimator=None,
    effects: list[Effect] | None = None,
    alpha: float = 0.01,
    effect_alpha: float = 1e-3,
    ic_margin: float = 6.0,
    max_effects: int = 3,
    calibration_runs: int = 10,
    calibration: Calibration | None = None,
    smoothing_bins: int = 9,
    band=None,
    debias_rounds: int = 2,
    rng: int | np.random.Generator | None = None,
    random_state=None,
    window=None,
) -> DiagnosisReport:
    """Find what is missing from a plant model, given a (slow-rate) measurement.

    The measured FRF (fast grid, beyond the slow Nyquist frequency, from
    ``estimator``) is compared with the model; if they differ by more than the
    calibrated noise, effects from the catalogue are fitted to the whitened
    discrepancy, the best is accepted when significant and unambiguous
    (greedy, up to ``max_effects``), all accepted effects are refitted jointly
    (then corrected for the estimator's bias, ``debias_rounds``), and an
    unnamed low-order model error is fitted when nothing in the catalogue
    explains the gap. ``gap_before`` and ``gap_after`` are measured with the
    same std, calibrated at the updated model.

    Parameters
    ----------
    plant : control.StateSpace or control.TransferFunction
        SISO model of the plant: discrete with ``dt == sample_time`` (taken as
        the ZOH discretisation of a continuous model) or continuous
        (discretised with ZOH).
    u_h : array-like of shape (N,) or (P, N)
        Fast-rate input(s); several experiments give better statistics.
    y_l : array-like of shape (M,) or (P, M)
        Slow-rate output(s), ``M = N / F``.
    F : int
        Downsampling factor.
    sample_time : float, optional
        Fast sample time in s. Default: the ``dt`` of ``plant`` if it is
        discrete, else of ``controller``; one of the three must give it. A
        value that contradicts a discrete model's ``dt`` is an error.
    controller : control.StateSpace or control.TransferFunction, optional
        Discrete SISO feedback controller (``dt == sample_time``). The measured
        system is then ``P (1 + C P)^-1`` (eq. EquivalentSystems) and effects
        are named at the plant level. Without it the measured system is ``P``.
    estimator : estimator, optional
        FRF estimator with ``fit(u_h, y_l, F, *, sample_time)`` and ``frf_``,
        ``frf_std_``, ``valid_`` (default ``LRMBeyondNyquist()``). An already
        fitted estimator is used as is (it must match the data sizes); an
        unfitted one is cloned and fitted to the data.
    effects : list of Effect, optional
        Catalogue (default :func:`default_effects`).
    alpha : float, default=0.01
        False-alarm level of the global test (no findings when it passes).
    effect_alpha : float, default=1e-3
        Level of the likelihood-ratio test that accepts an effect.
    ic_margin : float, default=6.0
        BIC margin by which the best candidate must beat every other; else the
        step is reported as ``"ambiguous"`` and nothing is added.
    max_effects : int, default=3
        Most effects accepted in the greedy search; ``0`` only tests (the
        report then has no findings, whatever the p-values say).
    calibration_runs : int, default=10
        Simulated experiments used to calibrate the tests against the
        estimator (see :func:`lrmfrf.discrepancy.detect.calibrate`). ``0``
        trusts the estimator's std and uses a heuristic correlation inflation
        (documented fallback, with a warning).
    calibration : Calibration, optional
        Reuse the nominal-model calibration of an earlier report
        (``report.calibration``) with the same inputs, plant and bins.
    smoothing_bins : int, default=9
        Width in bins of the moving mean that makes the discrepancy spectrum
        (called ``window`` before issue 12).
    band : (float, float), optional
        Compare only the estimator's bins with ``low <= f <= high`` (Hz), e.g.
        ``(0, slow_nyquist)`` to mimic a slow-rate-only analysis.
    debias_rounds : int, default=2
        Rounds of the final, bias-corrected joint refit: the estimator bias
        calibrated at the updated model (large at sharp resonances, where it
        flattens the peak) is subtracted from the measurement, the accepted
        effects are refitted and the bias is recalibrated at the new model.
        Without it the damping of a 0.8 %-damped mode comes out ~30 % high.
        ``0`` skips it; it needs ``calibration_runs >= 2``.
    rng : int, numpy.random.Generator or None
        Seed or generator of the calibration noise (as ``rng`` in
        :func:`lrmfrf.signals.multisine` and :func:`lrmfrf.simulate.simulate`).
    random_state, window : optional
        Deprecated names of ``rng`` and ``smoothing_bins`` (they warn with a
        ``FutureWarning`` and are removed in the next release).

    Returns
    -------
    DiagnosisReport

    Raises
    ------
    TypeError, ValueError
        For a plant or controller of the wrong type or sample time, no sample
        time (neither given nor a discrete model's ``dt``), an unstable closed
        loop of the given plant and controller, data the estimator cannot fit,
        or too few usable bins. (Candidate models tried by the search that
        would make the loop unstable are skipped and listed in the report's
        ``skipped_candidates``, not an error.)

    Examples
    --------
    >>> import control, numpy as np
    >>> from lrmfrf.discrepancy import diagnose
    >>> from lrmfrf.signals import multisine
    >>> from lrmfrf.simulate import simulate
    >>> Ts = 1e-3
    >>> model = control.c2d(control.tf([1.0], [1e-3, 1.0]), Ts)
    >>> u = np.stack([multisine(600, rng=i) for i in range(2)])
    >>> y = np.stack([simulate(control.ss(model), ui, 3, snr_db=40, rng=i).y_l
    ...               for i, ui in enumerate(u)])
    >>> report = diagnose(model, u, y, 3, rng=0,
    ...                   calibration_runs=6)  # doctest: +SKIP
    """
    rng = renamed_keyword(rng, random_state, new="rng", old="random_state")
    smoothing_bins = renamed_keyword(smoothing_bins, window, new="smoothing_bins",
                                     old="window", default=9)
    u, y, F = check_records(u_h, y_l, F)
    sample_time, source = _resolve_sample_time(sample_time, plant, controller)
    alpha = check_probability(alpha, "alpha")
    effect_alpha = check_probability(effect_alpha, "effect_alpha")
    ic_margin = check_nonnegative_float(ic_margin, "ic_margin")
    max_effects = check_nonnegative_int(max_effects, "max_effects")
    calibration_runs = check_nonnegative_int(calibration_runs, "calibration_runs")
    smoothing_bins = check_nonnegative_int(smoothing_bins, "smoothing_bins",
                                           minimum=1)
    debias_rounds = check_nonnegative_int(debias_rounds, "debias_rounds")
    if calibration_runs == 1:
        raise ValueError(
            "`calibration_runs` must be 0 (no calibration) or >= 2 (the spread of "
            "the runs is needed). Got 1. Use e.g. calibration_runs=10."
        )
    catalogue = list(default_effects() if effects is None else effects)
    for entry in catalogue:
        if not isinstance(entry, Effect):
            raise TypeError(
                f"`effects` must hold Effect instances. Got {type(entry).__name__}. "
                "Subclass lrmfrf.discrepancy.Effect."
            )
    rng = check_rng(rng)
    nominal = as_continuous_plant(plant, sample_time)
    controller = _check_controller(controller, sample_time, source)
    measured_system(nominal, controller, sample_time)  # stability check

    band = _check_band(band)
    fitted, template = _fit_estimator(estimator, u, y, F, sample_time)
    bins = _usable_bins(fitted, band)
    frequencies = np.asarray(fitted.frequencies_, dtype=float)[bins]
    controller_frf = (
        None if controller is None
        else frequency_response(controller, frequencies, sample_time)
    )

    with threadpool_limits(limits=1, user_api="blas"):
        problem = FitProblem(
            frequencies=frequencies,
            measured=np.asarray(fitted.frf_)[bins],
            std=np.asarray(fitted.frf_std_)[bins],
            sample_time=sample_time,
            controller=controller_frf,
            bias=np.zeros(bins.size, complex),
            scale=np.ones(bins.size),
            inflation=1.0,
        )
        calibrator = _Calibrator(template, fitted, u, F, sample_time, bins, controller,
                                 problem, calibration_runs, smoothing_bins, rng)
        cal0 = calibration if calibration is not None else calibrator(nominal)
        _check_calibration(cal0, bins.size)
        guard = _LoopGuard(controller, sample_time)
        return _run(problem, nominal, catalogue, calibrator, cal0, plant, controller,
                    alpha=alpha, effect_alpha=effect_alpha, ic_margin=ic_margin,
                    max_effects=max_effects, debias_rounds=debias_rounds, F=F,
                    guard=guard)


# ---------------------------------------------------------------------------
# The workflow
# ---------------------------------------------------------------------------


def _run(problem, nominal, catalogue, calibrator, cal0, plant, controller, *,
         alpha, effect_alpha, ic_margin, max_effects, debias_rounds, F, guard):
    _set_calibration(problem, cal0)
    w0 = problem.whitened(nominal)
    test0 = global_test(np.abs(w0) ** 2, cal0, alpha)
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
        test = global_test(np.abs(problem.whitened(current)) ** 2, cal_final, alpha)
        if test.significant and ambiguous is None:
            extra = _unexplained(problem, nominal, accepted, params, current,
                                 cal_final, effect_alpha, guard)
            if extra is not None:
                current, finding = extra
                findings.append(finding)

    _set_calibration(problem, cal_final)
    test1 = global_test(np.abs(problem.whitened(current)) ** 2, cal_final, alpha)
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
        context = _context(problem, current, cal)
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
                                      context, current, guard)
        cal = calibrator(current)
        _set_calibration(problem, cal)
        w_after = problem.whitened(current)
        if not global_test(np.abs(w_after) ** 2, cal, alpha).significant:
            break
    return current, None, cal


def _total_bic(problem, cost, effects) -> float:
    n_params = sum(len(e.all_names) for e in effects)
    return cost / problem.inflation + n_params * math.log(problem.n_effective)


def _refit_and_swap(problem, nominal, accepted, params, steps, context, current,
                    guard):
    """Joint refit, then try each accepted effect's runners-up in its place.

    A choice made early (e.g. delay or low-pass, while a missing mode was
    still unmodelled) is replaced when the joint fit with the alternative has
    a lower BIC. Refits whose closed loop is unstable are not taken.
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
            if bic < best_bic and guard.admits(fit.plant, _joint_label(trial)):
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
    return {n: float(params[n]) for n in effect.parameter_names}


def _intervals(fit, index, effect) -> dict:
    out = {}
    for name in effect.parameter_names:
        value = fit.params[index][name]
        sd = fit.std_of(index, name)
        if np.isfinite(sd):
            out[name] = (value - 1.96 * sd, value + 1.96 * sd)
    return out


def _band(frequencies, w_before, w_after) -> tuple:
    gain = np.maximum(np.abs(w_before) ** 2 - np.abs(w_after) ** 2, 0.0)
    total = gain.sum()
    if total <= 0:
        return (float(frequencies[0]), float(frequencies[-1]))
    cumulative = np.cumsum(gain) / total
    low = frequencies[np.searchsorted(cumulative, 0.05)]
    high = frequencies[min(np.searchsorted(cumulative, 0.95), frequencies.size - 1)]
    return (float(low), float(high))


def _context(problem: FitProblem, plant: ContinuousPlant, cal) -> EffectContext:
    plant_frf = problem.plant_response(plant)
    model = problem.measured_response(plant_frf)
    residual = problem.measured - model - problem.bias
    std = problem.scale * problem.std
    if problem.controller is None:
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
    w2 = np.abs(residual / std) ** 2
    return EffectContext(
        plant=plant,
        frequencies=problem.frequencies,
        sample_time=problem.sample_time,
        plant_ratio=ratio,
        plant_weight=weight,
        discrepancy=discrepancy_spectrum(w2, cal.smoothing_bins),
        resonances=resonances(plant),
        sensitivity=sensitivity,
        residual=residual,
        std=std,
    )


def _model_seen(problem: FitProblem, plant: ContinuousPlant) -> np.ndarray:
    return problem.measured_response(problem.plant_response(plant)) + problem.bias


def _set_calibration(problem: FitProblem, cal: Calibration) -> None:
    problem.bias = np.zeros_like(cal.bias)  # counted in the scale instead
    problem.scale = cal.scale
    problem.inflation = cal.inflation


class _Calibrator:
    """Calibrate at a given plant model (simulation, or the fallback)."""

    def __init__(self, template, fitted, u, F, sample_time, bins, controller,
                 problem, n_runs, smoothing_bins, rng):
        self.template, self.fitted = template, fitted
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
            return uncalibrated(self.bins.size, self.smoothing_bins, inflation)
        system = measured_system(plant, self.controller, self.sample_time)
        model_frf = self.problem.measured_response(self.problem.plant_response(plant))
        return calibrate(
            self.template, system, self.u, self.F, self.sample_time, self.noise,
            self.bins, model_frf, n_runs=self.n_runs,
            smoothing_bins=self.smoothing_bins,
            rng=self.rng,
        )


def _joint_label(effects, prefix="") -> str:
    return f"{prefix}joint refit of " + " + ".join(e.label() for e in effects)


class _LoopGuard:
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
        _, radius = _closed_loop(plant, self.controller, self.sample_time)
        if radius < 1.0:
            return True
        self.skipped.append(label)
        return False


def _closed_loop(plant: ContinuousPlant, controller, sample_time: float):
    """Discrete closed loop ``P (1 + C P)^-1`` and its largest pole magnitude."""
    discrete = to_discrete_ss(plant, sample_time)
    loop = control.feedback(discrete, control.ss(controller), sign=-1)
    radius = float(np.max(np.abs(np.linalg.eigvals(loop.A)))) if loop.nstates else 0.0
    return loop, radius


def measured_system(plant: ContinuousPlant, controller, sample_time: float):
    """Discrete model of the measured system; raise if the loop is unstable."""
    if controller is None:
        return to_discrete_ss(plant, sample_time)
    loop, radius = _closed_loop(plant, controller, sample_time)
    if radius >= 1.0:
        raise ValueError(
            "the closed loop of `plant` and `controller` is unstable (largest pole "
            f"magnitude {radius:.6g} >= 1), so it cannot be the measured system. "
            "Check the controller sign convention (u = u_h - C y) and the plant."
        )
    return loop


# ---------------------------------------------------------------------------
# Input checks
# ---------------------------------------------------------------------------


def _fit_estimator(estimator, u, y, F, sample_time):
    if estimator is None:
        from ..estimators import LRMBeyondNyquist

        estimator = LRMBeyondNyquist()
    if not hasattr(estimator, "fit"):
        raise TypeError(
            "`estimator` must be an FRF estimator with fit(u_h, y_l, F, *, "
            f"sample_time). Got {type(estimator).__name__}."
        )
    template = clone(estimator)
    if hasattr(estimator, "frf_"):
        N = u.shape[1]
        if getattr(estimator, "n_samples_", N) != N or getattr(
            estimator, "downsampling_factor_", F
        ) != F:
            raise ValueError(
                "the fitted `estimator` does not match the data: it was fitted to "
                f"N={getattr(estimator, 'n_samples_', None)}, "
                f"F={getattr(estimator, 'downsampling_factor_', None)}; the data "
                f"have N={N}, F={F}. Pass an unfitted estimator to fit it here."
            )
        stime = getattr(estimator, "sample_time_", sample_time)
        if not math.isclose(stime, sample_time, rel_tol=1e-9):
            raise ValueError(
                f"the fitted `estimator` used sample_time={stime!r} s, the call "
                f"sample_time={sample_time!r} s. Use one sample time."
            )
        return estimator, template
    fitted = clone(estimator)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fitted.fit(u, y, F, sample_time=sample_time)
    except ValueError as exc:
        raise ValueError(
            f"the estimator could not be fitted to the data ({exc}). Record more "
            "samples or use a smaller half_window."
        ) from exc
    return fitted, template


def _usable_bins(fitted, band) -> np.ndarray:
    frf = np.asarray(fitted.frf_)
    std = np.asarray(fitted.frf_std_)
    freqs = np.asarray(fitted.frequencies_, dtype=float)
    valid = np.asarray(getattr(fitted, "valid_", np.ones(frf.shape, bool)), bool)
    if frf.ndim != 1 or std.shape != frf.shape or freqs.shape != frf.shape:
        raise ValueError(
            "the estimator's frequencies_, frf_ and frf_std_ must be 1-D arrays of "
            f"one length. Got shapes {freqs.shape}, {frf.shape} and {std.shape}."
        )
    inside = (freqs > 0) & (freqs >= band[0]) & (freqs <= band[1])
    good = inside & valid & np.isfinite(frf) & np.isfinite(std) & (std > 0)
    n_inside = int(np.count_nonzero(inside))
    n_bad = n_inside - int(np.count_nonzero(good))
    if n_bad:
        warnings.warn(
            f"{n_bad} of {n_inside} bins have a non-finite FRF or a std that is "
            "zero, negative or NaN; they are left out of the comparison.",
            UserWarning, stacklevel=3,
        )
    bins = np.flatnonzero(good)
    needed = max(MIN_BINS, n_inside // 2)
    if bins.size < needed:
        raise ValueError(
            f"only {bins.size} of {n_inside} bins have a finite FRF and a "
            f"positive finite std; at least {needed} are needed. Check the "
            "estimator's frf_std_ (zero or NaN std), the input excitation and "
            "`band`."
        )
    return bins


def _check_band(band) -> tuple:
    if band is None:
        return (0.0, math.inf)
    try:
        low, high = (float(v) for v in band)
    except (TypeError, ValueError) as exc:
        raise TypeError(
            f"`band` must be a pair (low, high) in Hz or None. Got {band!r}."
        ) from exc
    if not (low >= 0 and high > low):
        raise ValueError(
            f"`band` must satisfy 0 <= low < high (Hz). Got {band!r}."
        )
    return (low, high)


def _resolve_sample_time(sample_time, plant, controller) -> tuple[float, str]:
    """The fast sample time and where it came from (for messages).

    Given: checked. Not given: the ``dt`` of a discrete ``plant``, else of a
    discrete ``controller``; else an error asking for it.
    """
    if sample_time is not None:
        value = check_sample_time(sample_time)
        return value, f"sample_time={value!r} s"
    check_siso_system(plant, "`plant`", discrete=False,
                      hint="stage.plant[0, 0] for y4")
    for model, name in ((plant, "`plant`"), (controller, "`controller`")):
        if model is None or not isinstance(model, control.LTI):
            continue
        dt = model.dt
        if control.isdtime(model, strict=True) and not isinstance(dt, bool):
            value = check_sample_time(dt)
            return value, f"sample_time={value!r} s (the dt of {name})"
    raise ValueError(
        "`sample_time` was not given and neither `plant` nor `controller` is a "
        "discrete model with a known dt to take it from. Pass the fast sample "
        "time in seconds, e.g. sample_time=0.5e-3."
    )


def _check_controller(controller, sample_time, source):
    if controller is None:
        return None
    check_siso_system(controller, "`controller`", discrete=False)
    if not control.isdtime(controller, strict=True):
        raise ValueError(
            "`controller` must be discrete with dt == sample_time. Got "
            f"dt={controller.dt!r}. Discretise it, e.g. "
            "control.sample_system(C, sample_time, 'tustin')."
        )
    if not math.isclose(float(controller.dt), sample_time, rel_tol=1e-9):
        raise ValueError(
            f"`controller` has dt={float(controller.dt)!r} s but {source}. Pass "
            "the controller at the fast sample time."
        )
    return control.ss(controller)


def _check_calibration(cal, n_bins):
    if not isinstance(cal, Calibration):
        raise TypeError(
            "`calibration` must be a Calibration from an earlier report "
            f"(report.calibration). Got {type(cal).__name__}."
        )
    if cal.bias.shape != (n_bins,):
        raise ValueError(
            f"`calibration` was made for {cal.bias.shape[0]} bins, these data have "
            f"{n_bins}. Reuse a calibration only with the same inputs and estimator."
        )
