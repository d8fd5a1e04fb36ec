"""Tests for lrmfrf.plants.mimo_stage: the MIMO OAT-like wafer stage."""

import doctest
import math

import control
import numpy as np
import pytest

import lrmfrf.plants.mimo_stage as mimo_module
from lrmfrf.plants import (
    DEFAULT_PLATE_MODES,
    MIMOWaferStage,
    PlateMode,
    mimo_wafer_stage,
)

TS = 0.5e-3
FREQUENCIES_HZ = np.array([3.0, 39.0, 171.0, 236.0, 333.0, 440.0, 612.0, 950.0])


@pytest.fixture(scope="module")
def stage():
    return mimo_wafer_stage()


def response(system, frequencies_hz):
    """``C (z I - A)^-1 B + D`` (or at ``s = j w``), shape (n_y, n_u, n_f)."""
    A, B, C, D = (np.asarray(m, dtype=float) for m in (system.A, system.B,
                                                         system.C, system.D))
    if system.isdtime():
        points = np.exp(2j * np.pi * frequencies_hz * system.dt)
    else:
        points = 2j * np.pi * frequencies_hz
    out = np.empty((C.shape[0], B.shape[1], len(points)), dtype=complex)
    for i, p in enumerate(points):
        out[:, :, i] = C @ np.linalg.solve(p * np.eye(A.shape[0]) - A, B) + D
    return out


def test_shapes_labels_and_sample_time(stage):
    assert isinstance(stage, MIMOWaferStage)
    assert (stage.plant.noutputs, stage.plant.ninputs) == (5, 4)
    assert (stage.controller.noutputs, stage.controller.ninputs) == (4, 4)
    assert (stage.G.noutputs, stage.G.ninputs) == (5, 4)
    assert stage.plant.output_labels == ["y1", "y2", "y3", "y4", "z"]
    assert stage.controller.input_labels == ["y1", "y2", "y3", "y4"]
    assert stage.plant.dt == stage.controller.dt == stage.G.dt == TS
    assert stage.feedback_outputs == (0, 1, 2, 3)
    assert math.isclose(stage.slow_nyquist_hz, 1 / (6 * TS))
    # 3 rigid degrees of freedom and 4 modes, 2 states each; 3 x 4 controller states
    assert stage.plant.nstates == 14 and stage.controller.nstates == 12
    assert stage.G.nstates == 26


def test_continuous_plant_matches_the_modal_formula(stage):
    """Known answer: the module docstring's sum over rigid DOFs and modes."""
    a, b = stage.half_width
    xy = np.array([[a, b], [-a, b], [-a, -b], [a, -b], stage.poi])
    masses = (stage.mass, *stage.inertia)
    s = 2j * np.pi * FREQUENCIES_HZ
    expected = np.zeros((5, 4, len(s)), dtype=complex)
    for o in range(5):
        for j in range(4):
            c = (1.0, xy[o, 1], -xy[o, 0])
            g = (1.0, xy[j, 1], -xy[j, 0])
            for d in range(3):
                expected[o, j] += c[d] * g[d] / (masses[d] * s**2)
            for mode in stage.modes:
                w = 2 * np.pi * mode.frequency_hz
                expected[o, j] += (
                    mode.shape()[o] * mode.corners[j]
                    / (stage.mass * (s**2 + 2 * mode.damping * w * s + w**2))
                )
    got = response(stage.plant_continuous, FREQUENCIES_HZ)
    np.testing.assert_allclose(got, expected, rtol=1e-12)


def test_closed_loop_is_the_equivalent_system(stage):
    """G = P (I + C P_y)^-1 at every frequency (eq. EquivalentSystems)."""
    P = response(stage.plant, FREQUENCIES_HZ)
    C = response(stage.controller, FREQUENCIES_HZ)
    G = response(stage.G, FREQUENCIES_HZ)
    for i in range(len(FREQUENCIES_HZ)):
        loop = np.eye(4) + C[:, :, i] @ P[:4, :, i]
        expected = P[:, :, i] @ np.linalg.inv(loop)
        np.testing.assert_allclose(G[:, :, i], expected, rtol=1e-9, atol=0)


def test_decoupled_plant_is_diagonal(stage):
    """T_y P_y T_u has no off-diagonal terms (the corner patterns are chosen
    so): relative size below round-off."""
    P = response(stage.plant, FREQUENCIES_HZ)[:4]
    t_y, t_u = stage.sensor_decoupling, stage.actuator_decoupling
    for i in range(len(FREQUENCIES_HZ)):
        decoupled = t_y @ P[:, :, i] @ t_u
        off = decoupled - np.diag(np.diag(decoupled))
        assert np.max(np.abs(off)) < 1e-12 * np.max(np.abs(decoupled))
    # T_y recovers heave, roll, pitch from the corners; T_u produces them.
    a, b = stage.half_width
    corners = np.array([[a, b], [-a, b], [-a, -b], [a, -b]])
    rigid = np.column_stack([np.ones(4), corners[:, 1], -corners[:, 0]])
    np.testing.assert_allclose(t_y @ rigid, np.eye(3), atol=1e-13)
    np.testing.assert_allclose(rigid.T @ t_u, np.eye(3), atol=1e-13)


