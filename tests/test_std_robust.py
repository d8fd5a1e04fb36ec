"""``std_method="eiv_robust"``: the bias-aware std route of lrmfrf.uncertainty.

Known answers on constructed inputs first (the neighbour term vanishes where
the neighbouring local models agree exactly; the switched noise level keeps a
window's own level where it exceeds twice its neighbours' median), then the
route on a fit (noise part times the eiv shape, plus a non-negative term),
MIMO rows, the errors, and a small Monte Carlo against ``"eiv"``
(``benchmarks/coverage_bias_study.py`` has the full tables).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import band_variances, random_stage_record
from scipy.stats import chi2

from lrmfrf import LRMBeyondNyquist
from lrmfrf.local_models import (
    LocalModelFit,
    OneSidedSpectra,
    dft,
    fit_local_models,
    one_sided_fast_grid,
)
from lrmfrf.plants import mimo_wafer_stage, random_stage
from lrmfrf.refinement import refine_local_models
from lrmfrf.signals import multisine, orthogonal_multisines
from lrmfrf.simulate import simulate, true_frf
from lrmfrf.uncertainty import (
    ROBUST_NBR_THRESHOLD,
    band_covariance,
    calibrated_local_fit,
    calibrated_refined_fit,
    eiv_terms,
    iter_calibrated_fits,
    neighbour_bias_term,
    neighbour_disagreement,
    robust_band_covariance,
    robust_noise_variance,
    variance_terms,
)
from lrmfrf.windows import LocalModelLayout


@pytest.fixture(scope="module")
def record():
    """A random stage (seed 3000: neither tuning nor held-out), F = 3, 40 dB."""
    return random_stage_record()


def _polynomial_fit(layout, M, rng):
    """A LocalModelFit whose windows are the restrictions of ONE global model
    per band, ``g_f(j) = a_f + b_f j + c_f j^2`` (j the slow bin), e = 1."""
    B, F, n = M // 2 + 1, layout.F, layout.half_window
    a, b, c = (rng.standard_normal(F) + 1j * rng.standard_normal(F)
               for _ in range(3))
    k = np.arange(B)[:, None]
    theta = np.zeros((B, layout.n_params), complex)
    # g(k + n x) = g(k) + (b + 2 c k) n x + c n^2 x^2, over F (G = F theta)
    theta[:, 0:F] = (a + b * k + c * k**2) / F
    theta[:, F:2 * F] = (b + 2 * c * k) * n / F
    theta[:, 2 * F:3 * F] = c * n**2 / F
    ones = np.ones(B, bool)
    return LocalModelFit(layout=layout, slow_bins=np.arange(B), theta=theta,
                         system=F * theta[:, :F], system_var=np.ones((B, F)),
                         transient=np.zeros((B, 1), complex),
                         noise_var=np.ones(B), rss=np.ones(B), well_posed=ones,
                         excited=ones)


def test_neighbour_term_vanishes_where_the_local_models_agree():
    """Windows cut from one global model: the neighbours' models at the
    window's bin give its band value exactly, d = 0 (round-off); a change of
    one window's value shows up at that window and its two neighbours only,
    at the known size."""
    layout = LocalModelLayout(F=3, half_window=6, num_degree=2,
                              transient_degree=0, den_degree=2)
    fit = _polynomial_fit(layout, 60, np.random.default_rng(0))
    d = neighbour_disagreement(fit)
    assert d.shape == (31, 3)
    scale = np.max(np.abs(fit.system)) ** 2
    assert np.max(d) < 1e-24 * scale
    # move window 10's constant term of band 1 by delta: G_10 moves by F delta
    delta = 0.5
    fit.theta[10, 1] += delta
    fit.system[10, 1] += 3 * delta
    d = neighbour_disagreement(fit)
    # window 10 against both neighbours: |3 delta|^2; windows 9 and 11: one of
    # their two neighbours (window 10's model at offset -+1) is off by 3 delta
    np.testing.assert_allclose(d[10, 1], 9 * delta**2, rtol=1e-10)
    np.testing.assert_allclose(d[[9, 11], 1], 4.5 * delta**2, rtol=1e-10)
    others = np.ones_like(d, bool)
    others[[9, 10, 11], 1] = False
    assert np.max(d[others]) < 1e-24 * scale


def test_neighbour_term_edges_and_invalid_windows():
    """Windows 0 and M/2 use their one inner neighbour; a NaN neighbour is left
    out; a NaN window stays NaN; no usable neighbour: no term (0)."""
    layout = LocalModelLayout(F=2, half_window=5, num_degree=2,
                              transient_degree=0, den_degree=1)
    fit = _polynomial_fit(layout, 40, np.random.default_rng(1))
    fit.theta[0, 0] += 1.0  # window 0 off by F = 2 in band 0
    fit.system[0, 0] += 2.0
    fit.theta[20, 1] += 1.0  # window M/2 off by 2 in band 1
    fit.system[20, 1] += 2.0
    for k in (5, 7, 8):  # invalid windows
        fit.theta[k] = np.nan
        fit.system[k] = np.nan
    d = neighbour_disagreement(fit)
    np.testing.assert_allclose(d[0, 0], 4.0, rtol=1e-10)  # one neighbour only
    np.testing.assert_allclose(d[20, 1], 4.0, rtol=1e-10)
    assert np.all(np.isnan(d[[5, 7, 8]]))
    assert np.all(np.isfinite(d[[4, 6, 9]]))  # the valid neighbour is used
    assert np.all(d[6] == 0.0)  # both neighbours invalid: nothing to add
    with pytest.raises(ValueError, match="eiv_robust.*consecutive"):
        sub = LocalModelFit(**{**fit.__dict__, "slow_bins": fit.slow_bins * 2})
        neighbour_disagreement(sub)


def test_bias_term_where_the_ratio_stands_out():
    """d is added exactly where d / v exceeds the threshold times its median."""
    v = np.full((50, 3), 2.0)
    d = np.full((50, 3), 1.0)  # d / v = 0.5: the median
    d[7, 2] = 0.5 * 2.0 * ROBUST_NBR_THRESHOLD * 1.01  # just above
    d[8, 0] = 0.5 * 2.0 * ROBUST_NBR_THRESHOLD * 0.99  # just below
    v[9, 1] = np.nan
    add = neighbour_bias_term(d, v)
    expected = np.zeros_like(d)
    expected[7, 2] = d[7, 2]
    np.testing.assert_array_equal(add, expected)


def test_switched_noise_level_known_answer():
    """Own levels 1 except a misfit window (10, > 2x) and a mild one (1.5,
    < 2x): the misfit keeps 10, every other window takes the neighbours'
    median 1 over median(chi^2_2q / 2q); NaN windows stay NaN and are left out
    of their neighbours' medians."""
    M, B, q, n = 100, 51, 7, 4
    rss = np.ones(B)
    rss[20], rss[30] = 10.0, 1.5
    rss[40] = np.nan
    level = robust_noise_variance(rss, np.ones(B), np.arange(B), M, n, q)
    pooled = 1.0 / (chi2.median(2 * q) / (2 * q))
    assert pooled > 1.0  # the median of a chi^2 lies below its mean
    assert level[20] == 10.0
    assert np.isnan(level[40])
    rest = np.ones(B, bool)
    rest[[20, 40]] = False
    np.testing.assert_allclose(level[rest], pooled, rtol=1e-12)
    # with switch=inf (the study's "pmed") the misfit takes the median too
    inf = robust_noise_variance(rss, np.ones(B), np.arange(B), M, n, q,
                                switch=np.inf)
    np.testing.assert_allclose(inf[20], pooled, rtol=1e-12)


