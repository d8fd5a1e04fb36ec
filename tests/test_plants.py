"""Tests for lrmfrf.plants: the OAT-like wafer stage."""

import math

import control
import numpy as np
import pytest

from lrmfrf.plants import (
    DEFAULT_MODES,
    Mode,
    closed_loop,
    lead_pid_controller,
    loop_margins,
    modal_plant,
    wafer_stage,
)

TS = 0.5e-3
SLOW_SAMPLING_HZ = 1.0 / (3 * TS)  # 666.7 Hz


@pytest.fixture(scope="module")
def stage():
    return wafer_stage()


@pytest.fixture(scope="module")
def margins(stage):
    return stage.margins()


def _evaluate(system, z):
    """Frequency response through python-control's own evaluation."""
    return np.array([complex(np.squeeze(system(point))) for point in z])


def _unit_circle(frequencies_hz):
    return np.exp(2j * np.pi * np.asarray(frequencies_hz) * TS)


# --- plant structure ---------------------------------------------------------


def test_modes_at_stated_frequencies_and_damping(stage):
    eigenvalues = np.linalg.eigvals(stage.plant_continuous.A)
    assert np.sum(eigenvalues == 0) == 2  # rigid body: double integrator
    upper = eigenvalues[eigenvalues.imag > 0]
    assert upper.size == len(stage.modes)
    for mode in stage.modes:
        omega = 2 * np.pi * mode.frequency_hz
        match = upper[np.argmin(np.abs(np.abs(upper) - omega))]
        assert abs(abs(match) - omega) / omega < 1e-12
        assert abs(-match.real / abs(match) - mode.damping) < 1e-12


def test_default_modes_are_lightly_damped_with_one_above_slow_nyquist(stage):
    assert len(stage.modes) >= 3
    assert all(0.005 <= mode.damping <= 0.02 for mode in stage.modes)
    assert stage.slow_nyquist_hz == pytest.approx(1000.0 / 3, rel=1e-12)
    assert any(mode.frequency_hz > stage.slow_nyquist_hz for mode in stage.modes)


def test_alias_of_mode_3_falls_near_mode_2(stage):
    # mode 3 (440 Hz) aliases to |440 - 666.7| = 226.7 Hz, 8.3 Hz from mode 2
    f2, f3 = stage.modes[1].frequency_hz, stage.modes[2].frequency_hz
    alias = abs(f3 - SLOW_SAMPLING_HZ)
    assert f3 > stage.slow_nyquist_hz
    assert abs(alias - f2) < 10.0


def test_outputs_have_different_participations_with_sign_changes(stage):
    y4 = np.array([m.participation_y4 for m in stage.modes])
    z = np.array([m.participation_z for m in stage.modes])
    assert np.all(y4 > 0)
    assert np.any(np.sign(z) != np.sign(y4))


