"""Asymmetric 2x2 stages (``two_by_two_stage(..., asymmetry=seed)``) and
``diagnose`` on them.

The symmetric 2x2 stage (collocated, ``K = [[7, 1], [1, 7]] / m``, unit gains,
the same PID on both corners) has ``P = P^T`` and ``C = c I``: a transposed
plant response or the loop closed on the wrong side (``P (I + P C)^-1``)
gives the same answer there. On the asymmetric stage they do not; the
known-answer tests below fail with either mistake injected (checked by hand:
see the report of branch ``asym26``).
"""

from __future__ import annotations

import dataclasses
import warnings

import control
import numpy as np
import pytest

from lrmfrf.discrepancy import diagnose
from lrmfrf.discrepancy._models import frequency_response
from lrmfrf.discrepancy.fit import closed_loop_response
from lrmfrf.discrepancy.hidden_mimo import (
    ASYMMETRY_RANGES,
    mimo_hidden_effect_experiment,
    two_by_two_stage,
)
from lrmfrf.plants import lead_pid_controller, mimo_wafer_stage

FREQS = np.linspace(1.0, 999.0, 301)
FAST = {"calibration_runs": 6, "debias_rounds": 1}
SEED = 3  # K_11 m = 8.55, K_22 m = 5.98; gains 0.76-1.26; PIDs at 35 and 29 Hz


@pytest.fixture(scope="module")
def plate():
    return mimo_wafer_stage(downsampling_factor=3)


@pytest.fixture(scope="module")
def stage(plate):
    return two_by_two_stage(plate, loop="closed", asymmetry=SEED)


def _z(frequencies, sample_time):
    return np.exp(2j * np.pi * frequencies * sample_time)


def _modal_response(stage, s):
    """``diag(g_y) [K / s^2 + sum_i c_i b_i^T / (m (s^2 + 2 z w s + w^2))]
    diag(g_u)`` at the points ``s``, shape (2, 2, K); built here from the
    stage's attributes, not from its state space."""
    total = stage.rigid[:, :, None] / s**2
    for mode in stage.modes:
        w = 2 * np.pi * mode.frequency_hz
        residue = np.outer(mode.sensor_shape, mode.shape) / stage.mass
        total = total + residue[:, :, None] / (s**2 + 2 * mode.damping * w * s + w**2)
    gains = np.outer(stage.output_gains, stage.input_gains)
    return gains[:, :, None] * total


def test_asymmetric_stage_is_what_it_claims(plate, stage):
    low, high = ASYMMETRY_RANGES["gain"]
    for gains in (stage.input_gains, stage.output_gains):
        assert all(low <= g <= high for g in gains)
        assert abs(gains[0] / gains[1] - 1) > 0.05
    K = stage.rigid * stage.mass
    assert abs(K[0, 0] / K[1, 1] - 1) > 0.1  # centre of gravity off centre
    assert abs(K[0, 1] / K[1, 0] - 1) > 0.1  # sensors off the actuators
    # the same rigid compliance with the sensors on the actuators and the
    # centre of gravity in the middle is the symmetric stage's
    symmetric = two_by_two_stage(plate, loop="open")
    np.testing.assert_allclose(symmetric.rigid * symmetric.mass,
                               [[7.0, 1.0], [1.0, 7.0]], rtol=1e-12)
    assert symmetric.output_gains == symmetric.input_gains == (1.0, 1.0)
    assert all(m.output_shape is None for m in symmetric.modes)
    # non-collocated: every mode's sensor values differ from its actuator values
    low, high = ASYMMETRY_RANGES["mode_sensor_ratio"]
    assert len(stage.modes) == len(symmetric.modes) == 4
    for mode, old in zip(stage.modes, symmetric.modes, strict=True):
        assert mode.shape == old.shape  # the actuator values are the plate's
        ratio = np.divide(mode.output_shape, mode.shape)
        assert np.all((ratio >= low) & (ratio <= high))
        assert np.max(np.abs(ratio - 1)) > 0.01
    # the state space is the modal sum with the gains on the right sides
    s = 2j * np.pi * FREQS
    ref = _modal_response(stage, s)
    P = frequency_response(stage.plant_continuous(), FREQS, stage.sample_time)
    np.testing.assert_allclose(P, ref, rtol=0, atol=1e-9 * np.abs(ref).max())
    asym = np.abs(P - P.transpose(1, 0, 2)).max(axis=2)
    assert asym[0, 1] > 0.05 * np.abs(P[0, 1]).max()


def test_actuator_and_sensor_gains_act_on_every_stage(plate):
    """``P = diag(output_gains) P_phys diag(input_gains)`` also on the
    symmetric stage: the gains were applied only when ``asymmetry`` was set,
    so ``dataclasses.replace(symmetric, input_gains=(1, 1.2))`` (as the test
    below does to an asymmetric stage) silently gave the unchanged plant."""
    symmetric = two_by_two_stage(plate, loop="open")
    z = _z(FREQS, symmetric.sample_time)
    P = symmetric.plant(z)
    changed = dataclasses.replace(symmetric, input_gains=(1.0, 1.2),
                                  output_gains=(0.9, 1.0))
    expected = np.array([[0.9, 0.9 * 1.2], [1.0, 1.2]])[:, :, None] * P
    np.testing.assert_allclose(changed.plant(z), expected, rtol=1e-12,
                               atol=1e-12 * np.abs(P).max())


