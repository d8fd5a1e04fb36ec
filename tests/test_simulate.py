"""Tests for lrmfrf.simulate: exact simulation, true FRF and transient."""

import control
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrmfrf.plants import wafer_stage
from lrmfrf.simulate import (
    SimulationResult,
    frequency_grid,
    periodic_state,
    simulate,
    transient_frf,
    true_frf,
)

TS = 0.5e-3


@pytest.fixture(scope="module")
def stage():
    return wafer_stage()


def _recursion(system, u, x0):
    """Plain state-space recursion, the reference."""
    A, B = system.A, system.B[:, 0]
    C, D = system.C[0], system.D[0, 0]
    x = np.array(x0, dtype=float)
    y = np.empty(u.size)
    for n, value in enumerate(u):
        y[n] = C @ x + D * value
        x = A @ x + B * value
    return y, x


def _relative(actual, expected):
    return np.max(np.abs(actual - expected)) / np.max(np.abs(expected))


def _assert_matches_recursion(system, u, x0):
    """``simulate`` from ``x0``: output and final state within 1e-9 relative
    of the plain recursion."""
    result = simulate(system, u, 3, x0=x0)
    expected, x_final = _recursion(system, u, x0)
    assert _relative(result.y_h, expected) < 1e-9
    assert _relative(result.x_final, x_final) < 1e-9


def _random_stable_system(seed, n_states, feedthrough):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n_states, n_states))
    A *= 0.95 / max(np.max(np.abs(np.linalg.eigvals(A))), 1e-3)
    B = rng.standard_normal((n_states, 1))
    C = rng.standard_normal((1, n_states))
    return control.ss(A, B, C, [[feedthrough]], TS)


# --- exactness -----------------------------------------------------------------


@pytest.mark.parametrize("output", ["G_y4", "G_z"])
@pytest.mark.parametrize("nonzero_x0", [False, True])
def test_simulate_matches_forced_response(stage, output, nonzero_x0):
    system = getattr(stage, output)
    rng = np.random.default_rng(1)
    u = rng.standard_normal(900)
    x0 = 1e-5 * rng.standard_normal(system.nstates) if nonzero_x0 else None
    result = simulate(system, u, 3, sample_time=TS, x0=x0)
    reference = control.forced_response(
        system, T=np.arange(u.size) * TS, U=u, X0=0.0 if x0 is None else x0
    )
    assert _relative(result.y_h, reference.outputs) < 1e-9
    _, x_final = _recursion(system, u, result.x0)
    np.testing.assert_allclose(result.x_final, x_final, rtol=1e-9, atol=1e-12)


def test_simulate_open_loop_plant_with_double_integrator(stage):
    # defective A (rigid body): the Schur fallback must stay exact
    system = stage.plant[1, 0]
    rng = np.random.default_rng(2)
    u = rng.standard_normal(600)
    x0 = 1e-6 * rng.standard_normal(system.nstates)
    _assert_matches_recursion(system, u, x0)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_states=st.integers(1, 7),
    feedthrough=st.floats(-2.0, 2.0),
)
def test_simulate_matches_recursion_for_random_systems(seed, n_states, feedthrough):
    system = _random_stable_system(seed, n_states, feedthrough)
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(300)
    x0 = rng.standard_normal(n_states)
    result = simulate(system, u, 1, x0=x0)
    expected, x_final = _recursion(system, u, x0)
    assert _relative(result.y_h, expected) < 1e-9
    np.testing.assert_allclose(result.x_final, x_final, rtol=1e-9, atol=1e-9)


def test_static_gain_and_pure_delay():
    u = np.arange(1.0, 7.0)
    gain = control.ss(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), [[2.0]], 1)
    np.testing.assert_array_equal(simulate(gain, u, 2).y_h, 2 * u)
    delay = control.ss([[0.0]], [[1.0]], [[1.0]], [[0.0]], 1.0)
    np.testing.assert_allclose(simulate(delay, u, 2).y_h, [0, 1, 2, 3, 4, 5], atol=0)


def test_downsampling_takes_every_F_th_sample(stage):
    u = np.random.default_rng(3).standard_normal(600)
    result = simulate(stage.G_z, u, 3)
    assert isinstance(result, SimulationResult)
    np.testing.assert_array_equal(result.y_l_clean, result.y_h[::3])
    np.testing.assert_array_equal(result.y_l, result.y_l_clean)
    assert result.noise_std == 0.0 and result.downsampling_factor == 3
    assert result.sample_time == TS


