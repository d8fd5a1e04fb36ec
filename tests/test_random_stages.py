"""Tests for lrmfrf.plants.random_stages: random stages with checked loops."""

import doctest

import numpy as np
import pytest

import lrmfrf.plants.random_stages as random_module
from lrmfrf.plants import MIMOWaferStage, WaferStage, random_stage

TS = 0.5e-3
SEEDS = range(8)


@pytest.fixture(scope="module")
def stages():
    return [random_stage(seed) for seed in SEEDS]


def test_same_seed_same_stage_and_seeds_differ(stages):
    again, draw = random_stage(0)
    np.testing.assert_array_equal(again.G_z.A, stages[0][0].G_z.A)
    assert draw == stages[0][1]
    assert not np.array_equal(stages[1][0].plant.A.shape, stages[0][0].plant.A.shape) \
        or not np.allclose(stages[1][0].plant.A, stages[0][0].plant.A)


def test_drawn_ranges(stages):
    for stage, draw in stages:
        assert isinstance(stage, WaferStage)
        assert 2 <= draw.downsampling_factor <= 5
        assert stage.downsampling_factor == draw.downsampling_factor
        assert 2 <= len(stage.modes) <= 6
        for mode in stage.modes:
            assert 80.0 <= mode.frequency_hz <= 0.95 / (2 * TS)
            assert 0.003 <= mode.damping <= 0.03
            assert 0.02 <= mode.participation_y4 <= 0.4  # collocated: positive
            assert 0.1 <= abs(mode.participation_z) <= 1.5
        assert 1.0 <= stage.mass <= 20.0


def test_every_loop_is_stable_with_the_margins(stages):
    for stage, _ in stages:
        for system in (stage.G_y4, stage.G_z):
            assert np.max(np.abs(np.linalg.eigvals(system.A))) < 1.0
        margins = stage.margins()
        assert margins.phase_margin >= 30.0 and margins.gain_margin >= 2.0
        assert 15.0 <= margins.crossover_hz <= 90.0  # drawn bandwidth 20-80 Hz


def test_placed_modes_alias_onto_their_partner(stages):
    """Mode i of a pair lies at j f_slow +- f_partner (1 + d), |d| <= 3 %."""
    with_pairs = 0
    for _, draw in stages:
        slow_rate = 1.0 / (draw.downsampling_factor * TS)
        f = draw.frequencies_hz
        for i, j in draw.aliasing_pairs:
            distance = min(
                abs(f[i] - (m * slow_rate + s * f[j]))
                for m in range(1, draw.downsampling_factor + 1)
                for s in (-1.0, 1.0)
            )
            assert distance <= 0.03 * f[j] + 1e-9
        with_pairs += bool(draw.aliasing_pairs)
    assert with_pairs >= 6  # most stages have at least one aliased pair


def test_open_loop_stage_gives_the_plant_channels():
    stage, _ = random_stage(3, loop="open")
    np.testing.assert_array_equal(stage.G_y4.A, stage.plant[0, 0].A)
    np.testing.assert_array_equal(stage.G_z.C, stage.plant[1, 0].C)
    assert stage.margins().phase_margin >= 30.0  # the controller is still checked


def test_open_loop_stage_is_suspended_closed_loop_stage_is_free():
    stage, draw = random_stage(3, loop="open")
    frequency, damping = stage.suspension
    assert 2.0 <= frequency <= 10.0 and 0.05 <= damping <= 0.2
    # known answer: the body's poles are -zeta w_s +- j w_s sqrt(1 - zeta^2)
    w = 2 * np.pi * frequency
    expected = np.array([-damping * w + 1j * w * np.sqrt(1 - damping**2)])
    poles = np.linalg.eigvals(stage.plant_continuous.A)
    assert np.min(np.abs(poles - expected)) < 1e-9 * w
    assert np.max(np.abs(np.linalg.eigvals(stage.plant.A))) < 1.0  # stable
    # the closed-loop stage of the same seed: a free body (a double pole at 0)
    # and the same draw (the suspension comes from a child generator)
    closed, closed_draw = random_stage(3)
    assert closed.suspension is None
    assert np.sum(np.abs(np.linalg.eigvals(closed.plant_continuous.A)) < 1e-12) == 2
    assert closed_draw == draw and closed.modes == stage.modes
    # a given suspension, or a free body in open loop
    given, _ = random_stage(3, loop="open", suspension=(4.0, 0.1))
    assert given.suspension == (4.0, 0.1)
    free, _ = random_stage(3, loop="open", suspension=False)
    assert free.suspension is None


def test_given_F_and_number_of_modes():
    stage, draw = random_stage(5, n_modes=4, downsampling_factor=2)
    assert len(stage.modes) == 4 and draw.downsampling_factor == 2


def test_mimo_stages():
    for seed in range(2):
        stage, draw = random_stage(seed, mimo=True)
        assert isinstance(stage, MIMOWaferStage)
        assert (stage.G.noutputs, stage.G.ninputs) == (5, 4)
        assert np.max(np.abs(np.linalg.eigvals(stage.G.A))) < 1.0
        for m in stage.margins().values():
            assert m.phase_margin >= 30.0
        assert len(stage.modes) == len(draw.frequencies_hz)


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"loop": "half"}, ValueError, "`loop` must be"),
        ({"loop": "open", "mimo": True}, ValueError, "SISO"),
        ({"mimo": True, "suspension": True}, ValueError, "`suspension` is for SISO"),
        ({"suspension": (0.0, 0.1)}, ValueError, "suspension frequency"),
        ({"suspension": (5.0, 1.5)}, ValueError, "suspension damping"),
        ({"suspension": "soft"}, TypeError, "pair"),
        ({"n_modes": 0}, ValueError, "`n_modes`"),
        ({"downsampling_factor": 0}, ValueError, "`downsampling_factor`"),
        ({"min_phase_margin": 89.0, "max_tries": 2}, RuntimeError, "no random stage"),
    ],
)
def test_bad_settings(kwargs, error, match):
    with pytest.raises(error, match=match):
        random_stage(0, **kwargs)


def test_docstring_examples_run():
    result = doctest.testmod(random_module)
    assert result.attempted > 0 and result.failed == 0