def test_asymmetric_stage_has_a_pid_per_loop_and_a_stable_loop(stage):
    C = frequency_response(stage.controller, FREQS, stage.sample_time)
    assert np.all(C[0, 1] == 0) and np.all(C[1, 0] == 0)
    bandwidths = stage.asymmetry["bandwidth_hz"]
    assert abs(bandwidths[0] / bandwidths[1] - 1) > 0.1
    for j in range(2):  # lead-PID on the corner's own effective mass
        mass = 1.0 / (stage.output_gains[j] * stage.rigid[j, j] * stage.input_gains[j])
        single = lead_pid_controller(bandwidths[j], mass, sample_time=stage.sample_time)
        ref = frequency_response(single, FREQS, stage.sample_time)
        np.testing.assert_allclose(C[j, j], ref, rtol=0,
                                   atol=1e-12 * np.abs(ref).max())
    loop = control.feedback(stage.plant, stage.controller, sign=-1)
    assert np.max(np.abs(np.linalg.eigvals(loop.A))) < 1.0
    # the crossover of each loop (the other closed) is near its bandwidth
    from lrmfrf.plants import loop_margins

    for j in range(2):
        other = control.append(*(stage.controller[k, k] if k != j else
                                 control.ss([], [], [], [[0.0]], stage.sample_time)
                                 for k in range(2)))
        half = control.feedback(stage.plant, other, sign=-1)
        margins = loop_margins(half[j, j], stage.controller[j, j])
        assert margins.phase_margin >= 30.0 and margins.gain_margin >= 2.0
        assert margins.crossover_hz == pytest.approx(bandwidths[j], rel=0.25)


def test_asymmetric_stage_is_reproducible_and_the_same_in_both_loops(plate, stage):
    again = two_by_two_stage(plate, loop="closed", asymmetry=SEED)
    opened = two_by_two_stage(plate, loop="open", asymmetry=SEED)
    other = two_by_two_stage(plate, loop="open", asymmetry=SEED + 1)
    for twin in (again, opened):
        np.testing.assert_array_equal(twin.rigid, stage.rigid)
        assert twin.modes == stage.modes
        assert (twin.input_gains, twin.output_gains) == (stage.input_gains,
                                                         stage.output_gains)
    assert opened.controller is None and opened.suspension is not None
    assert not np.array_equal(other.rigid, stage.rigid)


def test_closed_loop_equivalent_of_the_asymmetric_loop(stage):
    """P (I + C P)^-1 with C = diag(c_1, c_2) and P != P^T: the factors do not
    commute (P (I + P C)^-1 differs by more than 1 %)."""
    z = _z(FREQS, stage.sample_time)
    P = stage.plant(z)
    C = frequency_response(stage.controller, FREQS, stage.sample_time)
    ref = control.feedback(stage.plant, stage.controller, sign=-1)(z)
    np.testing.assert_allclose(closed_loop_response(P, C), ref,
                               atol=1e-9 * np.abs(ref).max())
    wrong = np.einsum("abk,bck->ack", P, np.linalg.inv(
        (np.eye(2)[None] + np.einsum("abk,bck->kac", P, C))).transpose(1, 2, 0))
    assert np.abs(wrong - ref).max() > 0.01 * np.abs(ref).max()


# ---------------------------------------------------------------------------
# diagnose on the asymmetric stage (closed loop, one experiment, 40 dB)
# ---------------------------------------------------------------------------


def _diagnose(stage, experiment):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return diagnose(stage.plant, experiment.u_h, experiment.y_l, experiment.F,
                        controller=stage.controller, rng=3, **FAST)


def test_nothing_hidden_on_the_asymmetric_stage_names_nothing(stage):
    experiment = mimo_hidden_effect_experiment(None, stage=stage, rng=7)
    report = _diagnose(stage, experiment)
    assert report.findings == []
    assert 0.7 < report.gap_before < 1.3


def test_one_actuator_gain_on_the_asymmetric_stage_is_named_on_its_input(stage):
    """The true stage's actuator 1 is 1.2 times stronger than the model's
    (a column of P): named ``input_gain`` of input 1, not of input 0 and not
    an output gain (a row), which a transposed P would give."""
    gains = (stage.input_gains[0], 1.2 * stage.input_gains[1])
    truth = dataclasses.replace(stage, input_gains=gains)
    # 60 dB: an input's gain and the same output's gain differ only in the
    # off-diagonal entries, here about 1/7 of the diagonal ones; at 40 dB
    # the transposed model response of the docstring still names the input
    experiment = mimo_hidden_effect_experiment(None, stage=truth, rng=7, snr_db=60.0)
    report = _diagnose(stage, experiment)
    assert [f.effect for f in report.findings] == ["input_gain"], report.findings
    assert report.findings[0].parameters["input"] == 1
    assert report.findings[0].parameters["gain"] == pytest.approx(1.2, rel=0.02)
