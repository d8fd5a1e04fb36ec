"""The covariance routes of lrmfrf.uncertainty and the calibration of frf_std_.

Known answers first (the Lemma 2 route is the estimator's old variance; the
errors-in-variables sandwich written out with plain per-window loops; without a
denominator it is Lemma 2), then Monte-Carlo statistics on random stages: the
fast versions here run in a few seconds, the 100-run versions are ``slow``.
The full tables are in ``benchmarks/generalisation_std.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import band_variances, random_stage_record

from lrmfrf import LPMBeyondNyquist, LRMBeyondNyquist
from lrmfrf.local_models import dft, fit_local_models
from lrmfrf.plants import mimo_wafer_stage, random_stage
from lrmfrf.signals import multisine, orthogonal_multisines
from lrmfrf.simulate import simulate, true_frf
from lrmfrf.uncertainty import (
    STD_METHODS,
    band_covariance,
    calibrated_local_fit,
    variance_terms,
)
from lrmfrf.windows import LocalModelLayout, local_regressor, window_offsets


@pytest.fixture(scope="module")
def record():
    """A random stage (seed 3000: neither tuning nor held-out), F = 3, 40 dB."""
    return random_stage_record()


def _terms(u, y, layout):
    U, Y = dft(u)[None], dft(y)[None]
    fit = fit_local_models(U, Y, layout, return_cov=True)
    return U, Y, fit, variance_terms(U, Y, layout, fit.theta, fit.slow_bins)


# --- known answers ----------------------------------------------------------------

def test_lemma2_route_is_the_estimators_old_variance(record):
    u, y = record
    est = LRMBeyondNyquist(std_method="lemma2").fit(u, y, 3)
    _, _, fit, terms = _terms(u, y, est.layout_)
    var = band_variances(band_covariance(terms, est.layout_, "lemma2"))
    np.testing.assert_allclose(var, est.local_fit_.system_var, rtol=1e-7)
    np.testing.assert_allclose(var, fit.system_var, rtol=1e-7)


def test_eiv_sandwich_against_plain_per_window_loops(record):
    """The sandwich F^2 s2 S^H diag|e|^2 S with s2 = ||r||^2 / sum |e|^2 (1 - h),
    written out window by window with a pseudo-inverse (independent of the
    batched normal equations)."""
    u, y = record
    layout = LocalModelLayout(F=3, half_window=18, num_degree=4,
                              transient_degree=4, den_degree=7)
    U, Y, fit, terms = _terms(u, y, layout)
    got = band_covariance(terms, layout, "eiv")
    _, x = window_offsets(18)
    for k in (0, 7, 60, 133, 200):
        A, b = local_regressor(U, Y, np.array([k]), layout)
        A, b = A[0], b[0]
        theta = np.linalg.lstsq(A, b, rcond=None)[0]
        np.testing.assert_allclose(theta, fit.theta[k], rtol=1e-6, atol=1e-9)
        pinv = np.linalg.pinv(A)  # rows: parameters
        hat = np.real(np.diag(A @ pinv))
        e = 1 + sum(theta[layout.den_columns][s] * x ** (s + 1) for s in range(7))
        w = np.abs(e) ** 2
        s2 = np.sum(np.abs(b - A @ theta) ** 2) / np.sum(w * (1 - hat))
        S = pinv[:3].conj().T  # (L, F)
        expected = 9 * s2 * S.conj().T @ np.diag(w) @ S
        np.testing.assert_allclose(got[k], expected, rtol=1e-6)


def test_eiv_is_lemma2_without_denominator(record):
    """e(x) = 1 and sum_r (1 - h_r) = q: the sandwich is Lemma 2 (LPM)."""
    u, y = record
    lpm = LPMBeyondNyquist().fit(u, y, 3)
    _, _, _, terms = _terms(u, y, lpm.layout_)
    for method in ("eiv", "eiv_pooled"):
        kwargs = {"slow_bins": np.arange(201), "n_slow": 400}
        var = band_covariance(terms, lpm.layout_, method, **kwargs)
        if method == "eiv":
            np.testing.assert_allclose(band_variances(var), lpm.local_fit_.system_var,
                                       rtol=1e-7)


def test_std_method_options(record):
    """Every route gives a finite, positive std on the same bins and the same
    FRF; frf_cov_ keeps frf_std_ on its diagonal; the default is eiv."""
    u, y = record
    ref = LRMBeyondNyquist(std_method="lemma2").fit(u, y, 3)
    for method in STD_METHODS:
        est = LRMBeyondNyquist(std_method=method).fit(u, y, 3)
        np.testing.assert_array_equal(est.frf_, ref.frf_)
        np.testing.assert_array_equal(est.noise_variance_, ref.noise_variance_)
        assert np.all(np.isfinite(est.frf_std_)) and np.all(est.frf_std_ > 0)
        np.testing.assert_allclose(est.frf_std_**2, np.real(est.frf_cov_[0, 0, 0]),
                                   rtol=1e-12)
    default = LRMBeyondNyquist().fit(u, y, 3)
    assert default.std_method == "eiv"  # compiled and streamed: the default
    eiv = LRMBeyondNyquist(std_method="eiv").fit(u, y, 3)
    np.testing.assert_array_equal(default.frf_std_, eiv.frf_std_)
    ratio = np.median(eiv.frf_std_ / ref.frf_std_)
    assert 1.03 < ratio < 1.4  # Lemma 2 is low: the point of the eiv route


def test_bad_std_method_names_the_choices(record):
    u, y = record
    with pytest.raises(ValueError, match=r"`std_method` must be one of .*'eiv'"):
        LRMBeyondNyquist(std_method="sandwich").fit(u, y, 3)


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
def test_refined_fits_take_the_eiv_noise_level(record):
    """After SK the std keeps the refinement's linearised shape; with
    std_method="eiv" (the default) it is scaled per window by the closed
    form's eiv noise variance over the refinement's own (which the refined
    fit lowers), with "lemma2" it is the refinement's own."""
    u, y = record
    a = LRMBeyondNyquist(sk_iterations=3).fit(u, y, 3)
    b = LRMBeyondNyquist(sk_iterations=3, std_method="lemma2").fit(u, y, 3)
    np.testing.assert_array_equal(a.frf_, b.frf_)
    layout = a.layout_
    U, Y = dft(u)[None], dft(y)[None]
    closed = fit_local_models(U, Y, layout, return_cov=True)
    terms = variance_terms(U, Y, layout, closed.theta, closed.slow_bins,
                           with_hc=False)
    factor = terms.rss / terms.eiv_trace / b.noise_variance_  # per window
    np.testing.assert_allclose(a.local_fit_.system_var,
                               b.local_fit_.system_var * factor[:, None],
                               rtol=1e-7)
    assert np.median(factor) > 1.0  # SK 3 lowers the residual (1.03x here)