def test_simulate_is_linear(stage):
    rng = np.random.default_rng(4)
    u1, u2 = rng.standard_normal((2, 300))
    y = simulate(stage.G_y4, 2.0 * u1 - 3.0 * u2, 3).y_h
    y1, y2 = simulate(stage.G_y4, u1, 3).y_h, simulate(stage.G_y4, u2, 3).y_h
    assert _relative(y, 2.0 * y1 - 3.0 * y2) < 1e-12


# --- frequency domain -------------------------------------------------------


@pytest.mark.parametrize("n_inputs", [1, 2])
def test_periodic_state_has_no_transient(stage, n_inputs):
    rng = np.random.default_rng(8)
    N = 1200
    if n_inputs == 1:
        system = stage.G_z  # closed loop: stable
        u = rng.standard_normal(N)
    else:
        system = control.drss(6, 2, n_inputs, strictly_proper=True)
        system = control.ss(system.A * 0.95 / max(1, np.max(np.abs(
            np.linalg.eigvals(system.A)))), system.B, system.C, system.D, TS)
        u = rng.standard_normal((n_inputs, N))
    x0 = periodic_state(system, u)
    result = simulate(system, u, 1, x0=x0)
    assert np.max(np.abs(result.x_final - x0)) < 1e-12 * np.max(np.abs(x0))
    # the steady state repeats: a second period starts where the first did
    again = simulate(system, u, 1, x0=result.x_final)
    np.testing.assert_allclose(again.y_h, result.y_h, rtol=0,
                               atol=1e-11 * np.max(np.abs(result.y_h)))
    # and the FRF identity holds without the transient term
    if n_inputs == 1:
        G = true_frf(system, N, one_sided=False)
        Y = np.fft.fft(result.y_h)
        assert _relative(G * np.fft.fft(u), Y) < 1e-10


def test_periodic_state_of_a_free_body_is_an_error(stage):
    with pytest.raises(ValueError, match="no periodic steady state"):
        periodic_state(stage.plant[0, 0], np.ones(100))


@pytest.mark.parametrize("n_samples", [1200, 1201])
def test_fft_identity_with_transient_term(stage, n_samples):
    rng = np.random.default_rng(5)
    u = rng.standard_normal(n_samples)
    x0 = 1e-5 * rng.standard_normal(stage.G_z.nstates)
    result = simulate(stage.G_z, u, 1, x0=x0)
    Y = np.fft.fft(result.y_h)
    G = true_frf(stage.G_z, n_samples, one_sided=False)
    T = transient_frf(stage.G_z, n_samples, result.x0, result.x_final, one_sided=False)
    assert _relative(G * np.fft.fft(u) + T, Y) < 1e-10
    # the transient term matters: without it the identity fails
    assert _relative(G * np.fft.fft(u), Y) > 1e-4


def test_true_frf_matches_control_evaluation(stage):
    n_samples = 1200
    G = true_frf(stage.G_z, n_samples)
    assert G.shape == (601,)
    bins = [1, 7, 204, 293, 366, 600]
    z = np.exp(2j * np.pi * np.array(bins) / n_samples)
    reference = [complex(np.squeeze(stage.G_z(point))) for point in z]
    np.testing.assert_allclose(G[bins], reference, rtol=1e-10)