def test_route_is_eiv_shape_times_the_level_plus_a_nonnegative_term(record):
    """On a fit: the variance is >= the switched noise part (eiv shape times
    the robust level) everywhere, equals it where the neighbour term adds
    nothing, the off-diagonal covariance is the noise part's, and
    frf_std_ of the estimator is this variance on the fast grid."""
    u, y = record
    est = LRMBeyondNyquist(std_method="eiv_robust").fit(u, y, 3)
    eiv = LRMBeyondNyquist().fit(u, y, 3)
    layout = est.layout_
    U, Y = dft(u)[None], dft(y)[None]
    fit = fit_local_models(U, Y, layout, return_cov=True)
    lead, trace = eiv_terms(U, Y, layout, fit.theta, fit.slow_bins)
    own = fit.rss / trace
    level = robust_noise_variance(fit.rss, trace, fit.slow_bins, 400,
                                  layout.half_window, layout.dof)
    noise = 9 * lead * level[:, None, None]
    cov = robust_band_covariance(lead, trace, fit, 400)
    var, noise_var = band_variances(cov), band_variances(noise)
    assert np.all(var >= noise_var * (1 - 1e-12))
    added = var > noise_var * (1 + 1e-12)
    assert 0 < added.mean() < 0.2  # a term at a few bins only
    np.testing.assert_allclose(var[~added], noise_var[~added], rtol=1e-12)
    off = ~np.eye(3, dtype=bool)
    np.testing.assert_allclose(cov[:, off], noise[:, off], rtol=1e-12)
    # the noise part is eiv's variance times level / own
    v_eiv = band_variances(9 * lead * own[:, None, None])
    np.testing.assert_allclose(noise_var, v_eiv * (level / own)[:, None],
                               rtol=1e-12)
    switched = level == own
    assert 0 < switched.mean() < 0.5  # some misfit windows keep their own level
    # the estimator: normalised spectra, the same variance
    np.testing.assert_allclose(est.frf_std_**2,
                               one_sided_fast_grid(var, 1200, 3, conj=False),
                               rtol=1e-7)
    np.testing.assert_array_equal(est.frf_, eiv.frf_)
    np.testing.assert_allclose(est.frf_std_**2, np.real(est.frf_cov_[0, 0, 0]),
                               rtol=1e-12)
    # through calibrated_local_fit, the same
    out = calibrated_local_fit(U, Y, layout, fit, "eiv_robust")
    np.testing.assert_allclose(out.system_var, var, rtol=1e-12)


