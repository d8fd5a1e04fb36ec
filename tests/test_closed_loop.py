"""plant_from_closed_loop (issue 13): the known open-loop plant recovered from
exact closed-loop FRFs (fast- and slow-rate loops, SISO, SIMO and MIMO), from
an LRM fit of noise-free slow-feedback data, and the first-order std against
a Monte Carlo. The estimates are fakes with the contract attributes, so these
tests do not depend on the MIMO estimators."""

from types import SimpleNamespace

import control
import numpy as np
import pytest
from sklearn.exceptions import NotFittedError

import lrmfrf
from lrmfrf import LRMBeyondNyquist, plant_from_closed_loop
from lrmfrf.plants import lead_pid_controller, mimo_wafer_stage, wafer_stage
from lrmfrf.plants.mimo_stage import _decoupled_controller, _rigid_controllers
from lrmfrf.signals import multisine
from lrmfrf.simulate import frequency_grid, simulate_slow_feedback, true_frf

F = 3
N = 1200
ENCODERS = (0, 1, 2, 3)


@pytest.fixture(scope="module")
def mimo():
    stage = mimo_wafer_stage()
    slow = _decoupled_controller(
        _rigid_controllers(20.0, (stage.mass, *stage.inertia), F * stage.sample_time),
        stage.sensor_decoupling, stage.actuator_decoupling, F * stage.sample_time,
    )
    return stage, slow


@pytest.fixture(scope="module")
def siso():
    stage = wafer_stage()
    slow = lead_pid_controller(20.0, stage.mass, sample_time=F * stage.sample_time)
    return stage, slow


def _fake(frf, sample_time, *, std=None, cov=None, valid=None):
    """A fitted estimate with the contract attributes (1-D frf_ for SISO)."""
    n_outputs, n_inputs = (1, 1) if frf.ndim == 1 else frf.shape[:2]
    finite = np.isfinite(frf)
    fake = SimpleNamespace(
        frequencies_=frequency_grid(2 * (frf.shape[-1] - 1), sample_time),
        frf_=frf,
        frf_std_=np.zeros(frf.shape) if std is None else std,
        valid_=finite if valid is None else valid,
        sample_time_=sample_time,
        downsampling_factor_=F,
        n_inputs_=n_inputs,
        n_outputs_=n_outputs,
        n_experiments_=1,
    )
    if cov is not None:
        fake.frf_cov_ = cov
    return fake