def test_torsion_direction_is_not_fed_back(stage):
    """The torsion pattern is orthogonal to heave, roll and pitch, so the loop
    does not see it: G v = P v exactly for v = (+1, -1, +1, -1)."""
    v = np.array([1.0, -1.0, 1.0, -1.0])
    P = response(stage.plant, FREQUENCIES_HZ)
    G = response(stage.G, FREQUENCIES_HZ)
    gv = np.einsum("oif,i->of", G, v)
    pv = np.einsum("oif,i->of", P, v)
    np.testing.assert_allclose(gv, pv, rtol=1e-9)


def test_loops_are_stable_with_margins(stage):
    radius = np.max(np.abs(np.linalg.eigvals(stage.G.A)))
    assert radius < 1.0
    margins = stage.margins()
    assert set(margins) == {"heave", "roll", "pitch"}
    for dof, m in margins.items():
        assert m.phase_margin > 30.0, dof
        assert m.gain_margin > 2.0, dof
        assert abs(m.crossover_hz - 40.0) < 4.0, dof


def test_aliasing_pattern_of_the_default_modes(stage):
    """Two modes above the slow Nyquist frequency (F = 3, 333.3 Hz)."""
    above = [m.frequency_hz for m in stage.modes if m.frequency_hz > 1 / (6 * TS)]
    assert above == [440.0, 610.0]
    assert stage.modes == DEFAULT_PLATE_MODES


def test_damping_scale_and_bandwidth_are_applied():
    light = mimo_wafer_stage(damping_scale=0.5, controller_bandwidth=30.0)
    assert light.modes[0].damping == pytest.approx(0.005)
    assert light.controller_bandwidth == 30.0
    assert abs(light.margins()["heave"].crossover_hz - 30.0) < 3.0


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"half_width": (0.1, -0.1)}, ValueError, "half_width"),
        ({"half_width": 0.1}, ValueError, "half_width"),
        ({"poi": (0.0, np.nan)}, ValueError, "poi"),
        ({"mass": 0.0}, ValueError, "mass"),
        ({"damping_scale": 200.0}, ValueError, "damping_scale"),
        ({"downsampling_factor": 0}, ValueError, "downsampling_factor"),
        ({"modes": [(170.0, 0.01, (1, 1, 1, 1), 1.0)]}, TypeError, "PlateMode"),
        ({"modes": [PlateMode(-1.0, 0.01, (1, 1, 1, 1), 1.0)]}, ValueError,
         "frequency_hz > 0"),
        ({"modes": [PlateMode(100.0, 0.01, (1, 1, 1), 1.0)]}, ValueError,
         "4 corner"),
    ],
)
def test_bad_parameters_are_named(kwargs, error, match):
    with pytest.raises(error, match=match):
        mimo_wafer_stage(**kwargs)


def test_unstable_loop_is_refused():
    # A strongly participating, undamped mode in the heave loop at 120 Hz.
    modes = [PlateMode(120.0, 0.0, (-2.0, -2.0, -2.0, -2.0), 1.0)]
    with pytest.raises(ValueError, match="does not stabilise the loop"):
        mimo_wafer_stage(modes=modes, controller_bandwidth=80.0)


def test_docstring_examples_run():
    result = doctest.testmod(mimo_module, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0


def test_control_library_agrees_on_the_closed_loop(stage):
    """Cross-check with python-control's own feedback interconnection."""
    fb = control.feedback(stage.plant[:4, :], stage.controller, sign=-1)
    G_fb = response(fb, FREQUENCIES_HZ)
    G = response(stage.G, FREQUENCIES_HZ)
    np.testing.assert_allclose(G[:4], G_fb, rtol=1e-8)


def test_controller_at_another_rate():
    """The design at the stage's own rate is the stage's controller; at the slow
    rate (vision in the loop) it stabilises the slow-feedback loop."""
    from lrmfrf.simulate import simulate_slow_feedback

    stage = mimo_wafer_stage()
    same = stage.controller_at(stage.sample_time)
    for name in ("A", "B", "C", "D"):
        np.testing.assert_array_equal(getattr(same, name),
                                      getattr(stage.controller, name))
    F = stage.downsampling_factor
    slow = stage.controller_at(F * stage.sample_time, bandwidth_hz=20.0)
    assert slow.dt == pytest.approx(F * stage.sample_time)
    assert (slow.ninputs, slow.noutputs) == (4, 4)
    r = np.random.default_rng(0).standard_normal((4, 600))
    sim = simulate_slow_feedback(stage.plant, slow, r, F,
                                 feedback_outputs=stage.feedback_outputs)
    assert np.all(np.isfinite(sim.y_l)) and sim.y_l.shape == (5, 200)
    with pytest.raises(ValueError, match="bandwidth_hz must be a positive"):
        stage.controller_at(stage.sample_time, bandwidth_hz=-1.0)
