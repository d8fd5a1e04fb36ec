"""``diagnose`` on 2x2 stages (issue 15 item 5, MIMO): known answers, seeded
hidden-effect runs in closed loop, and the shape-mismatch messages.

The 2x2 stage is corners 1 and 2 of the default four-corner plate
(:func:`lrmfrf.discrepancy.hidden_mimo.two_by_two_stage`), in the loop with a
diagonal lead-PID; ONE experiment of two uncorrelated multisines at 40 dB.
The rates over random stages are in ``benchmarks/generalisation_diagnose.py
--mimo``.
"""

from __future__ import annotations

import warnings

import control
import numpy as np
import pytest

from lrmfrf.discrepancy import (
    Delay,
    Gain,
    LowPass,
    MissingMode,
    ModeShift,
    diagnose,
)
from lrmfrf.discrepancy._models import (
    as_continuous_plant,
    discrete_response,
    frequency_response,
    resonances,
    to_discrete_ss,
)
from lrmfrf.discrepancy.detect import bin_power
from lrmfrf.discrepancy.effects import EffectContext, shift_mode
from lrmfrf.discrepancy.fit import closed_loop_response
from lrmfrf.discrepancy.hidden import HiddenEffect
from lrmfrf.discrepancy.hidden_mimo import (
    StageMode,
    draw_mimo_effect,
    mimo_hidden_effect_experiment,
    two_by_two_stage,
)
from lrmfrf.plants import mimo_wafer_stage, random_stage

FREQS = np.linspace(1.0, 999.0, 301)
#: A missing mode above the slow Nyquist frequency (333 Hz at F = 3).
HIDDEN_MODE = HiddenEffect(
    "missing_mode", {"frequency": 520.0, "damping": 0.01},
    {"participation": 0.3, "c": (1.2, -0.9), "b": (0.8, 1.0)},
)
HIDDEN_GAIN = HiddenEffect("gain", {"gain": 1.15})
FAST = {"calibration_runs": 6, "debias_rounds": 1}


@pytest.fixture(scope="module")
def stage():
    return two_by_two_stage(mimo_wafer_stage(downsampling_factor=3), loop="closed")