def test_calibrated_fit_leaves_invalid_windows_nan(record):
    u, y = record
    layout = LocalModelLayout(F=3, half_window=18, num_degree=4,
                              transient_degree=4, den_degree=7)
    U, Y = dft(u)[None], dft(y)[None]
    fit = fit_local_models(U, Y, layout, return_cov=True)
    fit.well_posed[5] = False
    fit.theta[5] = np.nan
    out = calibrated_local_fit(U, Y, layout, fit, "eiv")
    assert np.all(np.isnan(out.system_var[5])) and np.all(np.isnan(out.system_cov[5]))
    assert np.all(np.isfinite(out.system_var[6]))
    assert calibrated_local_fit(U, Y, layout, fit, "lemma2") is fit


# --- Monte Carlo ------------------------------------------------------------------

def _monte_carlo(system, F, snr_db, n_runs, seed, half_window=18, **kwargs):
    """(median ratio predicted / MC std, fraction within 2 std of the truth)."""
    rng = np.random.default_rng(seed)
    N = 400 * F
    u = multisine(N, rms=1.44, rng=rng)
    sim = simulate(system, u, F, snr_db=snr_db, rng=rng)
    truth = true_frf(system, N)
    est, var = [], []
    for _ in range(n_runs):
        y = sim.y_l_clean + sim.noise_std * rng.standard_normal(400)
        fit = LRMBeyondNyquist(half_window=half_window, **kwargs).fit(u, y, F)
        est.append(fit.frf_)
        var.append(fit.frf_std_**2)
    est, var = np.array(est), np.array(var)
    mc = np.sqrt(np.sum(np.abs(est - est.mean(0)) ** 2, axis=0) / (n_runs - 1))
    bins = np.all(np.isfinite(est), axis=0) & np.isfinite(truth)
    bins[0] = False
    ratio = np.median(np.sqrt(var.mean(0))[bins] / mc[bins])
    cover = np.mean(np.abs(est - truth)[:, bins] <= 2 * np.sqrt(var[:, bins]))
    return ratio, cover


def test_eiv_std_matches_monte_carlo_on_a_random_stage():
    """40 runs: each bin's MC std has ~8 % relative spread, the median over ~560
    correlated bins ~2 %; 0.92-1.08 holds for a calibrated std and fails for
    Lemma 2 (0.85-0.9x on these stages). The 2-std coverage of a perfect std is
    98.2 % for a complex Gaussian; 93 % is the floor of the benchmark's tuning
    stages at 40 runs (10 residual dof and heavy tails: see docs/method.md)."""
    stage, _ = random_stage(3001, downsampling_factor=3)
    ratio, cover = _monte_carlo(stage.G_y4, 3, 45, 40, seed=5, std_method="eiv")
    assert 0.92 <= ratio <= 1.08
    assert cover >= 0.93