def test_invalid_windows_stay_nan(record):
    u, y = record
    layout = LocalModelLayout(F=3, half_window=18, num_degree=4,
                              transient_degree=4, den_degree=7)
    U, Y = dft(u)[None], dft(y)[None]
    fit = fit_local_models(U, Y, layout, return_cov=True)
    fit.well_posed[5] = False
    fit.theta[5] = np.nan
    fit.system[5] = np.nan
    fit.rss[5] = np.nan
    out = calibrated_local_fit(U, Y, layout, fit, "eiv_robust")
    assert np.all(np.isnan(out.system_var[5])) and np.all(np.isnan(out.system_cov[5]))
    assert np.all(np.isfinite(out.system_var[[4, 6]]))


def test_mimo_rows_take_the_route():
    """2x2, two experiments: each output row gets the route (std >= the eiv
    noise part's typical size, the same FRF, diagonal of frf_cov_)."""
    system = mimo_wafer_stage().G[0:2, 0:2]
    rng = np.random.default_rng(0)
    u = orthogonal_multisines(2, 1200, rms=1.44, rng=rng)
    y = np.stack([simulate(system, u[p], 3, snr_db=45, rng=rng).y_l
                  for p in range(2)])
    a = LRMBeyondNyquist(std_method="eiv_robust").fit(u, y, 3)
    b = LRMBeyondNyquist(std_method="eiv").fit(u, y, 3)
    np.testing.assert_array_equal(a.frf_, b.frf_)
    assert a.frf_std_.shape == b.frf_std_.shape == (2, 2, 601)
    assert np.all(np.isfinite(a.frf_std_))
    diagonal = np.real(np.diagonal(a.frf_cov_, axis1=1, axis2=2))
    np.testing.assert_allclose(a.frf_std_**2, np.moveaxis(diagonal, -1, 1),
                               rtol=1e-12)
    ratio = np.median(a.frf_std_ / b.frf_std_, axis=-1)
    assert np.all((ratio > 0.9) & (ratio < 1.2)), ratio