def _diagnose(experiment, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return diagnose(experiment.plant, experiment.u_h, experiment.y_l,
                        experiment.F, controller=experiment.controller, rng=3,
                        **{**FAST, **options})


def _z(frequencies, sample_time):
    return np.exp(2j * np.pi * frequencies * sample_time)


# ---------------------------------------------------------------------------
# Known answers of the MIMO model layer
# ---------------------------------------------------------------------------


def test_mimo_response_and_fractional_delay_match_python_control(stage):
    plant = as_continuous_plant(stage.plant, stage.sample_time, shape=(2, 2))
    ref = stage.plant(_z(FREQS, stage.sample_time))
    response = discrete_response(plant, FREQS, stage.sample_time)
    assert response.shape == (2, 2, FREQS.size)
    np.testing.assert_allclose(response, ref, rtol=0, atol=1e-9 * np.abs(ref).max())
    delayed = plant.with_(delay=1.3 * stage.sample_time)  # two shift stages per input
    discrete = to_discrete_ss(delayed, stage.sample_time)
    assert discrete.nstates == plant.n_states + 2 * 2
    np.testing.assert_allclose(discrete_response(delayed, FREQS, stage.sample_time),
                               discrete(_z(FREQS, stage.sample_time)),
                               atol=1e-12 * np.abs(ref).max())


def test_closed_loop_response_is_the_feedback_loop(stage):
    z = _z(FREQS, stage.sample_time)
    P = stage.plant(z)
    C = frequency_response(stage.controller, FREQS, stage.sample_time)
    assert C.shape == (2, 2, FREQS.size)
    loop = control.feedback(stage.plant, stage.controller, sign=-1)
    np.testing.assert_allclose(closed_loop_response(P, C), loop(z),
                               atol=1e-9 * np.abs(loop(z)).max())


def test_missing_mode_adds_the_rank_one_mode(stage):
    plant = as_continuous_plant(stage.plant_continuous(), stage.sample_time,
                                shape=(2, 2))
    context = EffectContext(plant, FREQS, stage.sample_time, None, None,
                            np.zeros(FREQS.size))
    (effect,) = MissingMode().expand(context)
    assert effect.nuisance_names == ("residue_0", "residue_1", "input_angle_1")
    c, angle = np.array([0.3, -0.2]), 0.7
    params = {"frequency": 520.0, "damping": 0.01, "residue_0": c[0],
              "residue_1": c[1], "input_angle_1": angle}
    b = np.array([np.cos(angle), np.sin(angle)])
    # independent: the generator's modal construction with c b^T / m
    truth = stage.plant_continuous(extra=[(520.0, 0.01, c * stage.mass, b)])
    np.testing.assert_allclose(
        discrete_response(effect.apply(plant, params), FREQS, stage.sample_time),
        control.sample_system(truth, stage.sample_time)(_z(FREQS, stage.sample_time)),
        rtol=1e-8, atol=1e-12,
    )


def test_shift_mode_keeps_the_numerator_of_a_force_to_position_mode(stage):
    plant = as_continuous_plant(stage.plant_continuous(), stage.sample_time,
                                shape=(2, 2))
    moved = list(stage.modes)
    old = moved[2]
    moved[2] = StageMode(old.frequency_hz * 1.06, 0.02, old.shape)
    shifted = shift_mode(plant, old.frequency_hz, old.damping, moved[2].frequency_hz,
                         0.02)
    truth = control.sample_system(stage.plant_continuous(moved), stage.sample_time)
    ref = truth(_z(FREQS, stage.sample_time))
    np.testing.assert_allclose(discrete_response(shifted, FREQS, stage.sample_time),
                               ref, atol=1e-9 * np.abs(ref).max())


def test_bin_power_is_the_mean_over_entries():
    w = np.arange(12.0).reshape(2, 2, 3) * (1 + 1j)
    np.testing.assert_allclose(bin_power(w), np.mean(np.abs(w) ** 2, axis=(0, 1)))
    np.testing.assert_array_equal(bin_power(w[0, 0]), np.abs(w[0, 0]) ** 2)


# ---------------------------------------------------------------------------
# Sizes of the benchmark's 2x2 stages and effects
# ---------------------------------------------------------------------------


def test_siso_sizing_sizes_modes_relative_to_the_corner_like_the_siso_stages():
    # A corner's rigid compliance is 7 / m (heave, roll and pitch); the
    # plate's corner values squared are drawn in the SISO participation
    # range (0.02-0.4, relative to 1 / m), so relative to the corner its
    # modes are 7 times weaker than a SISO stage's unless scaled.
    plate, _ = random_stage(1000, mimo=True)
    own = two_by_two_stage(plate, loop="open")
    sized = two_by_two_stage(plate, loop="open", sizing="siso")
    compliance = sized.mass * np.diag(sized.rigid)
    np.testing.assert_allclose(compliance, [7.0, 7.0], rtol=1e-9)
    assert len(sized.modes) == len(own.modes) > 0
    for old, new in zip(own.modes, sized.modes, strict=True):
        assert new.frequency_hz == old.frequency_hz
        relative = np.square(new.shape) / compliance
        np.testing.assert_allclose(relative, np.square(old.shape), rtol=1e-9)
        assert np.all((relative > 0.0195) & (relative < 0.4))
    # a missing mode: the largest diagonal residue relative to the corner is
    # the participation, as a SISO missing mode's participation / m
    effect = draw_mimo_effect("missing_mode", np.random.default_rng(5), sized)
    residue = np.abs(np.multiply(effect.extra["c"], effect.extra["b"]))
    assert np.max(residue / compliance) == pytest.approx(
        effect.extra["participation"], rel=1e-9)
    same = draw_mimo_effect("missing_mode", np.random.default_rng(5), own)
    assert same.parameters == effect.parameters  # same draw, other size
    assert np.max(np.abs(np.multiply(same.extra["c"], same.extra["b"]))
                  / compliance) < effect.extra["participation"] / 5
    with pytest.raises(ValueError, match="`sizing`"):
        two_by_two_stage(plate, loop="open", sizing="large")


@pytest.mark.parametrize("seed", [1007, 2001])
def test_the_symmetric_closed_loop_has_the_random_stages_margins(seed):
    # item 1's margins (>= 30 deg, gain margin >= 2) for each loop, broken
    # with the other one closed; a stability check alone let these SISO-sized
    # stages through with 26.7 deg (gain margin 1.59) and 18.2 deg
    from lrmfrf.plants.loops import loop_margins

    plate, draw = random_stage(seed, mimo=True)
    stage = two_by_two_stage(plate, downsampling_factor=draw.downsampling_factor,
                             sizing="siso")
    plant, controller = stage.plant, stage.controller
    closed = control.feedback(plant, controller, sign=-1)
    assert np.max(np.abs(np.linalg.eigvals(closed.A))) < 1.0
    zero = control.ss(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)),
                      [[0.0]], plant.dt)
    for j in range(2):
        other = [zero, zero]
        other[1 - j] = controller[1 - j, 1 - j]
        half_closed = control.feedback(plant, control.append(*other), sign=-1)
        margins = loop_margins(half_closed[j, j], controller[j, j])
        assert margins.phase_margin >= 30.0
        assert margins.gain_margin >= 2.0