STAGES = [  # (seed, F, loop, channel): F = 2, 3, 5, both loops and outputs
    (3002, 2, "closed", "G_z"), (3003, 3, "open", "G_y4"),
    (3004, 3, "closed", "G_z"), (3005, 5, "closed", "G_y4"),
    (3006, 5, "open", "G_z"),
]


@pytest.mark.slow
def test_eiv_std_matches_monte_carlo_many_runs():
    """100 runs per stage at 45 dB (MC std per bin ~5 %, its median over the
    bins ~1 %), F = 5 with the half window 23 (10 residual dof). The issue's
    0.95-1.05 for the median over the stages; each stage within 0.92-1.08:
    open-loop stages sit at 0.94-0.96 in the benchmark (docs/method.md,
    section 5), which this bound records rather than hides."""
    ratios = []
    for seed, F, loop, channel in STAGES:
        stage, _ = random_stage(seed, downsampling_factor=F, loop=loop)
        ratio, cover = _monte_carlo(getattr(stage, channel), F, 45, 100, seed=seed,
                                    half_window=23 if F == 5 else 18,
                                    std_method="eiv")
        assert 0.92 <= ratio <= 1.08, (seed, F, loop, channel, ratio)
        assert cover >= 0.92, (seed, F, loop, channel, cover)
        ratios.append(ratio)
    assert 0.95 <= np.median(ratios) <= 1.05, ratios


def _mimo_record(system, F, snr_db, rng):
    """Two orthogonal multisine experiments through a 2x2 system."""
    u = orthogonal_multisines(2, 400 * F, rms=1.44, rng=rng)  # (P, n_u, N)
    sims = [simulate(system, u[p], F, snr_db=snr_db, rng=rng) for p in range(2)]
    return u, sims


def test_mimo_rows_use_the_same_route():
    """2x2, two experiments: frf_cov_ of each output row comes from the route,
    its diagonal is frf_std_**2, the FRF is the same as with lemma2 and the
    std larger."""
    system = mimo_wafer_stage().G[0:2, 0:2]
    u, sims = _mimo_record(system, 3, 45, np.random.default_rng(0))
    y = np.stack([s.y_l for s in sims])
    a = LRMBeyondNyquist(std_method="eiv").fit(u, y, 3)
    b = LRMBeyondNyquist(std_method="lemma2").fit(u, y, 3)
    np.testing.assert_array_equal(a.frf_, b.frf_)
    diagonal = np.real(np.diagonal(a.frf_cov_, axis1=1, axis2=2))  # (n_y, K, n_u)
    np.testing.assert_allclose(a.frf_std_**2, np.moveaxis(diagonal, -1, 1),
                               rtol=1e-12)
    assert np.median(a.frf_std_ / b.frf_std_) > 1.03


@pytest.mark.parametrize("rank", [27, 6])
def test_pseudo_inverse_gram_is_that_of_the_truncated_svd(rank):
    """``_pseudo_inverse_gram`` (a stacked matmul since the einsum was ~5x
    slower) is ``A^+ A^+^H = (A^H A)^+`` of complex windows, full rank and
    rank-deficient (rank 6 of 27 columns, as a noise-free record's common
    factor), and Hermitian: the Moore-Penrose conditions on the Gram."""
    from lrmfrf.uncertainty import _pseudo_inverse_gram, _truncated_svd

    rng = np.random.default_rng(3)

    def cn(*shape):
        return rng.standard_normal(shape) + 1j * rng.standard_normal(shape)

    # (full rank: a plain random A; a square random factor can be badly
    # conditioned and would test the conditioning, not the formula)
    A = cn(5, 40, 27) if rank == 27 else cn(5, 40, rank) @ cn(5, rank, 27)
    _, inv_s, Vh = _truncated_svd(A)
    ours = _pseudo_inverse_gram(inv_s, Vh)
    A_plus = np.linalg.pinv(A, rcond=1e-10)
    reference = A_plus @ np.conj(np.swapaxes(A_plus, 1, 2))
    scale = np.abs(reference).max()
    np.testing.assert_allclose(ours, reference, rtol=0, atol=1e-12 * scale)
    gram = np.conj(np.swapaxes(A, 1, 2)) @ A
    np.testing.assert_allclose(gram @ ours @ gram, gram, rtol=0,
                               atol=1e-12 * np.abs(gram).max())
    np.testing.assert_allclose(ours @ gram @ ours, ours, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(ours, np.conj(np.swapaxes(ours, 1, 2)), rtol=0,
                               atol=1e-14 * scale)