def test_mimo_entries_are_the_route_of_their_output_row():
    """2x2, two experiments (the 3-D input of generalisation_std --mimo):
    entry (o, i) of frf_std_ is the route of output row o on the bands of
    input i (bands i F .. i F + F - 1 of the row's local problem), mapped to
    the fast grid, to round-off."""
    F, N = 2, 800
    system = mimo_wafer_stage(downsampling_factor=F).G[0:2, 0:2]
    rng = np.random.default_rng(1)
    u = orthogonal_multisines(2, N, rms=1.44, rng=rng)
    y = np.stack([simulate(system, u[p], F, snr_db=30, rng=rng).y_l
                  for p in range(2)])
    est = LRMBeyondNyquist(std_method="eiv_robust").fit(u, y, F)
    assert est.frf_std_.shape == (2, 2, N // 2 + 1)
    U, Y = dft(u).reshape(2, -1), dft(y)
    for o in range(2):
        fit = fit_local_models(U, Y[:, o], est.layout_, return_cov=True)
        out = calibrated_local_fit(U, Y[:, o], est.layout_, fit, "eiv_robust")
        for i in range(2):
            expected = one_sided_fast_grid(out.system_var[:, i * F:(i + 1) * F],
                                           N, F, conj=False)
            np.testing.assert_allclose(est.frf_std_[o, i] ** 2, expected,
                                       rtol=1e-9)


def test_errors_name_the_option(record):
    u, y = record
    with pytest.raises(ValueError, match=r"`std_method` must be one of .*eiv_robust"):
        LRMBeyondNyquist(std_method="robust").fit(u, y, 3)
    # the streamed path cannot see the neighbouring windows: a clear error
    spectra = OneSidedSpectra.from_records(u[None, None], y[None, None], 3)
    layout = LRMBeyondNyquist().fit(u, y, 3).layout_
    with pytest.raises(ValueError, match="'eiv_robust' does not stream"):
        next(iter_calibrated_fits(spectra, layout, "eiv_robust"))

    # band_covariance has the variance terms but not the local models: it
    # cannot add the neighbour term, so it names the function that can
    # instead of returning the noise part under the route's name
    fit = LRMBeyondNyquist(std_method="lemma2").fit(u, y, 3)
    U, Y = dft(u)[None], dft(y)[None]
    terms = variance_terms(U, Y, layout, fit.local_fit_.theta,
                           fit.local_fit_.slow_bins, with_hc=False)
    with pytest.raises(ValueError, match="robust_band_covariance"):
        band_covariance(terms, layout, "eiv_robust",
                        slow_bins=fit.local_fit_.slow_bins, n_slow=400)


@pytest.mark.parametrize("refinement", [{"sk_iterations": 2},
                                        {"lm_iterations": 2}])
def test_refinement_with_the_robust_route_is_an_error(record, refinement):
    """The route is computed from the closed form's neighbouring local models;
    refined fits keep their own noise level for every route but "eiv", so
    "eiv_robust" with SK or LM would silently give Lemma 2's refined std (the
    same as std_method="lemma2"): an error naming the fix, before the data
    are read."""
    u, y = record
    est = LRMBeyondNyquist(std_method="eiv_robust", **refinement)
    with pytest.raises(ValueError, match=r"eiv_robust.*closed form.*'eiv'"):
        est.fit(u, y, 3)
    with pytest.raises(ValueError, match=r"eiv_robust.*closed form"):
        est.fit(None, None, 3)  # a parameter error, checked first


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
def test_refined_fit_function_refuses_the_robust_route(record):
    """The public calibrated_refined_fit, like the estimator: "eiv_robust"
    (and a misspelt route) raise instead of returning the refinement's own
    std unchanged under that name; "eiv" still rescales it."""
    u, y = record
    layout = LRMBeyondNyquist().fit(u, y, 3).layout_
    U, Y = dft(u)[None], dft(y)[None]
    closed = fit_local_models(U, Y, layout, return_cov=True)
    refined = refine_local_models(
        U, Y, layout, closed, sk_iterations=2, lm_iterations=0, tol=1e-6,
        guard=0.5, jump=5.0, keep_best=True, chunk_size=None, verbose=False,
    ).local_fit
    with pytest.raises(ValueError, match=r"eiv_robust.*closed form.*'eiv'"):
        calibrated_refined_fit(U, Y, layout, closed, refined, "eiv_robust")
    with pytest.raises(ValueError, match=r"`method` must be one of"):
        calibrated_refined_fit(U, Y, layout, closed, refined, "eiv-robust")
    scaled = calibrated_refined_fit(U, Y, layout, closed, refined, "eiv")
    ratio = scaled.system_var / refined.system_var
    ok = np.isfinite(ratio)
    assert ok.any() and not np.allclose(ratio[ok], 1.0)
    # one factor per window, the same for all bands
    np.testing.assert_allclose(ratio[ok.all(axis=1)],
                               ratio[ok.all(axis=1)][:, :1].repeat(3, axis=1))


# --- Monte Carlo ------------------------------------------------------------------

def _coverage(stage_seed, channel, n_runs, M=200, F=3, snr_db=30):
    """(ratio, coverage) of "eiv" and "eiv_robust" on the same records."""
    stage, _ = random_stage(stage_seed, downsampling_factor=F)
    system = getattr(stage, channel)
    rng = np.random.default_rng(stage_seed + 7)
    N = M * F
    u = multisine(N, rms=1.44, rng=rng)
    sim = simulate(system, u, F, snr_db=snr_db, rng=rng)
    truth = true_frf(system, N)
    est, var = [], {"eiv": [], "eiv_robust": []}
    for _ in range(n_runs):
        y = sim.y_l_clean + sim.noise_std * rng.standard_normal(M)
        for method in var:
            fit = LRMBeyondNyquist(half_window=18, std_method=method).fit(u, y, F)
            var[method].append(fit.frf_std_**2)
        est.append(fit.frf_)
    est = np.array(est)
    mc = np.sqrt(np.sum(np.abs(est - est.mean(0)) ** 2, axis=0) / (n_runs - 1))
    bins = np.all(np.isfinite(est), axis=0) & (mc > 0)
    bins[0] = False
    error = np.abs(est - truth)[:, bins]
    out = {}
    for method, v in var.items():
        v = np.array(v)[:, bins]
        out[method] = (np.median(np.sqrt(v.mean(0)) / mc[bins]),
                       np.mean(error <= 2 * np.sqrt(v)))
    return out


def test_robust_route_covers_more_than_eiv_on_a_random_stage():
    """F = 3, 30 dB, 20 runs of M = 400 on a random stage: "eiv_robust" covers
    the truth within 2 std more often than "eiv" and keeps its median ratio
    to the Monte-Carlo std near 1. Measured on stages 0-9 (both channels, the
    records of this function): coverage gain 0.018-0.033 and ratio
    0.985-1.053 with 20 runs (M = 200, 30 runs: gain 0.018-0.045); this
    stage with six other noise seeds: gain 0.023-0.029, ratio 0.983-1.032.
    The bounds leave room for the Monte-Carlo noise of 20 runs."""
    out = _coverage(3, "G_z", n_runs=20, M=400)
    (r_eiv, c_eiv), (r_rob, c_rob) = out["eiv"], out["eiv_robust"]
    assert c_rob > c_eiv + 0.01, out
    assert 0.95 < r_rob < 1.10, out
    assert r_rob > r_eiv, out  # never a smaller std at the median