def test_a_drawn_effect_that_destabilises_the_loop_is_drawn_again():
    # the SISO generator redraws such effects; this 2x2 stage's first delay
    # draw (0.525 ms) makes its closed loop unstable
    plate, draw = random_stage(1003, mimo=True)
    stage = two_by_two_stage(plate, downsampling_factor=draw.downsampling_factor,
                             sizing="siso")
    first = draw_mimo_effect("delay", np.random.default_rng(100302), stage)
    experiment = mimo_hidden_effect_experiment("delay", stage=stage, rng=100302)
    assert experiment.effects[0].parameters["delay"] < first.parameters["delay"]
    poles = np.linalg.eigvals(experiment.true_system.A)
    assert np.max(np.abs(poles)) < 1.0
    unstable = HiddenEffect("delay", first.parameters)
    with pytest.raises(RuntimeError, match="unstable in 3 draws"):
        mimo_hidden_effect_experiment(unstable, stage=stage, rng=1, max_draws=3)


# ---------------------------------------------------------------------------
# Seeded hidden-effect runs (closed loop, one experiment, 40 dB)
# ---------------------------------------------------------------------------


def test_nothing_hidden_names_nothing(stage):
    experiment = mimo_hidden_effect_experiment(None, stage=stage, rng=7)
    assert experiment.u_h.shape == (1, 2, 1200)
    assert experiment.y_l.shape == (1, 2, 400)
    report = _diagnose(experiment)
    assert report.findings == []
    assert report.measured.shape[:2] == (2, 2)
    assert report.calibration.n_entries == 4
    assert 0.7 < report.gap_before < 1.3


def test_hidden_missing_mode_is_named(stage):
    experiment = mimo_hidden_effect_experiment(HIDDEN_MODE, stage=stage, rng=7)
    report = _diagnose(experiment)
    named = [f for f in report.findings if f.effect == "missing_mode"]
    assert [f.effect for f in report.findings] == ["missing_mode"], report.findings
    assert named[0].parameters["frequency"] == pytest.approx(520.0, rel=0.02)
    assert report.gap_after < 1.3 < report.gap_before


def test_hidden_gain_is_named(stage):
    experiment = mimo_hidden_effect_experiment(HIDDEN_GAIN, stage=stage, rng=7)
    report = _diagnose(experiment)
    assert [f.effect for f in report.findings] == ["gain"], report.findings
    assert report.findings[0].parameters["gain"] == pytest.approx(1.15, rel=0.02)


# ---------------------------------------------------------------------------
# Shape mismatches between models and records
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def records(stage):
    experiment = mimo_hidden_effect_experiment(None, stage=stage, rng=1)
    return experiment.u_h, experiment.y_l


def test_mimo_plant_with_siso_records_is_refused(stage, records):
    u, y = records
    with pytest.raises(ValueError, match="must be SISO"):
        diagnose(stage.plant, u[:, :1], y[:, :1], 3, controller=stage.controller)