def _slow_equivalent(plant_frf, controller_frf, feedback):
    """The forward map of a slow-rate loop, written plainly per slow bin:
    G_eq(k + fM) = (I + Lam(k) C_l(k) S)^-1 P(k + fM), Lam(k) = (1/F) sum_f
    P(k + fM) H(k + fM). plant_frf (n_y, n_u, N) two-sided, controller_frf
    (n_u, n_fb, M) on the slow grid; returns the one-sided G_eq."""
    n_outputs, _, n_samples = plant_frf.shape
    slow = n_samples // F
    hold = np.exp(-2j * np.pi * np.outer(np.arange(n_samples), np.arange(F))
                  / n_samples).sum(axis=1)
    equivalent = np.empty_like(plant_frf)
    for k in range(slow):
        bands = k + slow * np.arange(F)
        lam = sum(plant_frf[:, :, q] * hold[q] for q in bands) / F
        loop = np.eye(n_outputs, dtype=complex)
        loop[:, feedback] += lam @ controller_frf[:, :, k]
        for q in bands:
            equivalent[:, :, q] = np.linalg.solve(loop, plant_frf[:, :, q])
    return equivalent[:, :, : n_samples // 2 + 1]


def _relative_error(actual, expected):
    """Per bin, max over entries of |actual - expected| / max |expected|."""
    axes = tuple(range(actual.ndim - 1))
    return (np.abs(actual - expected).max(axis=axes, initial=0.0)
            / np.abs(expected).max(axis=axes, initial=0.0))


# --- exact recovery ----------------------------------------------------------


def test_fast_loop_mimo_recovers_plant(mimo):
    """MIMO stage, controller on the encoders: P = G (I - C G_fb)^-1 from the
    exact closed loop (true_frf of the 26-state closed loop). The data's own
    rounding (about 1e-16 |C P| relative in G, where G ~ 1/C) is amplified by
    the loop gain |C P| again in I - C G: the bound is 1e-11 (1 + ||C P||)^2
    (measured: at most 1.3e-14 (1 + ||C P||)^2, 4.6e-9 at the first bin
    where ||C P|| = 590) and 1e-11 where the loop gain is < 1 (measured
    8.2e-12, at the Nyquist bin where the ZOH plant is small)."""
    stage, _ = mimo
    estimate = _fake(true_frf(stage.G, N), stage.sample_time)
    result = plant_from_closed_loop(estimate, stage.controller, (0, 1, 2, 3))
    truth = true_frf(stage.plant, N)
    assert result.frf_.shape == (5, 4, N // 2 + 1) and result.loop_rate_ == "fast"
    z = np.exp(2j * np.pi * np.arange(N // 2 + 1) / N)
    C = stage.controller(z)
    bins = np.arange(1, N // 2 + 1)  # DC: integrators in plant and controller
    assert not result.valid_[..., 0].any()
    assert result.valid_[..., bins].all()
    loop_gain = np.array([np.linalg.norm(C[:, :, k] @ truth[:4, :, k], 2)
                          for k in bins])
    error = _relative_error(result.frf_[..., bins], truth[..., bins])
    assert np.all(error <= 1e-11 * (1 + loop_gain) ** 2)
    assert error[loop_gain < 1].max() < 1e-11


def test_fast_loop_siso_and_simo_recover_plant(siso):
    """SISO stage: y4 fed back; SISO and SIMO (y4 and z, feedback_outputs=[0])
    within the loop-gain bound of the MIMO test, 1e-11 (1 + |C P|)^2."""
    stage, _ = siso
    bins = np.arange(1, N // 2 + 1)
    z = np.exp(2j * np.pi * bins / N)
    truth = true_frf(stage.plant, N)  # (2, 1, K): outputs y4, z
    bound = 1e-11 * (1 + np.abs(np.squeeze(stage.controller(z)) * truth[0, 0, bins]))**2
    one = plant_from_closed_loop(_fake(true_frf(stage.G_y4, N), stage.sample_time),
                                 stage.controller)
    assert one.frf_.shape == (N // 2 + 1,) and not one.valid_[0]
    assert np.all(_relative_error(one.frf_[bins], truth[0, 0, bins]) <= bound)
    both = np.stack([true_frf(stage.G_y4, N), true_frf(stage.G_z, N)])[:, None]
    simo = plant_from_closed_loop(_fake(both, stage.sample_time), stage.controller,
                                  feedback_outputs=[0])
    assert simo.frf_.shape == (2, 1, N // 2 + 1)
    assert np.all(_relative_error(simo.frf_[..., bins], truth[..., bins]) <= bound)


def test_slow_loop_mimo_recovers_plant(mimo):
    """Slow-rate loop (controller at F Ts on the encoders), G_eq from the
    forward formula: recovered to 1e-11 relative (measured 1.8e-12); the
    bands of slow DC (bins 0 and M) are invalid (controller integrators)."""
    stage, slow = mimo
    plant = true_frf(stage.plant, N, one_sided=False)
    equivalent = _slow_equivalent(plant, true_frf(slow, N // F, one_sided=False),
                                  [0, 1, 2, 3])
    result = plant_from_closed_loop(_fake(equivalent, stage.sample_time), slow,
                                    (0, 1, 2, 3))
    assert result.loop_rate_ == "slow"
    invalid = np.flatnonzero(~result.valid_[0, 0])
    np.testing.assert_array_equal(invalid, [0, N // F])
    assert np.all(np.isnan(result.frf_[..., invalid]))
    ok = result.valid_[0, 0]
    error = _relative_error(result.frf_[..., ok], plant[..., : N // 2 + 1][..., ok])
    assert error.max() < 1e-11


def test_slow_loop_siso_and_simo_recover_plant(siso):
    stage, slow = siso
    plant = true_frf(stage.plant, N, one_sided=False)  # (2, 1, N)
    controller = true_frf(slow, N // F, one_sided=False)[None, None]
    equivalent = _slow_equivalent(plant, controller, [0])
    simo = plant_from_closed_loop(_fake(equivalent, stage.sample_time), slow, [0])
    one = plant_from_closed_loop(_fake(equivalent[0, 0], stage.sample_time), slow)
    ok = one.valid_
    assert ok.sum() == N // 2 - 1  # bins 0 and M
    np.testing.assert_array_equal(simo.valid_[0, 0], ok)
    truth = plant[..., : N // 2 + 1]
    assert _relative_error(one.frf_[ok], truth[0, 0, ok]).max() < 1e-11
    assert _relative_error(simo.frf_[..., ok], truth[..., ok]).max() < 1e-11
    # SISO is G_eq / (1 - Lam_eq C_l), the same numbers
    np.testing.assert_allclose(one.frf_[ok], simo.frf_[0, 0, ok], rtol=1e-13)


def test_invalid_input_bins_invalidate_their_band_set(mimo):
    """Fast loop: an invalid bin stays invalid alone. Slow loop: it
    invalidates every band k + f M of its slow bin (Lam_eq sums them)."""
    stage, slow = mimo
    plant = true_frf(stage.plant, N, one_sided=False)
    equivalent = _slow_equivalent(plant, true_frf(slow, N // F, one_sided=False),
                                  [0, 1, 2, 3])
    valid = np.ones(equivalent.shape, bool)
    valid[2, 3, 7] = False
    result = plant_from_closed_loop(
        _fake(equivalent, stage.sample_time, valid=valid), slow, ENCODERS)
    invalid = np.flatnonzero(~result.valid_[0, 0])
    M = N // F
    np.testing.assert_array_equal(invalid, [0, 7, M - 7, M, M + 7])
    assert np.all(np.isnan(result.frf_std_[..., invalid]))
    fast = plant_from_closed_loop(
        _fake(true_frf(stage.G, N), stage.sample_time, valid=valid),
        stage.controller, ENCODERS)
    np.testing.assert_array_equal(np.flatnonzero(~fast.valid_[0, 0]), [0, 7])


# --- end to end -------------------------------------------------------------------


def test_lrm_on_noise_free_slow_feedback_data(siso):
    """SISO LRMBeyondNyquist fitted from r to y_l simulated in slow-rate
    feedback (noise-free, from rest: with transient), then the plant: the
    error of P follows the error of the G_eq estimate, amplified by at most
    the loop gain |Lam C_l|: measured median 3e-11, max 3.2e-8 where the loop
    gain < 1; per bin err_P <= 1.26 (1 + |Lam C_l|) err_Geq."""
    stage, slow = siso
    plant, ts = stage.plant[0, 0], stage.sample_time
    n_samples = 12_000
    r = multisine(n_samples, rng=0)
    y_l = simulate_slow_feedback(plant, slow, r, F).y_l
    estimate = LRMBeyondNyquist().fit(r, y_l, F, sample_time=ts)
    result = plant_from_closed_loop(estimate, slow)
    truth2 = true_frf(plant, n_samples, one_sided=False)
    slow_frf = true_frf(slow, n_samples // F, one_sided=False)
    exact = _slow_equivalent(truth2[None, None], slow_frf[None, None], [0])[0, 0]
    K, M = n_samples // 2 + 1, n_samples // F
    np.testing.assert_array_equal(np.flatnonzero(~result.valid_), [0, M])
    ok = result.valid_
    truth = truth2[:K]
    error_p = np.abs(result.frf_ - truth) / np.abs(truth)
    with np.errstate(all="ignore"):
        error_g = np.abs(estimate.frf_ - exact) / np.abs(exact)
    hold = np.exp(-2j * np.pi * np.outer(np.arange(n_samples), np.arange(F))
                  / n_samples).sum(axis=1)
    lam = (truth2 * hold).reshape(F, M).mean(axis=0)
    loop_gain = np.abs(lam * slow_frf)[np.arange(K) % M]
    assert np.median(error_p[ok]) < 1e-9
    assert error_p[ok & (loop_gain < 1)].max() < 1e-6
    assert np.all(error_p[ok] <= 2 * (1 + loop_gain[ok]) * error_g[ok] + 1e-14)


# --- uncertainty -----------------------------------------------------------------


def _random_covariance(rng, n_outputs, n_inputs, K, scale):
    """Hermitian positive definite per output row and bin, (n_y, n_u, n_u, K)."""
    root = rng.standard_normal((K, n_outputs, n_inputs, n_inputs)) + 1j * (
        rng.standard_normal((K, n_outputs, n_inputs, n_inputs)))
    cov = root @ np.conj(np.swapaxes(root, -1, -2)) / (2 * n_inputs)
    cov *= scale[..., None, None]
    return np.moveaxis(cov, 0, -1), root


@pytest.mark.parametrize("rate", ["fast", "slow"])
def test_first_order_std_matches_monte_carlo(mimo, rate):
    """Circular complex Gaussian errors with a random per-row covariance
    (1e-4 relative: linear regime), independent between bins and rows, as
    the propagation assumes; 400 runs. The std of a std from 400 runs is
    3.5 %; the median ratio MC/first order over bins and entries must be
    within 2 % of 1 and 95 % of the ratios in [0.85, 1.15] (measured: median
    1.00, fast and slow). Bins of the DC and slow-Nyquist band sets (mirrored
    bins, whose pseudo-covariance is neglected) are left out."""
    stage, slow = mimo
    rng = np.random.default_rng(0)
    n_samples = 240
    M = n_samples // F
    if rate == "fast":
        frf, controller = true_frf(stage.G, n_samples), stage.controller
    else:
        plant = true_frf(stage.plant, n_samples, one_sided=False)
        frf = _slow_equivalent(plant, true_frf(slow, M, one_sided=False),
                               [0, 1, 2, 3])
        controller = slow
    K = frf.shape[-1]
    scale = (1e-4 * np.abs(frf).max(axis=1)) ** 2  # (n_y, K)
    cov, root = _random_covariance(rng, 5, 4, K, scale.T)
    result = plant_from_closed_loop(
        _fake(frf, stage.sample_time, cov=cov,
              std=np.sqrt(np.einsum("oiik->oik", cov).real)), controller, ENCODERS)
    runs = []
    factor = np.sqrt(scale.T)[..., None, None] * root / np.sqrt(2 * 4)  # (K, n_y, ..)
    for _ in range(400):
        white = (rng.standard_normal((K, 5, 4)) + 1j * rng.standard_normal(
            (K, 5, 4))) / np.sqrt(2)
        noise = np.moveaxis(np.einsum("koij,koj->koi", factor, white), 0, -1)
        perturbed = _fake(frf + noise, stage.sample_time)
        runs.append(plant_from_closed_loop(perturbed, controller, ENCODERS).frf_)
    spread = np.sqrt(np.mean(np.abs(np.array(runs) - result.frf_) ** 2, axis=0))
    bins = np.arange(K)
    keep = result.valid_[0, 0] & (bins % M != 0) & (bins % M != M // 2)
    ratio = (spread / result.frf_std_)[..., keep]
    assert abs(np.median(ratio) - 1) < 0.02
    assert np.mean(np.abs(ratio - 1) < 0.15) > 0.95


@pytest.mark.parametrize("rate", ["fast", "slow"])
def test_first_order_std_with_covariance_between_rows(mimo, rate):
    """Errors correlated between output rows (a random joint covariance of
    the 20 entries of each bin with a part common to all rows, 1e-4
    relative), given as frf_joint_cov_;
    400 runs. Tolerances as in the per-row test above (std of a std from 400
    runs: 3.5 %): median MC/first order within 2 % of 1, 95 % of the ratios
    in [0.85, 1.15]. With the rows taken as independent (the propagation
    before frf_joint_cov_) 91-92 % of the ratios were in that band, some
    down to 0.35."""
    stage, slow = mimo
    rng = np.random.default_rng(1)
    n_samples = 240
    M = n_samples // F
    if rate == "fast":
        frf, controller = true_frf(stage.G, n_samples), stage.controller
    else:
        plant = true_frf(stage.plant, n_samples, one_sided=False)
        frf = _slow_equivalent(plant, true_frf(slow, M, one_sided=False),
                               [0, 1, 2, 3])
        controller = slow
    K = frf.shape[-1]
    scale = 1e-4 * np.abs(frf).max(axis=(0, 1))  # (K,)
    def gaussian(*shape):
        return rng.standard_normal(shape) + 1j * rng.standard_normal(shape)

    # each row's own errors, plus a common error of all rows (correlation
    # about 0.9, as noise fed back to every output): dG_o = R_o w_o + c_o Q w
    root = np.zeros((K, 5, 4, 5, 4 + 4), dtype=complex)
    for o in range(5):
        root[:, o, :, o, :4] = 0.3 * gaussian(K, 4, 4)
    root[..., 4:] = gaussian(5)[None, :, None, None, None] * gaussian(
        K, 1, 4, 1, 4)
    root = root.reshape(K, 20, 40) * (scale / np.sqrt(8))[:, None, None]
    joint = root @ np.conj(np.swapaxes(root, 1, 2))  # (K, 20, 20), rows o i
    joint = np.moveaxis(joint.reshape(K, 5, 4, 5, 4), 0, -1)
    per_row = np.einsum("oiojk->oijk", joint)
    fake = _fake(frf, stage.sample_time, cov=per_row,
                 std=np.sqrt(np.einsum("oiik->oik", per_row).real))
    fake.frf_joint_cov_ = joint
    result = plant_from_closed_loop(fake, controller, ENCODERS)
    runs = []
    for _ in range(400):
        white = gaussian(K, 40) / np.sqrt(2)
        noise = np.moveaxis(np.einsum("kab,kb->ka", root, white).reshape(K, 5, 4),
                            0, -1)
        perturbed = _fake(frf + noise, stage.sample_time)
        runs.append(plant_from_closed_loop(perturbed, controller, ENCODERS).frf_)
    spread = np.sqrt(np.mean(np.abs(np.array(runs) - result.frf_) ** 2, axis=0))
    bins = np.arange(K)
    keep = result.valid_[0, 0] & (bins % M != 0) & (bins % M != M // 2)
    ratio = (spread / result.frf_std_)[..., keep]
    assert abs(np.median(ratio) - 1) < 0.02
    assert np.mean(np.abs(ratio - 1) < 0.15) > 0.95
    # block-diagonal frf_joint_cov_ = frf_cov_ alone (the rows independent)
    fake.frf_joint_cov_ = np.zeros_like(joint)
    for o in range(5):
        fake.frf_joint_cov_[o, :, o] = per_row[o]
    alone = plant_from_closed_loop(fake, controller, ENCODERS).frf_std_
    del fake.frf_joint_cov_
    rows = plant_from_closed_loop(fake, controller, ENCODERS).frf_std_
    np.testing.assert_allclose(alone, rows, rtol=1e-12)


def test_std_from_frf_std_when_no_covariance(siso):
    """Without frf_cov_: independent entries with frf_std_; SISO fast loop
    dP = (1 + P C) dG / (1 - C G) = dG / (1 - C G)^2."""
    stage, _ = siso
    G = true_frf(stage.G_y4, N)
    std = 1e-3 * np.abs(G)
    result = plant_from_closed_loop(_fake(G, stage.sample_time, std=std),
                                    stage.controller)
    z = np.exp(2j * np.pi * np.arange(N // 2 + 1) / N)
    C = np.squeeze(stage.controller(z))
    expected = std / np.abs(1 - C * G) ** 2
    ok = result.valid_
    # rtol: the loop-gain amplification of rounding, as in the recovery tests
    np.testing.assert_allclose(result.frf_std_[ok], expected[ok], rtol=1e-7)


# --- result object and errors ------------------------------------------------------


def test_result_to_frd_and_public_name(mimo):
    stage, _ = mimo
    result = lrmfrf.plant_from_closed_loop(
        _fake(true_frf(stage.G, N), stage.sample_time), stage.controller, ENCODERS)
    frd, std = result.to_frd(return_std=True)
    assert frd.noutputs == 5 and frd.ninputs == 4
    assert frd.omega.size == N // 2 == std.shape[-1]
    np.testing.assert_allclose(frd.omega, 2 * np.pi * result.frequencies_[1:])
    assert "loop_rate_='fast'" in repr(result)


def test_errors(mimo, siso):
    stage, slow = mimo
    ts = stage.sample_time
    estimate = _fake(true_frf(stage.G, N), ts)
    with pytest.raises(ValueError, match=r"len\(feedback_outputs\) = 5 inputs"):
        plant_from_closed_loop(estimate, stage.controller)
    with pytest.raises(NotFittedError, match="not fitted yet"):
        plant_from_closed_loop(LRMBeyondNyquist(), stage.controller)
    with pytest.raises(ValueError, match="must be discrete-time"):
        plant_from_closed_loop(estimate, control.ss([], [], [], np.eye(4)))
    with pytest.raises(TypeError, match="controller must be a control.StateSpace"):
        plant_from_closed_loop(estimate, np.eye(4))
    wrong_rate = control.ss([], [], [], np.eye(4), 2 * ts)
    with pytest.raises(ValueError, match="matches neither the fast sample time"):
        plant_from_closed_loop(estimate, wrong_rate, ENCODERS)
    with pytest.raises(ValueError, match=r"len\(feedback_outputs\) = 2 inputs"):
        plant_from_closed_loop(estimate, stage.controller, feedback_outputs=(0, 1))
    with pytest.raises(ValueError, match="n_u = 4 outputs"):
        plant_from_closed_loop(estimate, stage.controller[:3, :], ENCODERS)
    with pytest.raises(ValueError, match="distinct output indices in"):
        plant_from_closed_loop(estimate, stage.controller, (0, 1, 2, 7))
    with pytest.raises(ValueError, match="hold must be 'zoh'"):
        plant_from_closed_loop(estimate, stage.controller, ENCODERS, hold="foh")
    segment = SimpleNamespace(**vars(estimate))
    segment.frequencies_ = segment.frequencies_ * 1.5
    with pytest.raises(ValueError, match="full one-sided fast DFT grid"):
        plant_from_closed_loop(segment, slow, ENCODERS)
    bad = SimpleNamespace(**vars(estimate))
    bad.n_outputs_ = 4
    with pytest.raises(ValueError, match=r"must have shape \(n_outputs_, n_inputs_"):
        plant_from_closed_loop(bad, stage.controller, ENCODERS)
    with pytest.raises(ValueError, match=r"frf_cov_ must have shape"):
        plant_from_closed_loop(_fake(estimate.frf_, ts, cov=np.zeros((5, 4, 4))),
                               stage.controller, ENCODERS)


def test_inputs_are_not_modified(mimo):
    stage, _ = mimo
    estimate = _fake(true_frf(stage.G, N), stage.sample_time)
    before = {name: np.copy(value) for name, value in vars(estimate).items()}
    plant_from_closed_loop(estimate, stage.controller, ENCODERS)
    for name, value in before.items():
        np.testing.assert_array_equal(getattr(estimate, name), value)