@pytest.mark.parametrize("n_samples", [10, 11])
def test_true_frf_two_sided_is_conjugate_symmetric(stage, n_samples):
    G = true_frf(stage.G_y4, n_samples, one_sided=False)
    assert G.shape == (n_samples,)
    np.testing.assert_allclose(G[1:], np.conj(G[1:][::-1]), rtol=1e-12)
    np.testing.assert_allclose(
        true_frf(stage.G_y4, n_samples), G[: n_samples // 2 + 1], rtol=1e-12
    )


def test_true_frf_of_integrator_is_infinite_at_dc():
    integrator = control.ss([[1.0]], [[1.0]], [[1.0]], [[0.0]], 1.0)
    G = true_frf(integrator, 4)
    assert not np.isfinite(G[0])
    np.testing.assert_allclose(
        G[1:], 1 / (np.exp(2j * np.pi * np.arange(1, 3) / 4) - 1)
    )


def test_frequency_grid_known_answer():
    np.testing.assert_allclose(
        frequency_grid(1200, TS), np.arange(601) / 0.6, rtol=1e-15
    )
    assert frequency_grid(5, 1.0).tolist() == [0.0, 0.2, 0.4]


# --- noise --------------------------------------------------------------------


def test_noise_level_matches_snr_db(stage):
    # M = 20 000 slow samples: the sample variance of Gaussian noise has a
    # relative std of sqrt(2 / M) = 1 %; 5 % is a 5-sigma tolerance.
    u = np.random.default_rng(6).standard_normal(60_000)
    result = simulate(stage.G_z, u, 3, snr_db=30.0, rng=7)
    expected_std = np.sqrt(np.var(result.y_l_clean) / 10**3.0)
    assert result.noise_std == pytest.approx(expected_std, rel=1e-12)
    assert np.var(result.noise) == pytest.approx(expected_std**2, rel=0.05)
    measured_snr = 10 * np.log10(np.var(result.y_l_clean) / np.var(result.noise))
    assert measured_snr == pytest.approx(30.0, abs=0.25)
    assert abs(np.mean(result.noise)) < 5 * expected_std / np.sqrt(20_000)


def test_noise_std_and_seeding(stage):
    u = np.random.default_rng(8).standard_normal(30_000)
    first = simulate(stage.G_y4, u, 3, noise_std=2e-7, rng=11)
    again = simulate(stage.G_y4, u, 3, noise_std=2e-7, rng=np.random.default_rng(11))
    np.testing.assert_array_equal(first.y_l, again.y_l)
    assert first.noise_std == 2e-7
    # 10 000 samples: relative std of the sample std is 0.7 %; allow 4 %
    assert np.std(first.noise) == pytest.approx(2e-7, rel=0.04)
    other = simulate(stage.G_y4, u, 3, noise_std=2e-7, rng=12)
    assert not np.array_equal(first.y_l, other.y_l)


# --- bad input ----------------------------------------------------------------


def test_rejects_non_state_space_and_continuous_and_mimo_shape(stage):
    """MIMO systems are simulated since issue 13 (this test pinned their
    refusal before); a record whose channels do not match the inputs is
    refused."""
    u = np.zeros(6)
    with pytest.raises(TypeError, match="must be a control.StateSpace or "
                       "TransferFunction"):
        simulate(control.frd([1.0, 2.0], [0.1, 0.2]), u, 3)
    with pytest.raises(ValueError, match="must be discrete-time"):
        simulate(stage.plant_continuous[0, 0], u, 3)
    two_inputs = control.ss([[0.5]], [[1.0, 2.0]], [[1.0]], [[0.0, 0.0]], TS)
    with pytest.raises(ValueError, match=r"shape \(n_u, N\) = \(2, N\)"):
        simulate(two_inputs, u, 3)
    with pytest.raises(ValueError, match=r"shape \(n_u, N\) = \(2, N\)"):
        simulate(two_inputs, np.zeros((3, 6)), 3)


def test_rejects_mismatched_sample_time(stage):
    with pytest.raises(ValueError, match="does not match system.dt"):
        simulate(stage.G_y4, np.zeros(6), 3, sample_time=1.5e-3)
    with pytest.raises(ValueError, match="`sample_time` must be a positive, finite"):
        simulate(stage.G_y4, np.zeros(6), 3, sample_time=-1.0)


def test_rejects_bad_input_signal(stage):
    with pytest.raises(ValueError, match="u_h contains NaN or inf"):
        simulate(stage.G_y4, np.array([0.0, np.nan, 0.0]), 3)
    with pytest.raises(ValueError, match="u_h must be 1-D"):
        simulate(stage.G_y4, np.zeros((3, 2)), 3)
    with pytest.raises(ValueError, match="not a multiple of F=3"):
        simulate(stage.G_y4, np.zeros(7), 3)
    with pytest.raises(ValueError, match="u_h is empty"):
        simulate(stage.G_y4, np.zeros(0), 3)
    with pytest.raises(TypeError, match="u_h must be real-valued"):
        simulate(stage.G_y4, np.zeros(3, dtype=complex), 3)
    with pytest.raises(TypeError, match="u_h must be a real numeric array"):
        simulate(stage.G_y4, ["a", "b", "c"], 3)


@pytest.mark.parametrize(
    ("F", "error", "message"),
    [
        (0, ValueError, "positive integer"),
        (2.5, ValueError, "positive integer"),
        ("3", TypeError, "positive integer"),
    ],
)
def test_rejects_bad_downsampling_factor(stage, F, error, message):
    with pytest.raises(error, match=message):
        simulate(stage.G_y4, np.zeros(6), F)


def test_rejects_bad_noise_settings(stage):
    u = np.random.default_rng(9).standard_normal(30)
    with pytest.raises(ValueError, match="either snr_db or noise_std, not both"):
        simulate(stage.G_y4, u, 3, snr_db=40.0, noise_std=1e-6)
    with pytest.raises(ValueError, match="noise_std must be >= 0"):
        simulate(stage.G_y4, u, 3, noise_std=-1.0)
    with pytest.raises(ValueError, match="noise_std must be a finite number"):
        simulate(stage.G_y4, u, 3, noise_std=np.nan)
    with pytest.raises(ValueError, match="snr_db must be a finite number"):
        simulate(stage.G_y4, u, 3, snr_db=np.inf)
    with pytest.raises(ValueError, match="zero variance"):
        simulate(stage.G_y4, np.zeros(30), 3, snr_db=40.0)
    with pytest.raises(TypeError, match="`rng` must be None, an int seed"):
        simulate(stage.G_y4, u, 3, noise_std=1.0, rng=0.5)


def test_rejects_bad_states_and_lengths(stage):
    with pytest.raises(ValueError, match=r"x0 must have shape \(14,\)"):
        simulate(stage.G_y4, np.zeros(6), 3, x0=np.zeros(3))
    with pytest.raises(ValueError, match="x0 contains NaN or inf"):
        simulate(stage.G_y4, np.zeros(6), 3, x0=np.full(14, np.nan))
    with pytest.raises(ValueError, match=r"x_final must have shape \(14,\)"):
        transient_frf(stage.G_y4, 6, np.zeros(14), np.zeros(2))
    with pytest.raises(ValueError, match="`n_samples` must be an integer >= 1"):
        true_frf(stage.G_y4, 0)
    with pytest.raises(TypeError, match="`n_samples` must be an integer >= 1"):
        true_frf(stage.G_y4, 10.5)
    with pytest.raises(ValueError, match="`sample_time` must be a positive, finite"):
        frequency_grid(10, 0.0)


def test_parameter_checks_are_the_package_ones(stage):
    """One rule per kind of value across the package (issue 12, item 9): a
    whole float is a valid count, as for every other integer parameter."""
    np.testing.assert_array_equal(true_frf(stage.G_y4, 10.0),
                                  true_frf(stage.G_y4, 10))
    np.testing.assert_array_equal(frequency_grid(10.0, 1e-3),
                                  frequency_grid(10, 1e-3))


def test_simulate_accepts_a_transfer_function():
    """As `diagnose` does: a discrete TransferFunction is converted with
    control.ss. A 2nd-order tf against scipy's lfilter of the same
    polynomials (1e-12 relative: both are exact recursions, rounding only);
    true_frf against the polynomial ratio; transient_frf closes the DFT
    identity Y = G U + T of the converted realisation."""
    from scipy.signal import lfilter

    b, a = [0.2, 0.1, 0.0], [1.0, -1.2, 0.5]
    tf = control.tf(b, a, 1e-3)
    u = np.random.default_rng(4).standard_normal(600)
    result = simulate(tf, u, 3, noise_std=0.0)
    expected = lfilter(b, a, u)
    np.testing.assert_allclose(result.y_h, expected, rtol=1e-12,
                               atol=1e-12 * np.abs(expected).max())
    np.testing.assert_array_equal(result.y_l, result.y_h[::3])
    z = np.exp(2j * np.pi * np.arange(301) / 600)
    np.testing.assert_allclose(true_frf(tf, 600), np.polyval(b, z) / np.polyval(a, z),
                               rtol=1e-12)
    G = true_frf(tf, 600, one_sided=False)
    T = transient_frf(tf, 600, result.x0, result.x_final, one_sided=False)
    Y = np.fft.fft(result.y_h)
    np.testing.assert_allclose(Y, G * np.fft.fft(u) + T, atol=1e-10 * np.abs(Y).max())


def test_inputs_are_never_modified(stage):
    rng = np.random.default_rng(10)
    u = rng.standard_normal(300)
    x0 = 1e-6 * rng.standard_normal(stage.G_z.nstates)
    u_copy, x0_copy = u.copy(), x0.copy()
    result = simulate(stage.G_z, u, 3, x0=x0, snr_db=40.0, rng=1)
    np.testing.assert_array_equal(u, u_copy)
    np.testing.assert_array_equal(x0, x0_copy)
    result.u_h[:] = 0.0  # the result holds copies
    np.testing.assert_array_equal(u, u_copy)


def test_uncoupled_blocks_in_any_state_order_match_recursion(stage):
    """The plant's modes are uncoupled blocks of A (simulated separately);
    shuffle the states so the blocks interleave, and give one block no output:
    output and final state still match the plain recursion."""
    system = stage.plant[1, 0]
    rng = np.random.default_rng(11)
    order = rng.permutation(system.nstates)
    A = system.A[np.ix_(order, order)]
    B, C = system.B[order], system.C[:, order].copy()
    C[0, order.tolist().index(4)] = 0.0  # mode 2's first state: output row...
    C[0, order.tolist().index(5)] = 0.0  # ...and its second: no output
    shuffled = control.ss(A, B, C, [[0.3]], TS)
    u = rng.standard_normal(900)
    x0 = 1e-6 * rng.standard_normal(system.nstates)
    _assert_matches_recursion(shuffled, u, x0)