def test_plant_of_other_dimensions_than_the_records_is_refused(stage, records):
    u, y = records
    plant = control.append(stage.plant, stage.plant[0, 0])  # 3 x 3
    with pytest.raises(ValueError, match="has 3 output.*records have 2 output"):
        diagnose(plant, u, y, 3, controller=stage.controller)


def test_controller_of_wrong_dimensions_is_refused(stage, records):
    u, y = records
    with pytest.raises(ValueError, match="must have 2 outputs and 2 inputs"):
        diagnose(stage.plant, u, y, 3, controller=stage.controller[0, :])


def test_catalogue_effects_are_the_mimo_ones(stage):
    plant = as_continuous_plant(stage.plant_continuous(), stage.sample_time,
                                shape=(2, 2))
    for effect, params in ((Gain(), {"gain": 2.0}), (Delay(), {"delay": 1e-3}),
                           (LowPass(), {"cutoff": 200.0})):
        changed = effect.apply(plant, params)
        assert (changed.n_outputs, changed.n_inputs) == (2, 2)
    context = EffectContext(plant, FREQS, stage.sample_time, None, None,
                            np.zeros(FREQS.size), resonances=resonances(plant))
    shifts = ModeShift().expand(context)
    assert {round(s.target.frequency) for s in shifts} == {
        round(m.frequency_hz) for m in stage.modes}


def test_report_of_a_mimo_diagnosis(stage):
    import json

    import matplotlib

    matplotlib.use("Agg")
    experiment = mimo_hidden_effect_experiment(None, stage=stage, rng=7)
    report = _diagnose(experiment, calibration_runs=2, debias_rounds=0)
    assert report.std.shape == report.measured.shape == report.model_after.shape
    assert report.spectrum_before.shape == report.frequencies.shape
    data = json.loads(json.dumps(report.to_dict()))
    assert data["calibration"]["n_entries"] == 4
    assert "gap" in report.summary()
    fig, axes = report.plot(entry=(1, 0))
    assert "entry y1/u0" in axes[0].get_title()
    with pytest.raises(ValueError, match="within \\(2, 2\\)"):
        report.plot(entry=(2, 0))


# ---------------------------------------------------------------------------
# Known answers of the MIMO search internals (independent constructions)
# ---------------------------------------------------------------------------


#: A static input coupling and controller mixing that make the 2x2 loop
#: generic: the stage itself is symmetric (collocated, P = P^T) and its
#: controller a scalar times the identity (C P = P C), so transposed or
#: swapped factors (S_o for S_i, (I + C P)^-1 P for P (I + C P)^-1, a left for
#: a right singular vector) give the same values on it and no test of it can
#: see them.
COUPLING = np.array([[1.0, 0.25], [-0.1, 0.8]])
MIXING = np.array([[0.9, 0.15], [-0.05, 1.1]])


def _static(matrix, dt=None):
    return control.ss(np.zeros((0, 0)), np.zeros((0, 2)), np.zeros((2, 0)), matrix,
                      *(() if dt is None else (dt,)))


@pytest.fixture(scope="module")
def skewed(stage):
    """``(plant, controller)``: the stage's plant times COUPLING (continuous)
    and MIXING times its controller (a stable loop, not symmetric)."""
    plant = control.ss(stage.plant_continuous()) * _static(COUPLING)
    controller = _static(MIXING, stage.sample_time) * stage.controller
    loop = control.feedback(control.sample_system(plant, stage.sample_time),
                            controller, sign=-1)
    assert np.max(np.abs(np.linalg.eigvals(loop.A))) < 1.0
    return plant, controller


def _loop_problem(stage, skewed):
    """The closed-loop FitProblem of the skewed 2x2 loop on FREQS."""
    from lrmfrf.discrepancy.fit import FitProblem

    plant = as_continuous_plant(skewed[0], stage.sample_time, shape=(2, 2))
    P = discrete_response(plant, FREQS, stage.sample_time)
    C = frequency_response(skewed[1], FREQS, stage.sample_time)
    assert np.abs(P - P.transpose(1, 0, 2)).max() > 0.1 * np.abs(P).max()
    shape = (2, 2, FREQS.size)
    problem = FitProblem(FREQS, closed_loop_response(P, C), np.ones(shape),
                         stage.sample_time, C, np.zeros(shape, complex),
                         np.ones(shape), 1.0)
    return plant, P, problem


