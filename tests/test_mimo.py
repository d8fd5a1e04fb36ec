"""MIMO identification beyond Nyquist (issue 13): record forms, exact in-class
recovery, std calibration, LRM vs LPM on aliased modes, spectral analysis."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.signal import dlsim

from lrmfrf import LPMBeyondNyquist, LRMBeyondNyquist, SpectralAnalysis
from lrmfrf.signals import multisine, orthogonal_multisines
from lrmfrf.testing import in_class_mimo_data
from lrmfrf.windows import LocalModelLayout

DEG = {"num_degree": 2, "transient_degree": 2, "den_degree": 2}


def _half_window(n_u, F, P, minimum=8):
    """Smallest half window with a few residual degrees of freedom."""
    n_params = 3 * F * n_u + 3 * P + 2
    return max(minimum, int(np.ceil((n_params / P - 1) / 2)) + 2)


def _entries(est, n_y, n_u):
    return np.asarray(est.frf_).reshape(n_y, n_u, -1)


def _in_class(n_u, n_y, F, P, seed=0, M=240):
    n = _half_window(n_u, F, P)
    layout = LocalModelLayout(F=F, half_window=n, n_experiments=P, n_inputs=n_u,
                              **DEG)
    u, y, centres, G = in_class_mimo_data(layout, M, n_y, seed)
    return n, u, y, centres, G


def _at_centres(frf, centres, M, F):
    """frf (n_y, n_u, K) at the fast bins k + fM of the centres, and a mask of
    the bins that lie on the one-sided grid."""
    N = F * M
    fast = centres[:, None] + M * np.arange(F)
    ok = fast <= N // 2
    values = frf[..., np.minimum(fast, N // 2)]  # (n_y, n_u, C, F)
    return np.moveaxis(values, (0, 1), (1, 2)), ok  # (C, n_y, n_u, F)


# --- exact in-class recovery ---------------------------------------------------


@pytest.mark.parametrize("n_u, n_y", [(2, 1), (1, 2), (2, 2), (3, 2)])
@pytest.mark.parametrize("F", [2, 3])
@pytest.mark.parametrize("P", [1, 2])
def test_in_class_mimo_data_are_recovered_exactly(n_u, n_y, F, P):
    """Noise-free data in the model class (per output row: local models of all
    inputs over all bands, one denominator, one transient per experiment): the
    closed form recovers every entry to round-off (1e-12 relative on
    well-conditioned windows; we see ~1e-14)."""
    n, u, y, centres, G = _in_class(n_u, n_y, F, P)
    est = LRMBeyondNyquist(half_window=n, **DEG).fit(u, y, F)
    assert est.n_inputs_ == n_u and est.n_outputs_ == n_y
    assert est.n_experiments_ == P
    estimate, ok = _at_centres(_entries(est, n_y, n_u), centres, y.shape[-1], F)
    for o in range(n_y):
        for i in range(n_u):
            np.testing.assert_allclose(estimate[:, o, i][ok], G[:, o, i][ok],
                                       rtol=1e-12, atol=0)


def test_one_experiment_with_several_inputs_needs_a_wide_enough_window():
    """P = 1, n_u = 3, F = 3: (2+1)*3*3 + 3 + 2 = 32 parameters need 2n+1 >= 32.
    The error names the smallest half window and the number of experiments."""
    n, u, y, _, _ = _in_class(3, 1, 3, 1)
    with pytest.raises(ValueError, match=r"Increase half_window to at least 16.*"
                       r"at least 2 experiments"):
        LRMBeyondNyquist(half_window=10, **DEG).fit(u[0], y[0], 3)
    # with the half window it asks for, one experiment works
    est = LRMBeyondNyquist(half_window=16, **DEG).fit(u[0], y[0], 3)
    assert est.dof_ == 33 - 32


def test_too_short_record_names_the_number_of_experiments():
    """When no half window fits the record, the message says how many
    experiments are needed."""
    rng = np.random.default_rng(3)
    u, y = rng.standard_normal((3, 60)), rng.standard_normal((1, 20))
    with pytest.raises(ValueError, match=r"allows half_window <= 9 only.*"
                       r"at least \d+ experiments"):
        LRMBeyondNyquist(half_window=9, **DEG).fit(u, y, 3)


def test_old_2d_stack_of_experiments_gets_the_list_hint():
    rng = np.random.default_rng(4)
    u = rng.standard_normal((4, 600))
    y = rng.standard_normal((4, 200))
    with pytest.raises(ValueError, match="several experiments go in a list"):
        LRMBeyondNyquist().fit(u, y, 3)


def test_column_vectors_stay_refused():
    rng = np.random.default_rng(5)
    with pytest.raises(ValueError, match="column vector"):
        LRMBeyondNyquist().fit(rng.standard_normal((600, 1)),
                               rng.standard_normal(200), 3)


# --- record forms ---------------------------------------------------------------


def test_list_and_3d_forms_give_identical_results():
    n, u, y, _, _ = _in_class(2, 2, 3, 2, seed=1)
    y = y + 1e-3 * np.random.default_rng(1).standard_normal(y.shape)
    a = LRMBeyondNyquist(half_window=n, **DEG).fit(u, y, 3)
    b = LRMBeyondNyquist(half_window=n, **DEG).fit(list(u), list(y), 3)
    for name in ("frf_", "frf_std_", "frf_cov_", "valid_", "noise_variance_",
                 "transient_"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_siso_as_one_by_n_equals_the_1d_fit():
    rng = np.random.default_rng(6)
    u = multisine(600, rng=rng)
    y = np.convolve(u, [0.3, 0.2, 0.1])[:600][::3] + 1e-3 * rng.standard_normal(200)
    a = LRMBeyondNyquist(half_window=10, **DEG).fit(u, y, 3)
    b = LRMBeyondNyquist(half_window=10, **DEG).fit(u[None], y[None], 3)
    assert b.frf_.shape == (301,) and b.valid_.shape == (301,)
    for name in ("frf_", "frf_std_", "frf_cov_", "noise_variance_", "transient_"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.frf_cov_.shape == (1, 1, 1, 301)
    np.testing.assert_allclose(np.sqrt(a.frf_cov_[0, 0, 0].real), a.frf_std_,
                               rtol=1e-12)
    assert b.predict(u[None]).shape == (1, 200)
    assert a.predict(u).shape == (200,)


def test_simo_and_miso_work():
    n, u, y, centres, G = _in_class(1, 2, 2, 1, seed=2)
    simo = LRMBeyondNyquist(half_window=n, **DEG).fit(u[0, 0], y[0], 2)  # 1-D u
    assert simo.frf_.shape == (2, 1, 241)
    n, u, y, centres, G = _in_class(2, 1, 2, 1, seed=3)
    miso = LRMBeyondNyquist(half_window=n, **DEG).fit(u[0], y[0, 0], 2)  # 1-D y
    assert miso.frf_.shape == (1, 2, 241)
    estimate, ok = _at_centres(miso.frf_, centres, 120, 2)
    np.testing.assert_allclose(estimate[:, 0, 1][ok], G[:, 0, 1][ok], rtol=1e-12)


def test_fitted_attribute_shapes_and_to_frd():
    n, u, y, _, _ = _in_class(2, 2, 3, 2, seed=4, M=120)
    est = LRMBeyondNyquist(half_window=n, **DEG).fit(u, y, 3)
    K, B = 181, 61
    assert est.frf_.shape == est.frf_std_.shape == est.valid_.shape == (2, 2, K)
    assert est.frf_cov_.shape == (2, 2, 2, K)
    assert est.noise_variance_.shape == (2, B)
    assert est.transient_.shape == (2, 2, B)
    np.testing.assert_allclose(
        np.sqrt(np.real(np.diagonal(est.frf_cov_, axis1=1, axis2=2))),
        np.moveaxis(est.frf_std_, 1, 2), rtol=1e-12)
    # Hermitian per bin
    np.testing.assert_allclose(est.frf_cov_, np.conj(np.swapaxes(est.frf_cov_, 1, 2)),
                               rtol=1e-12, atol=1e-300)
    frd, std = est.to_frd(return_std=True)
    assert frd.noutputs == 2 and frd.ninputs == 2
    assert std.shape == (2, 2, frd.omega.size)


def test_predict_returns_the_input_form_and_score_averages_outputs():
    n, u, y, _, _ = _in_class(2, 2, 3, 2, seed=5)
    est = LRMBeyondNyquist(half_window=n, **DEG).fit(u, y, 3)
    assert est.predict(u[0]).shape == (2, 240)
    three = est.predict(u)
    assert three.shape == (2, 2, 240)
    listed = est.predict(list(u))
    assert isinstance(listed, list) and len(listed) == 2
    np.testing.assert_array_equal(listed[1], three[1])
    prediction = three
    per_output = [
        1 - np.sum((y[:, o] - prediction[:, o]) ** 2)
        / np.sum((y[:, o] - y[:, o].mean()) ** 2) for o in range(2)
    ]
    assert est.score(u, y) == pytest.approx(np.mean(per_output), rel=1e-12)
    with pytest.raises(ValueError, match="fitted with 2 input channel"):
        est.predict(u[0, :1])


# --- simulated 2x2 stage ------------------------------------------------------


def _stage_2x2():
    from lrmfrf.plants import mimo_wafer_stage

    stage = mimo_wafer_stage()
    return stage.G[0:2, 0:2], stage.downsampling_factor


def _true_frf(system, N):
    """C (zI - A)^-1 B + D at z = exp(j 2 pi k / N), k = 0..N//2: (2, 2, K)."""
    A, B, C, D = (np.asarray(m) for m in (system.A, system.B, system.C, system.D))
    z = np.exp(2j * np.pi * np.arange(N // 2 + 1) / N)
    eye = np.eye(A.shape[0])
    X = np.linalg.solve(z[:, None, None] * eye - A,
                        np.broadcast_to(B, (z.size,) + B.shape))
    return np.moveaxis(C @ X + D, 0, -1)


def _simulate(system, u, F, periods=3):
    """Slow outputs (n_y, M) of one record u (n_u, N) in periodic steady state."""
    A, B, C, D = (np.asarray(m) for m in (system.A, system.B, system.C, system.D))
    N = u.shape[1]
    _, y, _ = dlsim((A, B, C, D, system.dt), np.tile(u, periods).T)
    return y[-N:].T[:, ::F]


def _noisy_fits(system, estimator, F, N, runs, seed, snr=1e-3):
    rng = np.random.default_rng(seed)
    u = orthogonal_multisines(2, N, rng=rng)  # (P=2, 2, N)
    clean = np.stack([_simulate(system, u[p], F) for p in range(2)])
    sigma = snr * clean.std(axis=(0, 2), keepdims=True)
    fits = []
    for _ in range(runs):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fits.append(estimator.fit(u, clean + sigma * rng.standard_normal(
                clean.shape), F))
            fits[-1] = (fits[-1].frf_.copy(), fits[-1].frf_std_.copy())
    return fits


def test_lrm_beats_lpm_on_lightly_damped_aliased_modes():
    """Two channels of the MIMO stage's closed-loop G, orthogonal multisines,
    noise 1e-4 of the output std (the output is dominated by low frequencies:
    above the slow Nyquist frequency |G| is ~1e-3 of its peak): the rational
    local model follows the lightly damped modes above the slow Nyquist
    frequency, the polynomial one does not (we see the median relative error
    above Nyquist 5-10x lower per entry; we require 2x per entry)."""
    system, F = _stage_2x2()
    N = 3600
    G = _true_frf(system, N)
    above = np.arange(N // 2 + 1) > N // (2 * F)
    errors = {}
    for name, est in (("lrm", LRMBeyondNyquist()), ("lpm", LPMBeyondNyquist())):
        frf, _ = _noisy_fits(system, est, F, N, 1, seed=0, snr=1e-4)[0]
        errors[name] = np.nanmedian(
            np.abs(frf - G)[..., above] / np.abs(G[..., above]), axis=-1)
    assert np.all(errors["lrm"] < 0.5 * errors["lpm"]), errors


def test_std_matches_monte_carlo_on_a_2x2_system():
    """frf_std_ per entry against the Monte-Carlo RMS error on the 2x2 stage,
    20 runs (each entry's MC std to ~16 %, the median over bins much better;
    we see 0.85).
    As for SISO (0.85-0.9x) the errors-in-variables fit makes it a little
    low; we require the median ratio std/MC within [0.7, 1.3] per entry."""
    system, F = _stage_2x2()
    N = 1800
    G = _true_frf(system, N)
    fits = _noisy_fits(system, LRMBeyondNyquist(), F, N, 20, seed=1)
    err = np.sqrt(np.mean([np.abs(f - G) ** 2 for f, _ in fits], axis=0))
    std = np.sqrt(np.mean([s**2 for _, s in fits], axis=0))
    ratio = np.nanmedian(std[..., 1:] / err[..., 1:], axis=-1)
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio


# --- spectral analysis -------------------------------------------------------------


def test_mimo_spectral_analysis_recovers_a_static_gain_below_nyquist():
    """y = D u with inputs below the slow Nyquist frequency, one experiment:
    zero stuffing is exact there up to the aliased leakage of the Hann
    segments, so H1 = S_yu S_uu^-1 = D to 5e-3 (we see 1.3e-3 at worst)."""
    rng = np.random.default_rng(7)
    N, F = 2400, 3
    D = np.array([[1.0, -0.5], [0.25, 2.0]])
    bins = np.arange(1, N // (2 * F) - 20)
    u = np.stack([multisine(N, bins=bins, rng=rng) for _ in range(2)])
    y = (D @ u)[:, ::F]
    sa = SpectralAnalysis(segment_length=240, overlap=120).fit(u, y, F)
    assert sa.frf_.shape == (2, 2, 121)
    low = sa.frequencies_ < 0.9 / (2 * F)
    keep = sa.valid_[0, 0] & low
    assert keep.sum() > 30
    np.testing.assert_allclose(sa.frf_[..., keep],
                               np.broadcast_to(D[..., None], (2, 2, keep.sum())),
                               rtol=5e-3, atol=0)
    listed = SpectralAnalysis(segment_length=240, overlap=120).fit([u], [y], F)
    np.testing.assert_array_equal(listed.frf_, sa.frf_)


def test_mimo_spectral_analysis_needs_as_many_segments_as_inputs():
    rng = np.random.default_rng(8)
    u, y = rng.standard_normal((3, 300)), rng.standard_normal((1, 100))
    with pytest.raises(ValueError, match="at least 3 segments"):
        SpectralAnalysis(segment_length=300, overlap=0).fit(u, y, 3)


def test_mimo_spectral_analysis_std_matches_monte_carlo():
    """y = D u + white noise, inputs below the slow Nyquist frequency, one
    experiment of two inputs: frf_std_ per entry (multiple-input H1 variance,
    [S_uu^-1]_ii times the residual output power over n_avg) against the
    Monte-Carlo RMS error over 60 runs (each bin's MC std to ~9 %, the median
    over ~35 bins to a few %; overlapping Hann segments make the formula a
    little optimistic, as for SISO). We see ratios 0.93-0.94; we require
    [0.7, 1.3]."""
    rng = np.random.default_rng(9)
    N, F = 2400, 3
    D = np.array([[1.0, -0.5], [0.25, 2.0]])
    bins = np.arange(1, N // (2 * F) - 20)
    u = np.stack([multisine(N, bins=bins, rng=rng) for _ in range(2)])
    clean = (D @ u)[:, ::F]
    sa = SpectralAnalysis(segment_length=240, overlap=120)
    errors, stds = [], []
    for _ in range(60):
        sa.fit(u, clean + 0.05 * rng.standard_normal(clean.shape), F)
        errors.append(np.abs(sa.frf_ - D[..., None]) ** 2)
        stds.append(sa.frf_std_**2)
    keep = sa.valid_[0, 0] & (sa.frequencies_ < 0.8 / (2 * F)) & (sa.frequencies_ > 0)
    ratio = np.median(np.sqrt(np.mean(stds, axis=0))[..., keep]
                      / np.sqrt(np.mean(errors, axis=0))[..., keep], axis=-1)
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio


def test_records_are_parsed_once_with_their_form():
    from lrmfrf._validation import check_records

    rng = np.random.default_rng(10)
    u, y = rng.standard_normal((2, 3, 60)), rng.standard_normal((2, 1, 20))
    records = check_records(u, y, 3)
    assert records.u.shape == (2, 3, 60) and records.y.shape == (2, 1, 20)
    assert (records.u_form, records.y_form) == ("3d", "3d")
    assert records.n_inputs == 3 and records.n_outputs == 1
    listed = check_records([u[0], u[1]], [y[0, 0], y[1, 0]], 3)
    assert listed.u_form == "list" and listed.y.shape == (2, 1, 20)
    np.testing.assert_array_equal(listed.u, records.u)
    assert records.u is not u  # a copy: inputs are never modified
    single = check_records(u[0, 0], y[0, 0], 3)
    assert single.u.shape == (1, 1, 60) and single.u_form == "1d"


@pytest.mark.parametrize("solver, backend", [("normal", "numba"), ("qr", "auto")])
def test_mimo_solvers_agree_with_the_numpy_normal_equations(solver, backend):
    """The compiled kernel and the QR solver read the F n_u bands like the
    numpy path: the same band values and Lemma 2 covariances to ~1e-12."""
    from lrmfrf import _compiled
    from lrmfrf.local_models import fit_local_models

    if backend == "numba" and not _compiled.AVAILABLE:
        pytest.skip("numba not installed")
    layout = LocalModelLayout(F=3, half_window=10, n_experiments=2, n_inputs=2,
                              **DEG)
    u, y, _, _ = in_class_mimo_data(layout, 240, 2, 0)
    y = y + 0.01 * np.random.default_rng(1).standard_normal(y.shape)
    U = np.fft.fft(u, axis=-1).reshape(2, -1)
    Y = np.fft.fft(y, axis=-1)[:, 1]
    ref = fit_local_models(U, Y, layout, backend="numpy", return_cov=True)
    other = fit_local_models(U, Y, layout, solver=solver, backend=backend,
                             return_cov=True)
    scale = np.abs(ref.system).max()
    np.testing.assert_allclose(other.system, ref.system, rtol=0, atol=1e-12 * scale)
    cov_scale = np.abs(ref.system_cov).max()
    np.testing.assert_allclose(other.system_cov, ref.system_cov, rtol=0,
                               atol=1e-12 * cov_scale)
    np.testing.assert_allclose(
        np.real(np.diagonal(ref.system_cov, axis1=1, axis2=2)), ref.system_var,
        rtol=1e-12)


@pytest.mark.slow
def test_std_matches_monte_carlo_on_a_2x2_system_many_runs():
    """The larger version: N = 3600, 60 runs (benchmarks/mimo_accuracy.py
    measures 0.81-0.84 per entry with 20 runs). As for SISO (0.85-0.9x) the
    linearised std is a little low; we require [0.7, 1.1] per entry."""
    system, F = _stage_2x2()
    N = 3600
    G = _true_frf(system, N)
    fits = _noisy_fits(system, LRMBeyondNyquist(), F, N, 60, seed=2)
    err = np.sqrt(np.mean([np.abs(f - G) ** 2 for f, _ in fits], axis=0))
    std = np.sqrt(np.mean([s**2 for _, s in fits], axis=0))
    ratio = np.nanmedian(std[..., 1:] / err[..., 1:], axis=-1)
    assert np.all((ratio > 0.7) & (ratio < 1.1)), ratio
