"""simulate_slow_feedback (issue 13): the exact slow-rate closed loop against
a plain sample-by-sample loop, shapes, noise in the loop, errors."""

import control
import numpy as np
import pytest

from lrmfrf.plants import lead_pid_controller, mimo_wafer_stage, wafer_stage
from lrmfrf.plants.mimo_stage import _decoupled_controller, _rigid_controllers
from lrmfrf.simulate import FeedbackSimulationResult, simulate_slow_feedback

F = 3


def _matrices(system):
    return [np.asarray(m, dtype=float).reshape(shape) for m, shape in (
        (system.A, (system.nstates, system.nstates)),
        (system.B, (system.nstates, system.ninputs)),
        (system.C, (system.noutputs, system.nstates)),
        (system.D, (system.noutputs, system.ninputs)))]


def _plain_loop(plant, controller, r, feedback, noise):
    """Sample by sample: at n = m F read y_l(m) = y(mF) + v(m) (solving the
    algebraic loop through D and D_c), update the controller, hold c."""
    A, B, C, D = _matrices(plant)
    Ac, Bc, Cc, Dc = _matrices(controller)
    n_u, n_samples = r.shape
    select = np.eye(C.shape[0])[list(feedback)]
    x, xc = np.zeros(A.shape[0]), np.zeros(Ac.shape[0])
    u, y = np.zeros((n_u, n_samples)), np.zeros((C.shape[0], n_samples))
    for n in range(n_samples):
        if n % F == 0:
            v = noise[list(feedback), n // F]
            W = np.linalg.inv(np.eye(n_u) + Dc @ select @ D)
            c = W @ (Cc @ xc + Dc @ (select @ (C @ x + D @ r[:, n]) + v))
            y_fb = select @ (C @ x + D @ (r[:, n] - c)) + v
            xc = Ac @ xc + Bc @ y_fb
        u[:, n] = r[:, n] - c
        y[:, n] = C @ x + D @ u[:, n]
        x = A @ x + B @ u[:, n]
    return u, y


def _relative(actual, expected):
    return np.max(np.abs(actual - expected)) / np.max(np.abs(expected))


def test_mimo_stage_matches_plain_loop():
    """MIMO stage plant (double integrators: the plain loop's rounding grows)
    with a 20 Hz decoupled controller at F Ts on the encoders, noise in the
    loop: u_h to 1e-11, y_h to 1e-9 relative (measured 1.9e-13, 1.0e-10)."""
    stage = mimo_wafer_stage()
    ts = stage.sample_time
    controller = _decoupled_controller(
        _rigid_controllers(20.0, (stage.mass, *stage.inertia), F * ts),
        stage.sensor_decoupling, stage.actuator_decoupling, F * ts)
    r = np.random.default_rng(0).standard_normal((4, 1200))
    result = simulate_slow_feedback(stage.plant, controller, r, F,
                                    feedback_outputs=(0, 1, 2, 3),
                                    noise_std=1e-6, rng=1)
    assert isinstance(result, FeedbackSimulationResult)
    assert result.y_l.shape == (5, 400) and result.u_h.shape == (4, 1200)
    assert result.controller_output.shape == (4, 400)
    u, y = _plain_loop(stage.plant, controller, r, (0, 1, 2, 3), result.noise)
    assert _relative(result.u_h, u) < 1e-11
    assert _relative(result.y_h, y) < 1e-9
    np.testing.assert_array_equal(result.y_l, result.y_h[:, ::F] + result.noise)
    np.testing.assert_array_equal(result.r, r)


def test_siso_with_feedthroughs_and_snr_matches_plain_loop():
    """Feedthrough in plant and controller (an algebraic loop at each slow
    sample) and a subset of outputs fed back: 1e-12 relative."""
    plant = control.ss([[0.5, 0.2], [0.0, 0.3]], [[1.0], [0.5]],
                       [[1.0, 0.3], [0.2, -1.0]], [[0.4], [0.1]], 1.0)
    controller = control.ss([[0.7]], [[1.0]], [[0.5]], [[0.3]], 3.0)
    r = np.random.default_rng(2).standard_normal(300)
    result = simulate_slow_feedback(plant, controller, r, F, feedback_outputs=[1],
                                    snr_db=20.0, rng=3)
    assert result.u_h.shape == (300,) and result.y_l.shape == (2, 100)
    u, y = _plain_loop(plant, controller, r[None], (1,), result.noise)
    assert _relative(result.u_h, u[0]) < 1e-12
    assert _relative(result.y_h, y) < 1e-12
    # snr_db per output, relative to the noise-free closed loop
    clean = simulate_slow_feedback(plant, controller, r, F, feedback_outputs=[1])
    np.testing.assert_allclose(
        result.noise_std, np.sqrt(np.var(clean.y_l, axis=1) / 100.0), rtol=1e-12)


def test_siso_shapes_and_known_answer():
    plant = control.ss([[0.9]], [[1.0]], [[1.0]], [[0.0]], 1e-3)
    controller = control.ss([], [], [], [[0.2]], 3e-3)
    result = simulate_slow_feedback(plant, controller, np.ones(6), 3)
    # y(3) = 1 + 0.9 + 0.81 = 2.71, c = 0.2 * 2.71
    np.testing.assert_allclose(result.u_h, [1, 1, 1, 0.458, 0.458, 0.458],
                               rtol=1e-14)
    assert result.y_l.shape == (2,) and result.noise_std == 0.0
    assert result.controller_output.shape == (2,)


def test_stage_in_slow_feedback_is_reproducible_and_noisy_in_the_loop():
    stage = wafer_stage()
    controller = lead_pid_controller(20.0, stage.mass,
                                     sample_time=F * stage.sample_time)
    r = np.random.default_rng(4).standard_normal(3000)
    plant = stage.plant[0, 0]
    first = simulate_slow_feedback(plant, controller, r, F, noise_std=1e-7, rng=5)
    again = simulate_slow_feedback(plant, controller, r, F, noise_std=1e-7, rng=5)
    np.testing.assert_array_equal(first.y_l, again.y_l)
    clean = simulate_slow_feedback(plant, controller, r, F)
    # the noise enters the loop: the plant input changes
    assert not np.allclose(first.u_h, clean.u_h, rtol=0, atol=1e-12)


def test_errors():
    plant = control.ss([[0.9]], [[1.0]], [[1.0]], [[0.0]], 1e-3)
    slow = control.ss([], [], [], [[0.2]], 3e-3)
    r = np.ones(6)
    with pytest.raises(ValueError, match=r"must be F \* plant.dt"):
        simulate_slow_feedback(plant, control.ss([], [], [], [[0.2]], 1e-3), r, 3)
    with pytest.raises(ValueError, match="controller must be discrete-time"):
        simulate_slow_feedback(plant, control.ss([], [], [], [[0.2]]), r, 3)
    with pytest.raises(TypeError, match="controller must be a control.StateSpace"):
        simulate_slow_feedback(plant, 0.2, r, 3)
    with pytest.raises(ValueError, match="n_u = 1 outputs"):
        simulate_slow_feedback(plant, control.ss([], [], [], [[0.2], [0.1]], 3e-3),
                               r, 3)
    with pytest.raises(ValueError, match="distinct output indices"):
        simulate_slow_feedback(plant, slow, r, 3, feedback_outputs=[1])
    with pytest.raises(ValueError, match="does not stabilise the loop"):
        simulate_slow_feedback(plant, control.ss([], [], [], [[5.0]], 3e-3), r, 3)
    with pytest.raises(ValueError, match="algebraically singular"):
        simulate_slow_feedback(control.ss([], [], [], [[1.0]], 1e-3),
                               control.ss([], [], [], [[-1.0]], 3e-3), r, 3)
    with pytest.raises(ValueError, match="not a multiple of F=3"):
        simulate_slow_feedback(plant, slow, np.ones(7), 3)
    with pytest.raises(ValueError, match="either snr_db or noise_std"):
        simulate_slow_feedback(plant, slow, r, 3, snr_db=1.0, noise_std=1.0)