def test_closed_loop_response_of_a_skewed_loop(stage, skewed):
    """P (I + C P)^-1 against python-control's feedback on a loop where the
    order of the factors matters."""
    _, P, problem = _loop_problem(stage, skewed)
    loop = control.feedback(control.sample_system(skewed[0], stage.sample_time),
                            skewed[1], sign=-1)
    ref = loop(_z(FREQS, stage.sample_time))
    np.testing.assert_allclose(problem.measured, ref, atol=1e-9 * np.abs(ref).max())


def test_plant_level_sensitivities_are_the_loop_derivative(stage, skewed):
    """dG = S_o dP S_i for G = P (I + C P)^-1 (central differences along a
    random complex direction), and the measured plant G (I - C G)^-1 is P."""
    from lrmfrf.discrepancy._search import _plant_level

    _, P, problem = _loop_problem(stage, skewed)
    (S_o, S_i), plant_seen = _plant_level(problem, P)
    rng = np.random.default_rng(0)
    dP = rng.standard_normal(P.shape) + 1j * rng.standard_normal(P.shape)
    h = 1e-6 * np.abs(P).max(axis=(0, 1))  # per bin: P spans decades
    C = problem.controller
    numeric = (closed_loop_response(P + h * dP, C)
               - closed_loop_response(P - h * dP, C)) / (2 * h)
    linear = np.einsum("iak,abk,bjk->ijk", S_o, dP, S_i)
    scale = np.abs(linear).max(axis=(0, 1))
    assert np.max(np.abs(linear - numeric) / scale) < 1e-6
    np.testing.assert_allclose(plant_seen, P, atol=1e-12 * np.abs(P).max())


def test_mode_shape_guess_is_the_rank_one_residue(stage, skewed):
    """The missing mode's starting shape c b^T is the residue of a small
    rank-one mode seen through the closed loop (linearised: 1e-4 of the
    plant's scale, so the guess is exact to ~1e-4)."""
    from lrmfrf.discrepancy._search import _plant_level
    from lrmfrf.discrepancy.effects import _mode_shape_guess, _unit_vector, add_mode

    plant, P, problem = _loop_problem(stage, skewed)
    sensitivity, _ = _plant_level(problem, P)
    c, b = np.array([0.8, -1.3]) * 1e-4, _unit_vector([2.0])  # b = (cos 2, sin 2)
    with_mode = add_mode(plant, 520.0, 0.01, c, 0.0, input_vector=b)
    residual = closed_loop_response(
        discrete_response(with_mode, FREQS, stage.sample_time), problem.controller
    ) - problem.measured
    std = np.full(residual.shape, 1e-3)
    context = EffectContext(plant, FREQS, stage.sample_time, None, None,
                            np.zeros(FREQS.size), sensitivity=sensitivity,
                            residual=residual, std=std)
    c_guess, b_guess = _mode_shape_guess(context, 520.0, 0.01)
    assert np.linalg.norm(b_guess) == pytest.approx(1.0)
    np.testing.assert_allclose(np.outer(c_guess, b_guess), np.outer(c, b),
                               rtol=0, atol=1e-3 * np.abs(c).max())


def test_series_effects_filter_every_input_alike(stage):
    """Low-pass and model error: the plant times the same SISO filter on each
    input channel (python-control: plant * append(H, H))."""
    from lrmfrf.discrepancy import ModelError
    from lrmfrf.discrepancy._models import ContinuousPlant

    plant = as_continuous_plant(stage.plant_continuous(), stage.sample_time,
                                shape=(2, 2))
    tau = 1.0 / (2 * np.pi * 200.0)
    lag = control.ss(control.tf([1.0], [tau, 1.0]))
    params = {"zero_frequency": 700.0, "zero_damping": 0.2,
              "pole_frequency": 800.0, "pole_damping": 0.4}
    unit = ContinuousPlant(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)),
                           np.ones((1, 1)))
    one = ModelError().apply(unit, params)  # the SISO filter alone
    H = control.ss(one.A, one.B, one.C, one.D)
    z = _z(FREQS, stage.sample_time)
    for effect, p, filt in ((LowPass(), {"cutoff": 200.0}, lag),
                            (ModelError(), params, H)):
        truth = control.sample_system(
            control.ss(stage.plant_continuous()) * control.append(filt, filt),
            stage.sample_time)
        ref = truth(z)
        np.testing.assert_allclose(
            discrete_response(effect.apply(plant, p), FREQS, stage.sample_time),
            ref, atol=1e-9 * np.abs(ref).max())