def test_modal_realisation_is_block_diagonal_and_well_scaled():
    plant = modal_plant(4.0, DEFAULT_MODES)
    A = plant.A
    mask = np.kron(np.eye(A.shape[0] // 2), np.ones((2, 2))).astype(bool)
    assert np.all(A[~mask] == 0)
    # scaled states: off-diagonal entries of a flexible block are +/- omega
    omega = 2 * np.pi * DEFAULT_MODES[0].frequency_hz
    assert A[2, 3] == pytest.approx(omega) and A[3, 2] == pytest.approx(-omega)


def test_modal_plant_frequency_response_matches_formula():
    mass = 4.0
    plant = modal_plant(mass, DEFAULT_MODES, outputs=("z",))
    s = 2j * np.pi * np.array([3.0, 100.0, 300.0, 700.0])
    expected = 1 / (mass * s**2)
    for m in DEFAULT_MODES:
        w = 2 * np.pi * m.frequency_hz
        expected += m.participation_z / (mass * (s**2 + 2 * m.damping * w * s + w**2))
    np.testing.assert_allclose(_evaluate(plant, s), expected, rtol=1e-12)


def test_discretisation_matches_control_sample_system(stage):
    reference = control.sample_system(stage.plant_continuous, TS, method="zoh")
    z = _unit_circle([1.0, 40.0, 170.0, 235.0, 440.0, 610.0, 999.0])
    for output in range(2):
        np.testing.assert_allclose(
            _evaluate(stage.plant[output, 0], z),
            _evaluate(reference[output, 0], z),
            rtol=1e-10,
        )


# --- closed loop -------------------------------------------------------------


def test_closed_loops_are_stable(stage):
    for system in (stage.G_y4, stage.G_z):
        assert control.isdtime(system, strict=True) and system.dt == TS
        assert (system.ninputs, system.noutputs) == (1, 1)
        assert np.max(np.abs(np.linalg.eigvals(system.A))) < 1.0


def test_closed_loops_match_eq_equivalent_systems(stage):
    z = _unit_circle([2.0, 39.0, 171.0, 300.0, 440.0, 900.0])
    controller = _evaluate(stage.controller, z)
    p_y4 = _evaluate(stage.plant[0, 0], z)
    p_z = _evaluate(stage.plant[1, 0], z)
    sensitivity = 1.0 / (1.0 + controller * p_y4)
    np.testing.assert_allclose(_evaluate(stage.G_y4, z), p_y4 * sensitivity, rtol=1e-9)
    np.testing.assert_allclose(_evaluate(stage.G_z, z), p_z * sensitivity, rtol=1e-9)


def test_G_y4_and_G_z_differ(stage):
    z = _unit_circle(np.linspace(50, 950, 91))
    g_y4, g_z = _evaluate(stage.G_y4, z), _evaluate(stage.G_z, z)
    relative = np.abs(g_y4 - g_z) / np.abs(g_y4)
    assert np.max(relative) > 1.0
    assert np.median(relative) > 0.1


def test_margins_and_crossover(stage, margins):
    assert 30.0 <= margins.crossover_hz <= 50.0
    assert margins.crossover_hz == pytest.approx(40.0, rel=0.05)
    assert 30.0 < margins.phase_margin < 60.0
    assert margins.gain_margin > 1.5
    assert 0.0 < margins.lower_gain_margin < 0.5
    assert margins.modulus_margin > 0.35
    # independent check at the crossover with python-control's evaluation
    loop = control.series(stage.plant[0, 0], stage.controller)
    value = _evaluate(loop, _unit_circle([margins.crossover_hz]))[0]
    assert abs(value) == pytest.approx(1.0, abs=1e-6)
    assert 180.0 + np.angle(value, deg=True) == pytest.approx(
        margins.phase_margin, abs=1e-4
    )


def test_controller_bandwidth_sets_crossover():
    stage = wafer_stage(controller_bandwidth=30.0)
    assert stage.margins().crossover_hz == pytest.approx(30.0, rel=0.05)


def test_controller_has_integral_action(stage):
    # G = P / (1 + C P) -> 0 at DC because C has a pole at z = 1
    assert np.any(np.isclose(np.linalg.eigvals(stage.controller.A), 1.0, atol=1e-12))
    g_dc = _evaluate(stage.G_y4, [1.0])[0]
    assert abs(g_dc) < 1e-9 * abs(_evaluate(stage.G_y4, _unit_circle([20.0]))[0])


def test_damping_scale_scales_all_dampings():
    stage = wafer_stage(damping_scale=0.5)
    for scaled, base in zip(stage.modes, DEFAULT_MODES, strict=True):
        assert scaled.damping == pytest.approx(0.5 * base.damping, rel=1e-15)


def test_closed_loop_public_builder_matches_stage(stage):
    system = closed_loop(stage.plant[1, 0], stage.plant[0, 0], stage.controller)
    np.testing.assert_array_equal(system.A, stage.G_z.A)
    np.testing.assert_array_equal(system.C, stage.G_z.C)


def test_closed_loop_accepts_transfer_function_controller(stage):
    z = _unit_circle([10.0, 100.0])
    controller_tf = control.ss2tf(stage.controller)
    system = closed_loop(stage.plant[0, 0], stage.plant[0, 0], controller_tf)
    np.testing.assert_allclose(
        _evaluate(system, z), _evaluate(stage.G_y4, z), rtol=1e-8
    )


def test_closed_loop_with_feedthrough_solves_algebraic_loop():
    plant = control.ss([[0.5]], [[1.0]], [[1.0]], [[0.5]], 1.0)
    controller = control.ss([], [], [], [[0.4]], 1.0)
    system = closed_loop(plant, plant, controller)
    z = np.exp(1j * np.array([0.3, 1.1]))
    p = _evaluate(plant, z)
    np.testing.assert_allclose(_evaluate(system, z), p / (1 + 0.4 * p), rtol=1e-12)


# --- bad input ---------------------------------------------------------------


@pytest.mark.parametrize("mass", [0.0, -1.0, np.nan])
def test_rejects_non_physical_mass(mass):
    with pytest.raises(ValueError, match="mass must be a finite number > 0"):
        wafer_stage(mass=mass)


@pytest.mark.parametrize("damping", [-0.01, 1.0, 1.5])
def test_rejects_damping_outside_unit_interval(damping):
    with pytest.raises(ValueError, match=r"damping must be in \[0, 1\)"):
        wafer_stage(modes=[Mode(100.0, damping, 0.1, 0.1)])


@pytest.mark.parametrize("frequency", [0.0, -5.0])
def test_rejects_non_positive_frequency(frequency):
    with pytest.raises(ValueError, match="frequency_hz must be > 0 Hz"):
        modal_plant(4.0, [Mode(frequency, 0.01, 0.1, 0.1)])


def test_rejects_non_finite_mode():
    with pytest.raises(ValueError, match="non-finite value"):
        modal_plant(4.0, [Mode(100.0, 0.01, np.inf, 0.1)])


def test_rejects_non_mode_entries():
    with pytest.raises(TypeError, match=r"modes\[0\] must be a Mode"):
        modal_plant(4.0, [(100.0, 0.01, 0.1, 0.1)])


def test_rejects_unknown_outputs():
    with pytest.raises(ValueError, match="outputs must be a non-empty sequence"):
        modal_plant(4.0, DEFAULT_MODES, outputs=("y1",))


def test_rejects_damping_scale_out_of_range():
    with pytest.raises(ValueError, match="damping_scale must be a finite number"):
        wafer_stage(damping_scale=-1.0)
    with pytest.raises(ValueError, match="keep damping \\* damping_scale below 1"):
        wafer_stage(damping_scale=100.0)


def test_rejects_non_stabilising_controller():
    # a strong mode in the feedback sensor at 235 Hz, where the low-pass and
    # zero-order-hold lag leave it neither gain- nor phase-stabilised
    with pytest.raises(ValueError, match="does not stabilise the loop"):
        wafer_stage(modes=[Mode(235.0, 0.01, 0.9, 0.5)])


@pytest.mark.parametrize("bandwidth", [0.0, -3.0, 200.0, np.nan])
def test_rejects_bad_bandwidth(bandwidth):
    with pytest.raises(ValueError, match="bandwidth_hz must be in"):
        lead_pid_controller(bandwidth, 4.0, sample_time=TS)


@pytest.mark.parametrize("sample_time", [0.0, -1e-3, np.inf])
def test_rejects_bad_sample_time(sample_time):
    with pytest.raises(ValueError, match="must be a positive, finite number"):
        wafer_stage(sample_time=sample_time)


def test_rejects_bad_downsampling_factor():
    with pytest.raises(TypeError, match="downsampling_factor must be an int"):
        wafer_stage(downsampling_factor=2.5)
    with pytest.raises(ValueError, match="downsampling_factor must be >= 1"):
        wafer_stage(downsampling_factor=0)


def test_closed_loop_rejects_different_realisations(stage):
    other = wafer_stage(mass=5.0)
    with pytest.raises(ValueError, match="must share A and B"):
        closed_loop(other.plant[1, 0], stage.plant[0, 0], stage.controller)


def test_closed_loop_rejects_continuous_mimo_and_mixed_systems(stage):
    continuous = stage.plant_continuous[0, 0]
    with pytest.raises(ValueError, match="must be discrete-time"):
        closed_loop(continuous, continuous, stage.controller)
    with pytest.raises(ValueError, match="must be SISO"):
        closed_loop(stage.plant, stage.plant[0, 0], stage.controller)
    slow = lead_pid_controller(40.0, 4.0, sample_time=2 * TS)
    with pytest.raises(ValueError, match="share one sample time"):
        closed_loop(stage.plant[0, 0], stage.plant[0, 0], slow)
    with pytest.raises(TypeError, match="must be a control.StateSpace or Transfer"):
        closed_loop(np.eye(2), stage.plant[0, 0], stage.controller)
    plant_tf = control.ss2tf(stage.plant[0, 0])
    with pytest.raises(TypeError, match="channels of one plant realisation"):
        closed_loop(plant_tf, plant_tf, stage.controller)


def test_closed_loop_rejects_singular_algebraic_loop():
    plant = control.ss([[0.5]], [[1.0]], [[1.0]], [[1.0]], 1.0)
    controller = control.ss([], [], [], [[-1.0]], 1.0)
    with pytest.raises(ValueError, match="algebraically singular"):
        closed_loop(plant, plant, controller)


def test_loop_margins_rejects_continuous_systems(stage):
    continuous_controller = control.tf([1.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="needs discrete-time systems"):
        loop_margins(stage.plant_continuous[0, 0], continuous_controller)


def test_margins_type_is_named(margins):
    assert margins._fields == (
        "gain_margin",
        "lower_gain_margin",
        "phase_margin",
        "crossover_hz",
        "modulus_margin",
    )
    assert all(math.isfinite(value) for value in margins)


def test_documented_margins_and_closed_loop_poles(stage, margins):
    """The figures stated in the module docstring, to their stated digits."""
    assert margins.crossover_hz == pytest.approx(39.6, abs=0.05)
    assert margins.phase_margin == pytest.approx(40.2, abs=0.05)
    assert margins.gain_margin == pytest.approx(2.15, abs=0.005)
    assert 20 * np.log10(margins.gain_margin) == pytest.approx(6.7, abs=0.05)
    assert margins.lower_gain_margin == pytest.approx(0.126, abs=0.0005)
    assert margins.modulus_margin == pytest.approx(0.46, abs=0.005)
    s = np.log(np.linalg.eigvals(stage.G_z.A).astype(complex)) / TS
    s = s[s.imag >= 0]
    hz, zeta = np.abs(s) / (2 * np.pi), -s.real / np.abs(s)
    for f, z in [(171.2, 0.0067), (235.3, 0.0054), (439.3, 0.0114),
                 (609.9, 0.0151), (43.8, 0.86), (326.0, 0.58)]:
        k = np.argmin(np.abs(hz - f))
        assert hz[k] == pytest.approx(f, abs=0.5)
        assert zeta[k] == pytest.approx(z, abs=0.005)
    real = np.sort(hz[np.abs(s.imag) < 1e-9])
    np.testing.assert_allclose(real, [5.7, 35.2], atol=0.05)
