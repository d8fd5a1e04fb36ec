"""MIMO simulation (issue 13): exactness against python-control and the DFT
identity, per-output noise, shapes, SISO unchanged."""

import control
import numpy as np
import pytest

from lrmfrf.plants import mimo_wafer_stage, wafer_stage
from lrmfrf.simulate import simulate, transient_frf, true_frf

TS = 0.5e-3


@pytest.fixture(scope="module")
def stage():
    return mimo_wafer_stage()


def _relative(actual, expected):
    return np.max(np.abs(actual - expected)) / np.max(np.abs(expected))


@pytest.mark.parametrize("which", ["G", "plant"])
def test_mimo_simulate_matches_forced_response(stage, which):
    """Closed loop (26 coupled states) and open-loop plant (rigid-body double
    integrators, Schur path) against control.forced_response: 1e-9 relative
    (both are exact recursions; rounding only)."""
    system = getattr(stage, which)
    rng = np.random.default_rng(1)
    u = rng.standard_normal((4, 900))
    x0 = 1e-5 * rng.standard_normal(system.nstates)
    result = simulate(system, u, 3, x0=x0)
    reference = control.forced_response(
        system, T=np.arange(900) * TS, U=u, X0=x0, return_x=True
    )
    assert result.y_h.shape == (5, 900) and result.y_l.shape == (5, 300)
    assert _relative(result.y_h, reference.outputs) < 1e-9
    np.testing.assert_array_equal(result.y_l, result.y_h[:, ::3])
    # forced_response has no x(N): one more step of the recursion
    x_end = system.A @ reference.states[:, -1] + system.B @ u[:, -1]
    assert _relative(result.x_final, x_end) < 1e-9


@pytest.mark.parametrize("n_samples", [1200, 1201])
def test_mimo_fft_identity_per_entry(stage, n_samples):
    """Y_o = sum_i G_oi U_i + T_o for every output, 1e-10 relative; the
    transient term matters."""
    rng = np.random.default_rng(2)
    u = rng.standard_normal((4, n_samples))
    x0 = 1e-5 * rng.standard_normal(stage.G.nstates)
    result = simulate(stage.G, u, 1, x0=x0)
    G = true_frf(stage.G, n_samples, one_sided=False)
    T = transient_frf(stage.G, n_samples, result.x0, result.x_final, one_sided=False)
    assert G.shape == (5, 4, n_samples) and T.shape == (5, n_samples)
    Y = np.fft.fft(result.y_h, axis=-1)
    steady = np.einsum("oik,ik->ok", G, np.fft.fft(u, axis=-1))
    for output in range(5):
        assert _relative(steady[output] + T[output], Y[output]) < 1e-10
    assert _relative(steady, Y) > 1e-4


def test_mimo_true_frf_matches_control_evaluation(stage):
    G = true_frf(stage.G, 1200)
    assert G.shape == (5, 4, 601)
    for k in (1, 204, 600):
        expected = stage.G(np.exp(2j * np.pi * k / 1200))
        np.testing.assert_allclose(G[:, :, k], expected, rtol=1e-9, atol=1e-9 *
                                   np.abs(expected).max())


def test_siso_results_unchanged_and_one_channel_record():
    """A SISO system gives identical numbers as a 1-D record (as before) and
    as a (1, N) record (2-D out)."""
    siso = wafer_stage().G_z
    u = np.random.default_rng(3).standard_normal(600)
    flat = simulate(siso, u, 3, snr_db=30.0, rng=4)
    two_d = simulate(siso, u[np.newaxis], 3, snr_db=30.0, rng=4)
    assert flat.y_l.shape == (200,) and two_d.y_l.shape == (1, 200)
    np.testing.assert_array_equal(two_d.y_h[0], flat.y_h)
    np.testing.assert_array_equal(two_d.y_l[0], flat.y_l)
    np.testing.assert_array_equal(two_d.noise_std, [flat.noise_std])


def test_single_input_mimo_accepts_1d_record(stage):
    system = stage.G[:, 0]
    u = np.random.default_rng(5).standard_normal(600)
    one = simulate(system, u, 3)
    two = simulate(system, u[np.newaxis], 3)
    assert one.y_l.shape == (5, 200)
    np.testing.assert_array_equal(one.y_h, two.y_h)


def test_mimo_noise_per_output_channel(stage):
    """snr_db sets each output's noise from that output's own variance; a
    per-output noise_std is used as given. M = 20 000: 5 % on the variance is
    a 5-sigma tolerance."""
    u = np.random.default_rng(6).standard_normal((4, 60_000))
    result = simulate(stage.G, u, 3, snr_db=30.0, rng=7)
    expected = np.sqrt(np.var(result.y_l_clean, axis=1) / 1e3)
    np.testing.assert_allclose(result.noise_std, expected, rtol=1e-12)
    np.testing.assert_allclose(np.var(result.noise, axis=1), expected**2, rtol=0.05)
    stds = np.array([1e-7, 2e-7, 0.0, 3e-7, 1e-6])
    given = simulate(stage.G, u, 3, noise_std=stds, rng=8)
    np.testing.assert_array_equal(given.noise_std, stds)
    np.testing.assert_allclose(np.std(given.noise, axis=1), stds, rtol=0.05)
    assert np.all(given.noise[2] == 0.0)


def test_mimo_rejects_bad_noise_settings(stage):
    u = np.random.default_rng(9).standard_normal((4, 30))
    with pytest.raises(ValueError, match=r"one value per output channel, shape \(5,\)"):
        simulate(stage.G, u, 3, noise_std=[1.0, 2.0])
    with pytest.raises(ValueError, match="output 1: noise_std must be >= 0"):
        simulate(stage.G, u, 3, noise_std=[1.0, -1.0, 0, 0, 0])
    zero_row = control.ss(stage.G.A, stage.G.B, np.vstack([stage.G.C[:1], 0 *
                          stage.G.C[:1]]), np.zeros((2, 4)), TS)
    with pytest.raises(ValueError, match="output 1: snr_db cannot set"):
        simulate(zero_row, u, 3, snr_db=40.0)