def test_shift_mode_numerator_with_a_velocity_term(stage):
    """A mode with b1 = C_m B_m != 0 (a velocity output): shift_mode gives the
    numerator its docstring says, s b1 / alpha + b0 - (beta / alpha) b1 over
    the new pole pair (alpha = Im p' / Im p, beta = Re p' - alpha Re p)."""
    w0, z0, w1, z1 = 2 * np.pi * 400.0, 0.01, 2 * np.pi * 450.0, 0.03
    b = np.array([0.7, 0.3])
    position, velocity = np.array([16.0, -6.4]), np.array([0.2, 0.5])

    def mode(w, zeta, pos, vel):  # (s vel + pos) b^T / (s^2 + 2 zeta w s + w^2)
        return control.ss(np.array([[0.0, 1.0], [-w * w, -2 * zeta * w]]),
                          np.vstack([np.zeros(2), b]), np.column_stack([pos, vel]),
                          np.zeros((2, 2)))

    rest = control.ss(stage.plant_continuous())
    moving = mode(w0, z0, position, velocity)
    plant = as_continuous_plant(control.parallel(rest, moving), stage.sample_time,
                                shape=(2, 2))
    shifted = shift_mode(plant, 400.0, z0, 450.0, z1)
    p = complex(-z0 * w0, w0 * np.sqrt(1 - z0**2))
    q = complex(-z1 * w1, w1 * np.sqrt(1 - z1**2))
    alpha = q.imag / p.imag
    beta = q.real - alpha * p.real
    truth = control.parallel(rest, mode(w1, z1, position - beta / alpha * velocity,
                                         velocity / alpha))
    ref = control.sample_system(truth, stage.sample_time)(_z(FREQS, stage.sample_time))
    np.testing.assert_allclose(discrete_response(shifted, FREQS, stage.sample_time),
                               ref, atol=1e-8 * np.abs(ref).max())


def test_a_candidate_that_cannot_be_applied_is_dropped_not_raised(stage):
    """fit_candidate on a base where the effect cannot be applied at all (a
    mode shift aimed at the open-loop stage's suspension, a repeated pole
    pair: every start costs the penalty) returns None, so the search drops
    it. It built the plant at the optimum outside the residual's guard and
    raised "could not isolate the mode ... (repeated pole)" out of diagnose
    (7a11b03, which had no test)."""
    from lrmfrf.discrepancy._models import Resonance
    from lrmfrf.discrepancy.fit import FitProblem, fit_candidate

    open_stage = two_by_two_stage(mimo_wafer_stage(downsampling_factor=3),
                                  loop="open")
    T = open_stage.sample_time
    nominal = as_continuous_plant(open_stage.plant_continuous(), T, shape=(2, 2))
    suspension = [r for r in resonances(nominal) if abs(r.frequency - 5.0) < 0.01]
    assert len(suspension) == 2  # the same pole pair twice (x and y corners)
    measured = discrete_response(nominal, FREQS, T)
    shape = measured.shape
    problem = FitProblem(FREQS, measured, 0.01 * np.abs(measured), T, None,
                         np.zeros(shape, complex), np.ones(shape), 1.0)
    context = EffectContext(nominal, FREQS, T, np.ones(shape), np.ones(shape),
                            np.zeros(FREQS.size), resonances=resonances(nominal))
    target = Resonance(5.0, 0.1, -1)
    with pytest.raises(ValueError, match="repeated pole"):
        ModeShift(target=target).apply(nominal, {"frequency": 5.2, "damping": 0.1})
    assert fit_candidate(problem, nominal, [], [], ModeShift(target=target),
                         context) is None
