"""Tests of the model-vs-measurement workflow (lrmfrf.discrepancy).

Fast tier: known answers of the model surgery and the exact ZOH with
fractional delay (checked against an independent fine-rate lifting), the
calibrated tests on synthetic residuals, one seeded hidden-effect run per
effect class on the wafer stage, the report, and every bad-input message.
The detection statistics (>= 100 runs per class) are in
``benchmarks/discrepancy.py``; a smaller slow version is marked ``slow``.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import control
import numpy as np
import pytest

import lrmfrf
from lrmfrf import LRMBeyondNyquist
from lrmfrf.discrepancy import (
    Effect,
    Gain,
    LowPass,
    ModeShift,
    default_effects,
    diagnose,
)
from lrmfrf.discrepancy._models import (
    ContinuousPlant,
    as_continuous_plant,
    discrete_response,
    frequency_response,
    resonances,
    to_discrete_ss,
)
from lrmfrf.discrepancy.detect import (
    _coloured_noise,
    _inflation,
    discrepancy_spectrum,
    global_test,
    uncalibrated,
)
from lrmfrf.discrepancy.effects import add_mode, split_mode
from lrmfrf.discrepancy.hidden import (
    HiddenEffect,
    _lifted_zoh,
    _true_plant,
    hidden_effect_experiment,
    score,
)
from lrmfrf.plants import wafer_stage
from lrmfrf.signals import multisine
from lrmfrf.simulate import simulate

TS = 0.5e-3
FREQS = np.linspace(1.0, 999.0, 257)


@pytest.fixture(scope="module")
def stage():
    return wafer_stage()


@pytest.fixture(scope="module")
def nominal(stage):
    return as_continuous_plant(stage.plant[0, 0], TS)


def _relative(a, b):
    return float(np.max(np.abs(a - b) / np.abs(b)))


# ---------------------------------------------------------------------------
# Models: inverse ZOH, exact ZOH with fractional delay, model surgery
# ---------------------------------------------------------------------------


def test_inverse_zoh_recovers_the_continuous_plant(stage, nominal):
    # ZOH of the recovered continuous model reproduces the discrete plant, and
    # its response equals the ZOH of the original continuous plant.
    direct = frequency_response(stage.plant[0, 0], FREQS, TS)
    assert _relative(discrete_response(nominal, FREQS, TS), direct) < 1e-10
    original = as_continuous_plant(stage.plant_continuous[0, 0], TS)
    assert _relative(discrete_response(original, FREQS, TS), direct) < 1e-10


@pytest.mark.parametrize("delay_samples", [0.0, 0.2, 1.0, 1.35, 2.75])
def test_fractional_delay_zoh_matches_independent_lifting(stage, delay_samples):
    # Two independent constructions of the exact ZOH of a delayed plant: the
    # matrix-exponential integrals (workflow) and the sum over 20 fine ZOH
    # steps (generator). Delays are multiples of Ts/20 so both are exact.
    plant = stage.plant_continuous[0, 0]
    delay = delay_samples * TS
    lifted = _lifted_zoh(control.ss(plant), TS, delay)
    ours = as_continuous_plant(plant, TS).with_(delay=delay)
    assert _relative(discrete_response(ours, FREQS, TS),
                     frequency_response(lifted, FREQS, TS)) < 1e-8
    # and the state-space realisation (shift register) has the same response
    assert _relative(frequency_response(to_discrete_ss(ours, TS), FREQS, TS),
                     discrete_response(ours, FREQS, TS)) < 1e-10


def test_integer_delay_is_a_pure_shift(nominal):
    z = np.exp(2j * np.pi * FREQS * TS)
    delayed = discrete_response(nominal.with_(delay=2 * TS), FREQS, TS)
    assert _relative(delayed, discrete_response(nominal, FREQS, TS) * z**-2) < 1e-12


def test_split_and_add_mode_is_identity(nominal):
    base = discrete_response(nominal, FREQS, TS)
    for mode in resonances(nominal):
        rest, b1, b0 = split_mode(nominal, mode.frequency, mode.damping)
        rebuilt = add_mode(rest, mode.frequency, mode.damping, b0, b1)
        assert _relative(discrete_response(rebuilt, FREQS, TS), base) < 1e-9


def test_resonances_are_the_stage_modes(stage, nominal):
    found = [m.frequency for m in resonances(nominal)]
    expected = sorted(stage.resonance_frequencies_hz)
    np.testing.assert_allclose(found, expected, rtol=1e-9)
    np.testing.assert_allclose([m.damping for m in resonances(nominal)],
                               [m.damping for m in sorted(stage.modes,
                                key=lambda m: m.frequency_hz)], rtol=1e-6)


def test_mode_shift_equals_the_shifted_true_plant(stage, nominal):
    # the generator moves mode 2 in the physical model; the catalogue moves
    # the pole pair of the (inverse-ZOH) model keeping its numerator
    truth = HiddenEffect("mode_shift", {"frequency": 440.0 * 1.06, "damping": 0.02},
                         {"mode_index": 2})
    true_plant = _true_plant(stage, (truth,))
    target = [m for m in resonances(nominal) if abs(m.frequency - 440) < 1][0]
    shifted = ModeShift(target=target).apply(nominal, truth.parameters)
    assert _relative(discrete_response(shifted, FREQS, TS),
                     frequency_response(true_plant, FREQS, TS)) < 1e-8


def test_low_pass_and_gain_known_answers(stage, nominal):
    cutoff = 800.0
    series = control.tf([1.0], [1 / (2 * np.pi * cutoff), 1.0])
    expected = control.sample_system(stage.plant_continuous[0, 0] * series, TS, "zoh")
    got = LowPass().apply(nominal, {"cutoff": cutoff})
    assert _relative(discrete_response(got, FREQS, TS),
                     frequency_response(expected, FREQS, TS)) < 1e-9
    gained = Gain().apply(nominal, {"gain": 1.2})
    assert _relative(discrete_response(gained, FREQS, TS),
                     1.2 * discrete_response(nominal, FREQS, TS)) < 1e-12


def test_discrete_plant_with_wrong_sample_time_is_rejected(stage):
    with pytest.raises(ValueError, match="sample time dt=0.001"):
        as_continuous_plant(control.sample_system(stage.plant_continuous[0, 0],
                                                  1e-3), TS)


def test_discrete_plant_without_zoh_equivalent_is_rejected():
    plant = control.ss([[-0.5]], [[1.0]], [[1.0]], [[0.0]], TS)
    with pytest.raises(ValueError, match="non-positive real axis"):
        as_continuous_plant(plant, TS)


# ---------------------------------------------------------------------------
# Calibrated tests on synthetic residuals
# ---------------------------------------------------------------------------


def test_global_test_false_alarm_rate_independent_bins():
    # |w|^2 ~ Exp(1) independent: the family-wise false-alarm rate of the
    # combined (mean + spectrum max) test must be about alpha or less.
    # 2000 draws: the binomial std of a 1 % rate is 0.22 %; allow 2 %.
    rng = np.random.default_rng(0)
    cal = uncalibrated(400, smoothing_bins=9, inflation=1.0)
    alarms = [global_test(rng.exponential(size=400), cal, 0.01).significant
              for _ in range(2000)]
    assert np.mean(alarms) < 0.02


def test_inflation_measures_correlation():
    # Moving sum of L independent complex normals: correlation rho(l) =
    # (L - |l|) / L, and the variance of a band mean of |w|^2 is inflated by
    # c = sum_l rho(l)^2 (= 4.06 for L = 6) for bands much wider than L.
    rng = np.random.default_rng(1)
    L, K, runs = 6, 600, 200
    z = (rng.standard_normal((runs, K + L)) + 1j * rng.standard_normal((runs, K + L)))
    w = np.stack([np.convolve(row, np.ones(L), "valid")[:K] for row in z])
    w2 = np.abs(w) ** 2
    w2 /= w2.mean()
    c = _inflation(w2, 8)
    lags = np.arange(-L + 1, L)
    expected = float(np.sum(((L - np.abs(lags)) / L) ** 2))
    # 200 runs x 8 bands: relative std of the pooled variance about 4 %
    assert abs(c / expected - 1) < 0.15
    cal = uncalibrated(K, smoothing_bins=9, inflation=c)
    alarms = [global_test(row, cal, 0.05).significant for row in w2]
    assert np.mean(alarms) < 0.1


def test_coloured_noise_has_the_requested_spectrum():
    rng = np.random.default_rng(2)
    M = 400
    std = np.linspace(1.0, 3.0, M // 2 + 1)
    noise = _coloured_noise(std, M, 2000, rng)
    power = np.mean(np.abs(np.fft.fft(noise, axis=1)[:, : M // 2 + 1]) ** 2, axis=0)
    # 2000 records: relative std of each mean power is 1/sqrt(2000) = 2.2 %
    np.testing.assert_allclose(power[1:-1], std[1:-1] ** 2, rtol=0.12)


# ---------------------------------------------------------------------------
# Hidden effects on the wafer stage (fast tier: one seed per class)
# ---------------------------------------------------------------------------


def _run(hidden, seed, **kwargs):
    experiment = hidden_effect_experiment(hidden, rng=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = diagnose(
            experiment.plant, experiment.u_h, experiment.y_l, experiment.F,
            sample_time=experiment.sample_time, controller=experiment.controller,
            calibration_runs=6, rng=seed, **kwargs,
        )
    return experiment, report, score(experiment, report)


def test_generator_no_effect_is_the_nominal_loop(stage):
    experiment = hidden_effect_experiment(None, rng=0, stage=stage)
    assert experiment.effects == ()
    assert _relative(frequency_response(experiment.true_system, FREQS, TS),
                     frequency_response(stage.G_y4, FREQS, TS)) < 1e-8
    assert experiment.u_h.shape == (4, 1, 1200)
    assert experiment.y_l.shape == (4, 1, 400)
    assert np.isclose(experiment.u_h[0].std(), 1.44)


def test_no_effect_gives_no_findings():
    _, report, result = _run(None, 3)
    assert report.findings == []
    assert 0.7 < report.gap_before < 1.3
    assert report.gap_after == report.gap_before
    assert not result["any_finding"]


@pytest.mark.parametrize(
    "kind, seed",
    [("gain", 11), ("delay", 12), ("low_pass", 13), ("mode_shift", 14),
     ("missing_mode_high", 15)],
)
def test_one_hidden_effect_is_named_with_accurate_parameters(kind, seed):
    experiment, report, result = _run(kind, seed)
    assert result["exact"], report.summary()
    assert result["parameters_ok"], (result["errors"], report.summary())
    assert result["gap_ok"], report.summary()
    if kind == "missing_mode_high":
        # a mode above the slow Nyquist frequency, found from slow-rate data
        assert report.findings[0].parameters["frequency"] > report.slow_nyquist


def test_two_hidden_effects_are_both_named():
    _, report, result = _run(("delay", "missing_mode"), 21)
    assert result["all_named"], report.summary()


def test_custom_effect_joins_the_catalogue():
    # An open catalogue: a user effect (a sign-preserving output scaling named
    # "sensor_scale") replaces the built-in gain and is found instead of it.
    class SensorScale(Gain):
        name = "sensor_scale"
        parameter_names = ("scale",)

        def initial_guesses(self, context):
            return [{"scale": g["gain"]} for g in super().initial_guesses(context)]

        def bounds(self, context):
            return {"scale": (0.05, 20.0)}

        def apply(self, plant, params):
            return super().apply(plant, {"gain": params["scale"]})

        def describe(self, params):
            return f"sensor scale {params['scale']:.4g}"

    catalogue = [SensorScale()] + [e for e in default_effects()
                                   if not isinstance(e, Gain)]
    truth = HiddenEffect("gain", {"gain": 1.15})
    _, report, _ = _run((truth,), 31, effects=catalogue)
    assert [f.effect for f in report.findings] == ["sensor_scale"]
    assert abs(report.findings[0].parameters["scale"] / 1.15 - 1) < 0.02


def test_two_hidden_effects_gain_and_low_pass():
    _, report, result = _run(("gain", "low_pass"), 22)
    assert result["all_named"], report.summary()


def test_shift_of_the_sharpest_mode():
    # The 235 Hz mode (0.8 % damping, participation 0.06) moved down 4 %. The
    # LRM estimate flattens so sharp a peak (noise-induced bias), so a fit to
    # the raw FRF tends to put the damping high (up to +33 % in benchmark
    # runs); the bias-corrected refit (debias_rounds) reduces that. The
    # nominal model's calibration would count its own bias at 235 Hz as noise
    # and understate gap_before ~2x; both gaps use the final calibration.
    truth = HiddenEffect("mode_shift", {"frequency": 235.0 * 0.96, "damping": 0.008},
                         {"mode_index": 1})
    _, report, result = _run((truth,), 51)
    assert result["exact"] and result["gap_ok"], report.summary()
    assert result["errors"]["mode_shift.frequency"] < 0.005
    assert result["errors"]["mode_shift.damping"] < 0.15, result["errors"]


def test_equivalent_effects_are_reported_ambiguous():
    # Two catalogue entries that are the same model change cannot be told
    # apart: the step is "ambiguous", both are listed, nothing is added.
    class Scale(Gain):
        name = "scale"

    truth = HiddenEffect("gain", {"gain": 1.15})
    _, report, _ = _run((truth,), 32, effects=[Gain(), Scale()])
    assert report.effects == ["ambiguous"], report.summary()
    assert "gain" in report.findings[0].description
    assert "scale" in report.findings[0].description
    assert report.gap_after == report.gap_before
    assert _relative(frequency_response(report.updated_plant, FREQS, TS),
                     frequency_response(report.plant, FREQS, TS)) < 1e-9


def test_unnamed_model_error_when_the_catalogue_has_nothing():
    # An empty catalogue: the hidden 600 Hz low-pass is not named but fitted by
    # the unnamed second-order model error, which closes the gap.
    truth = HiddenEffect("low_pass", {"cutoff": 600.0})
    _, report, result = _run((truth,), 33, effects=[])
    assert report.effects == ["model_error"], report.summary()
    assert set(report.findings[0].parameters) == {
        "zero_frequency", "zero_damping", "pole_frequency", "pole_damping"}
    assert report.gap_before > 5 and report.gap_after < 1.3


def test_open_loop_without_controller():
    # No controller: the measured system is the plant. A stable, lightly
    # damped plant (open-loop experiment) given continuous (ZOH-discretised
    # by diagnose) with a hidden input delay of 0.35 ms = 0.7 samples.
    Ts = 0.5e-3
    w = 2 * np.pi * 300.0
    model = control.tf([w**2], [1.0, 2 * 0.05 * w, w**2])
    truth = _lifted_zoh(control.ss(model), Ts, 0.35e-3)
    rng = np.random.default_rng(8)
    u = np.stack([multisine(1200, rms=1.0, rng=rng) for _ in range(2)])
    y = np.stack([simulate(truth, ui, 3, snr_db=40, rng=rng).y_l for ui in u])
    u, y = list(u), list(y)  # two experiments (a 2-D array is one record)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = diagnose(model, u, y, 3, sample_time=Ts, calibration_runs=6,
                          rng=8)
    assert not report.closed_loop
    assert report.effects == ["delay"], report.summary()
    assert abs(report.findings[0].parameters["delay"] / 0.35e-3 - 1) < 0.05
    assert report.gap_after <= 1.3 and report.gap_before / report.gap_after >= 3


def test_redundant_effect_is_pruned_after_the_joint_refit(nominal):
    # A gain accepted early (standing in for something found later) that the
    # joint model no longer needs (gain 1, drop-one p ~ 1) is removed; the
    # delay that explains the data is kept and refitted.
    from lrmfrf.discrepancy._search import _context, _prune
    from lrmfrf.discrepancy.effects import Delay
    from lrmfrf.discrepancy.fit import FitProblem

    rng = np.random.default_rng(4)
    truth = Delay().apply(nominal, {"delay": 0.3e-3})
    G = discrete_response(truth, FREQS, TS)
    std = 0.01 * np.abs(G)
    noise = std * (rng.standard_normal(FREQS.size)
                   + 1j * rng.standard_normal(FREQS.size)) / np.sqrt(2)
    problem = FitProblem(frequencies=FREQS, measured=G + noise, std=std,
                         sample_time=TS, controller=None,
                         bias=np.zeros(FREQS.size, complex),
                         scale=np.ones(FREQS.size), inflation=1.0)
    accepted = [Gain(), Delay()]
    params = [{"gain": 1.0}, {"delay": 0.29e-3}]
    steps = [{"name": "gain"}, {"name": "delay"}]
    cal = uncalibrated(FREQS.size)
    context = _context(problem, nominal, cal)
    current, params, _ = _prune(problem, nominal, accepted, params, steps,
                                nominal, None, context, 1e-3)
    assert [e.name for e in accepted] == ["delay"]
    assert steps == [{"name": "delay"}]
    assert abs(params[0]["delay"] / 0.3e-3 - 1) < 1e-3
    # an effect that is needed is never pruned
    accepted = [Gain(), Delay()]
    params = [{"gain": 1.1}, {"delay": 0.3e-3}]
    truth2 = Gain().apply(truth, {"gain": 1.1})
    problem.measured = discrete_response(truth2, FREQS, TS) + 1.1 * noise
    _prune(problem, nominal, accepted, params, [{}, {}], nominal, None, context,
           1e-3)
    assert [e.name for e in accepted] == ["gain", "delay"]


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["gain", "delay", "low_pass", "missing_mode",
                                  "mode_shift"])
def test_hidden_effect_statistics_small(kind):
    # 10 seeded runs per class; issue 6 asks >= 90 % over >= 100 runs (see the
    # benchmark). With 10 runs, >= 8 right keeps a 90 %-rate method passing
    # with probability 0.93.
    right = sum(_run(kind, 100 + s)[2]["exact"] for s in range(10))
    assert right >= 8


@pytest.mark.slow
def test_no_effect_false_alarms_small():
    # 20 runs; at a true rate of 5 %, P(more than 3 alarms) = 1.6 %.
    alarms = sum(_run(None, 200 + s)[2]["any_finding"] for s in range(20))
    assert alarms <= 3


# ---------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def delay_report():
    truth = HiddenEffect("delay", {"delay": 0.3e-3})
    return _run((truth,), 41)[1]


def test_report_contents(delay_report):
    report = delay_report
    assert report.effects == ["delay"]
    finding = report.findings[0]
    assert set(finding.parameters) == {"delay"}
    low, high = finding.confidence_intervals["delay"]
    assert low < finding.parameters["delay"] < high
    assert finding.band[0] < finding.band[1]
    assert finding.p_value < 1e-6
    assert report.updated_plant.dt == TS
    # the updated model's response is the one the gap_after was computed with
    G = frequency_response(report.updated_plant, report.frequencies, TS)
    C = frequency_response(wafer_stage().controller, report.frequencies, TS)
    seen = G / (1 + C * G)
    gap = np.sqrt(np.mean(np.abs(report.measured - seen) ** 2 / report.std**2))
    assert math.isclose(gap, report.gap_after, rel_tol=1e-6)
    # gap_before: the original model, measured with the same std
    G0 = frequency_response(report.plant, report.frequencies, TS)
    seen0 = G0 / (1 + C * G0)
    gap0 = np.sqrt(np.mean(np.abs(report.measured - seen0) ** 2 / report.std**2))
    assert math.isclose(gap0, report.gap_before, rel_tol=1e-6)


def test_report_summary_and_json(delay_report):
    text = delay_report.summary()
    assert "delay" in text and "gap" in text
    data = json.loads(json.dumps(delay_report.to_dict()))
    assert data["findings"][0]["effect"] == "delay"
    assert set(data["findings"][0]["parameters"]) == {"delay"}


def test_report_plot(delay_report):
    """(fig, axes) like plot_frf; dB with units; continuous phase (item 16)."""
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = delay_report.plot(units="m/N")
    assert isinstance(fig, matplotlib.figure.Figure) and axes.shape == (3,)
    mag, phase, disc = axes
    assert mag.get_ylabel() == "Magnitude [dB re 1 m/N]"
    assert phase.get_ylabel() == "Phase [deg]"
    assert disc.get_xlabel() == "Frequency [Hz]"
    labels = mag.get_legend().get_texts()
    nyquist = f"slow Nyquist {delay_report.slow_nyquist:.4g} Hz"
    assert nyquist in [t.get_text() for t in labels]
    # magnitude in dB: the measured points are 20 log10 |G|
    measured = mag.get_lines()[0]
    np.testing.assert_allclose(measured.get_ydata(),
                               20 * np.log10(np.abs(delay_report.measured)),
                               rtol=1e-12)
    # the phase of both models is continuous: their wrapped phase jumps by
    # about 360 deg; drawn, no step between neighbouring bins is a wrap, and
    # the curves leave (-180, 180]
    models = (delay_report.model_before, delay_report.model_after)
    for line, model in zip(phase.get_lines()[1:3], models, strict=True):
        assert np.abs(np.diff(np.degrees(np.angle(model)))).max() > 300.0
        drawn = line.get_ydata()
        assert np.abs(np.diff(drawn)).max() < 180.0
        assert drawn.min() < -180.0
    # the measured phase lies on the updated model's branch
    gap = phase.get_lines()[0].get_ydata() - phase.get_lines()[2].get_ydata()
    assert np.all(np.abs(gap) <= 180.0)
    plt.close(fig)

    fig, axes = delay_report.plot()
    assert axes[0].get_ylabel() == "Magnitude [dB]"
    plt.close(fig)


def test_report_plot_old_api_warns(delay_report):
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, given = plt.subplots(3, 1)
    with pytest.warns(FutureWarning, match="`axes` was renamed to `ax`"):
        result = delay_report.plot(axes=given)
    with pytest.warns(FutureWarning, match=r"now returns \(fig, axes\)"):
        assert result["figure"] is fig
    assert result[0] is fig and list(result[1]) == list(given)
    with pytest.raises(ValueError, match=r"`ax` must be 3 Axes \(magnitude, phase"):
        delay_report.plot(ax=given[:2])
    plt.close(fig)


# ---------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_data(stage):
    rng = np.random.default_rng(5)
    u = np.stack([multisine(1200, rms=1.44, rng=rng) for _ in range(2)])
    y = np.stack([simulate(stage.G_y4, ui, 3, snr_db=45, rng=rng).y_l for ui in u])
    return u[:, None], y[:, None]  # two experiments, 3-D (P, 1, N)


def _call(stage, u, y, **kwargs):
    options = {"sample_time": TS, "controller": stage.controller,
               "calibration_runs": 0, "max_effects": 0}
    options.update(kwargs)
    plant = options.pop("plant", stage.plant[0, 0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return diagnose(plant, u, y, 3, **options)



def test_diagnose_shares_the_single_threaded_blas_section(
        stage, small_data, two_blas_threads, monkeypatch):
    """A fit in another thread (dask, joblib) whose single-threaded BLAS section
    overlaps diagnose's: BLAS stays on one thread through the search after that
    fit ends, and diagnose gives the original threads back when it ends."""
    import threading

    from conftest import blas_threads

    from lrmfrf.discrepancy import workflow
    from lrmfrf.local_models import _single_threaded_blas

    before = two_blas_threads
    fit_in, search_started, fit_out = (threading.Event() for _ in range(3))
    seen, errors = {}, []

    def other_fit():
        try:
            with _single_threaded_blas():
                fit_in.set()
                assert search_started.wait(timeout=60)
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)
        finally:
            fit_out.set()

    def search(*args, **kwargs):
        search_started.set()
        assert fit_out.wait(timeout=60)
        seen["search after the other fit ended"] = blas_threads()
        return "report"

    monkeypatch.setattr(workflow, "run_search", search)
    thread = threading.Thread(target=other_fit)
    thread.start()
    try:
        assert fit_in.wait(timeout=60)
        assert _call(stage, *small_data) == "report"
    finally:
        search_started.set()
        thread.join(timeout=60)
    assert not errors, errors
    assert seen == {"search after the other fit ended": [1] * len(before)}
    assert blas_threads() == before


def test_plant_with_wrong_sample_time(stage, small_data):
    plant = control.sample_system(stage.plant_continuous[0, 0], 1e-3)
    with pytest.raises(ValueError, match="sample time dt=0.001 s but the data"):
        _call(stage, *small_data, plant=plant)


def test_mimo_plant_is_rejected(stage, small_data):
    with pytest.raises(ValueError, match="must be SISO.*stage.plant\\[0, 0\\]"):
        _call(stage, *small_data, plant=stage.plant)


def test_plant_of_wrong_type(stage, small_data):
    with pytest.raises(TypeError, match="python-control StateSpace"):
        _call(stage, *small_data, plant=np.eye(2))


def test_unstable_closed_loop(stage, small_data):
    with pytest.raises(ValueError, match="closed loop of `plant` and `controller` "
                       "is unstable"):
        _call(stage, *small_data, controller=stage.controller * 20)


def test_candidate_that_destabilises_the_loop_is_skipped(stage):
    """Bug (issue 12, item 2): the shipped example data with the shipped model.

    The data are the closed loop to the `z` output, the model is the `y4`
    plant, so the search tries large changes; some candidates make the
    closed loop unstable. They must be skipped and counted, not abort the run
    with an error that blames the user's (stable) model. The search path that
    meets such candidates on these data is the one with the Lemma 2 std of
    the bug report (the default std since issue 15 whitens differently).
    """
    from lrmfrf import LRMBeyondNyquist

    data = np.load(Path(lrmfrf.__file__).parent / "data" / "wafer_stage_example.npz")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = diagnose(stage.plant[0, 0], data["u"], data["y"], 3,
                          sample_time=TS, controller=stage.controller, rng=0,
                          estimator=LRMBeyondNyquist(std_method="lemma2"))
    assert report.skipped_candidates, report.summary()
    assert "skipped" in report.summary()
    assert report.to_dict()["skipped_candidates"] == report.skipped_candidates
    # every model the report holds closes a stable loop with the controller
    loop = control.feedback(report.updated_plant, stage.controller)
    assert np.max(np.abs(np.linalg.eigvals(loop.A))) < 1.0
    assert report.gap_after <= report.gap_before


def test_loop_guard_skips_only_unstable_closed_loops(stage, nominal):
    from lrmfrf.discrepancy._search import LoopGuard

    guard = LoopGuard(control.ss(stage.controller), TS)
    loud = Gain().apply(nominal, {"gain": 20.0})  # the loop gain x 20: unstable
    assert guard.admits(nominal, "nominal")
    assert not guard.admits(loud, "gain")
    assert guard.skipped == ["gain"]
    open_loop = LoopGuard(None, TS)  # no loop to destabilise
    assert open_loop.admits(loud, "gain") and open_loop.skipped == []


def test_continuous_controller(stage, small_data):
    with pytest.raises(ValueError, match="`controller` must be discrete"):
        _call(stage, *small_data, controller=control.tf([1.0], [1.0, 1.0]))


def test_controller_with_wrong_sample_time(stage, small_data):
    controller = control.ss(*control.ssdata(stage.controller), 1e-3)
    with pytest.raises(ValueError, match="`controller` has dt=0.001 s"):
        _call(stage, *small_data, controller=controller)


def test_data_shorter_than_the_estimator_needs(stage):
    u = multisine(60, rng=0)
    y = simulate(stage.G_y4, u, 3).y_l
    with pytest.raises(ValueError, match="could not be fitted to the data"):
        _call(stage, u, y)


def test_nan_std_bins_are_dropped_with_a_warning(stage, small_data):
    u, y = small_data
    est = LRMBeyondNyquist().fit(u, y, 3, sample_time=TS)
    est.frf_std_ = est.frf_std_.copy()
    est.frf_std_[100:105] = np.nan
    est.frf_std_[200] = 0.0
    with pytest.warns(UserWarning, match="6 of 600 bins .* left out") as record:
        report = diagnose(stage.plant[0, 0], u, y, 3, sample_time=TS,
                          controller=stage.controller, estimator=est,
                          calibration_runs=0, max_effects=0)
    assert report.frequencies.size == 594
    assert record[0].filename == __file__  # the warning points at the caller
    assert np.all(np.isfinite(report.std))


def test_zero_std_everywhere_is_an_error(stage, small_data):
    u, y = small_data
    est = LRMBeyondNyquist().fit(u, y, 3, sample_time=TS)
    est.frf_std_ = np.zeros_like(est.frf_std_)
    with pytest.raises(ValueError, match="only 0 of 600 bins"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            diagnose(stage.plant[0, 0], u, y, 3, sample_time=TS,
                     controller=stage.controller, estimator=est)


def test_fitted_estimator_must_match_the_data(stage, small_data):
    u, y = small_data
    est = LRMBeyondNyquist().fit(u[..., :600], y[..., :200], 3, sample_time=TS)
    with pytest.raises(ValueError, match="does not match the data"):
        _call(stage, u, y, estimator=est)


def test_uncalibrated_fallback_warns_without_noise_estimate(stage, small_data):
    u, y = small_data

    class NoNoise(LRMBeyondNyquist):
        def fit(self, *args, **kwargs):
            super().fit(*args, **kwargs)
            del self.noise_variance_
            return self

    with pytest.warns(UserWarning, match="cannot be calibrated by simulation"):
        report = diagnose(stage.plant[0, 0], u, y, 3, sample_time=TS,
                          controller=stage.controller, estimator=NoNoise(),
                          max_effects=0)
    assert report.calibration.method == "uncalibrated"


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"alpha": 1.5}, ValueError, "`alpha` must be in"),
        ({"effect_alpha": "x"}, TypeError, "`effect_alpha` must be a probability"),
        ({"calibration_runs": 1}, ValueError, "`calibration_runs` must be 0"),
        ({"max_effects": -1}, ValueError, "`max_effects` must be an integer >= 0"),
        ({"debias_rounds": 1.5}, TypeError, "`debias_rounds` must be an integer"),
        ({"ic_margin": -2.0}, ValueError, "`ic_margin` must be a finite number"),
        ({"ic_margin": "6"}, TypeError, "`ic_margin` must be a number >= 0"),
        ({"rng": -1}, ValueError, "`rng` must be a seed >= 0"),
        ({"sample_time": 0.0}, ValueError, "`sample_time` must be a positive"),
        ({"smoothing_bins": 0}, ValueError, "`smoothing_bins` must be an integer >= 1"),
        ({"rng": "seed"}, TypeError, "`rng` must be None, an int seed or a numpy"),
        ({"rng": 0, "random_state": 1}, TypeError, "pass only `rng`, not both"),
        ({"smoothing_bins": 5, "window": 7}, TypeError,
         "`window` was renamed to `smoothing_bins`"),
        ({"effects": ["gain"]}, TypeError, "`effects` must hold Effect instances"),
        ({"calibration": 3}, TypeError, "`calibration` must be a Calibration"),
        ({"band": (500.0, 100.0)}, ValueError, "`band` must satisfy 0 <= low"),
        ({"band": "low"}, TypeError, "`band` must be a pair"),
    ],
)
def test_bad_settings(stage, small_data, kwargs, error, match):
    with pytest.raises(error, match=match):
        _call(stage, *small_data, **kwargs)


def test_renamed_keywords_warn_and_give_the_same_report(stage, small_data):
    """`random_state` -> `rng`, `window` -> `smoothing_bins` (issue 12, item 8)."""
    u, y = small_data
    options = {"controller": stage.controller, "calibration_runs": 2,
               "max_effects": 0, "sample_time": TS}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        new = diagnose(stage.plant[0, 0], u, y, 3, rng=4, smoothing_bins=5,
                       **options)
        with pytest.warns(FutureWarning) as record:
            old = diagnose(stage.plant[0, 0], u, y, 3, random_state=4, window=5,
                           **options)
    messages = [str(w.message) for w in record]
    assert any("`random_state` was renamed to `rng`" in m for m in messages)
    assert any("`window` was renamed to `smoothing_bins`" in m for m in messages)
    assert all(w.filename == __file__ for w in record)  # points at the caller
    assert new.settings["smoothing_bins"] == old.settings["smoothing_bins"] == 5
    assert new.calibration.smoothing_bins == 5
    np.testing.assert_array_equal(new.spectrum_before, old.spectrum_before)
    np.testing.assert_array_equal(new.calibration.scale, old.calibration.scale)
    with pytest.warns(FutureWarning, match="`Calibration.window` was renamed"):
        assert new.calibration.window == 5
    with pytest.warns(FutureWarning, match="`window` was renamed"):
        assert uncalibrated(10, window=3).smoothing_bins == 3
    w2 = np.random.default_rng(0).random(30)
    with pytest.warns(FutureWarning, match="`window` was renamed"):
        old_spectrum = discrepancy_spectrum(w2, window=3)
    np.testing.assert_array_equal(old_spectrum, discrepancy_spectrum(w2, 3))


def test_sample_time_is_taken_from_a_discrete_model(stage, small_data):
    """`sample_time` optional: the plant's dt, else the controller's (item 8)."""
    u, y = small_data
    given = _call(stage, u, y)
    from_plant = _call(stage, u, y, sample_time=None)
    from_controller = _call(stage, u, y, sample_time=None,
                            plant=stage.plant_continuous[0, 0])
    for report in (from_plant, from_controller):
        np.testing.assert_allclose(report.frequencies, given.frequencies,
                                   rtol=1e-12)
        assert report.updated_plant.dt == TS
    np.testing.assert_array_equal(from_plant.measured, given.measured)


def test_no_sample_time_anywhere_is_an_error(stage, small_data):
    with pytest.raises(ValueError, match="`sample_time` was not given and neither "
                       "`plant` nor `controller` is a discrete model.*"
                       "sample_time=0.5e-3"):
        _call(stage, *small_data, sample_time=None, controller=None,
              plant=stage.plant_continuous[0, 0])


def test_sample_time_taken_from_plant_must_match_controller(stage, small_data):
    plant = control.sample_system(stage.plant_continuous[0, 0], 1e-3)
    with pytest.raises(ValueError, match=r"`controller` has dt=0.0005 s but "
                       r"sample_time=0.001 s \(the dt of `plant`\)"):
        _call(stage, *small_data, sample_time=None, plant=plant)


def test_inputs_are_not_modified(stage, small_data):
    u, y = small_data
    u0, y0 = u.copy(), y.copy()
    _call(stage, u, y)
    np.testing.assert_array_equal(u, u0)
    np.testing.assert_array_equal(y, y0)


def test_effect_base_class_is_abstract():
    plant = ContinuousPlant(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)),
                            np.ones((1, 1)))
    effect = Effect()
    for call in (lambda: effect.initial_guesses(None), lambda: effect.bounds(None),
                 lambda: effect.apply(plant, {})):
        with pytest.raises(NotImplementedError):
            call()


def test_mode_shift_candidates_of_a_non_minimal_siso_model_can_be_applied():
    """A SISO model whose every pole pair appears twice (the same transfer
    function built non-minimally, e.g. a sum of parallel parts sharing a
    mode): the search fits every ModeShift candidate it expands and builds its
    plant at the end (fit_candidate's plant_of(x), outside the residual's
    guard), so a candidate that cannot be applied stopped diagnose with
    "could not isolate the mode ... (repeated pole)" (5715b12: a suspended
    random stage, P2 = 0.5 P + 0.5 P). Repeated pole pairs are not expanded
    now (e3ea14f, for MIMO stages): whatever is expanded can be applied."""
    from lrmfrf.discrepancy import ModeShift
    from lrmfrf.discrepancy.effects import EffectContext

    w = 2 * np.pi * 300.0
    mode = control.ss(control.tf([w * w], [1.0, 2 * 0.01 * w, w * w]))
    suspension = control.ss(control.tf([1.0], [1.0, 2 * 0.1 * 30.0, 900.0]))
    plant = as_continuous_plant(suspension + mode + 0.5 * mode, 1e-4)
    found = resonances(plant)
    assert [round(r.frequency) for r in found].count(300) == 2
    freqs = np.linspace(1.0, 4000.0, 50)
    context = EffectContext(plant, freqs, 1e-4, None, None, np.zeros(freqs.size),
                            resonances=found)
    for effect in ModeShift().expand(context):
        effect.apply(plant, {"frequency": 320.0, "damping": 0.02})


def test_mode_shift_candidates_target_only_modes_a_shift_can_move(monkeypatch):
    # Mode shifts are applied before missing modes: a shift "of" a mode that
    # an accepted missing mode added would move the nominal mode nearest it
    # under the added mode's label. With a missing mode accepted first (seed
    # 13: missing mode at 841 Hz and gain hidden) every mode_shift candidate
    # the search expands must target a mode of the nominal plant (no mode
    # shift is accepted here).
    from lrmfrf.discrepancy.effects import ModeShift

    expanded = []
    original = ModeShift.expand

    def recording(self, context):
        candidates = original(self, context)
        expanded.extend(f"{c.target.frequency:.4g}" for c in candidates)
        return candidates

    monkeypatch.setattr(ModeShift, "expand", recording)
    experiment = hidden_effect_experiment(("missing_mode", "gain"), rng=13)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = diagnose(experiment.plant, experiment.u_h, experiment.y_l,
                          experiment.F, controller=experiment.controller, rng=13,
                          calibration_runs=4)
    assert sorted(report.effects) == ["gain", "missing_mode"]
    nominal = {f"{mode.frequency:.4g}" for mode in resonances(
        as_continuous_plant(experiment.plant, experiment.sample_time))}
    assert expanded
    assert set(expanded) <= nominal, set(expanded) - nominal


def test_effect_context_keeps_its_positional_order():
    # EffectContext is public (custom effects read it, their tests build it):
    # modal_resonances, added later, comes after the fields it had before, so
    # a context built positionally still gets its sensitivity, residual and
    # std where they were (inserted after `resonances` it took the
    # sensitivity as the list of modes to shift)
    from lrmfrf.discrepancy.effects import EffectContext

    freqs = np.linspace(10.0, 900.0, 5)
    sensitivity, residual, std = (np.full(freqs.size, v) for v in (0.5, 0.1j, 0.2))
    context = EffectContext(None, freqs, 1e-4, None, None, np.zeros(freqs.size), [],
                            sensitivity, residual, std)
    assert context.sensitivity is sensitivity
    assert context.residual is residual and context.std is std
    assert context.modal_resonances is None
