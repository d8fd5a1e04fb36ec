"""Closed-form choice of window and degrees: LRMBeyondNyquistCV, LPMBeyondNyquistCV."""

from __future__ import annotations

import pickle
import warnings

import control
import joblib
import numpy as np
import pytest
from conftest import frf_of, resonant_system, simulate_resonant
from sklearn.base import clone

from lrmfrf import LPMBeyondNyquist, LRMBeyondNyquist, multisine
from lrmfrf.estimators.selection import (
    GAIC_PENALTY,
    LPMBeyondNyquistCV,
    LRMBeyondNyquistCV,
    local_model_criterion,
)
from lrmfrf.windows import LocalModelLayout, local_regressor

N, F = 600, 3
M = N // F
SMALL_GRID = {"half_windows": (8, 12), "num_degrees": (1, 2), "den_degrees": (0, 4)}


def _data(rng, P=1, noise_std=0.01, n_samples=N):
    u = np.array([multisine(n_samples, rng=rng) for _ in range(P)])
    y = simulate_resonant(u, F, noise_std, rng)
    return (u[0], y[0]) if P == 1 else (u, y)


def _dfts(u, y):
    return np.fft.fft(np.atleast_2d(u), axis=1), np.fft.fft(np.atleast_2d(y), axis=1)


def _brute_force_loo(U, Y, layout, bins, rows):
    """Refit each window without one equation; squared prediction errors."""
    A, b = local_regressor(U, Y, np.asarray(bins), layout)
    out = np.empty((len(bins), len(rows)))
    for w in range(len(bins)):
        for j, row in enumerate(rows):
            keep = np.arange(A.shape[1]) != row
            theta = np.linalg.lstsq(A[w, keep], b[w, keep], rcond=None)[0]
            out[w, j] = abs(b[w, row] - A[w, row] @ theta) ** 2
    return out


# --- the criterion does not depend on the spectra's scale -----------------------


@pytest.mark.parametrize("criterion", ["aicc", "gcv", "press", "gaic"])
def test_local_model_criterion_is_scale_invariant(criterion):
    """Spectra at 2**+-600 give the criterion of the ordinary ones in their own
    units (their residuals overflowed or underflowed: every window invalid, a
    log of 0, or an overflow error), and the inputs' scale does not enter."""
    rng = np.random.default_rng(3)
    U, Y = _dfts(*_data(rng, P=2))
    layout = LocalModelLayout(F=F, half_window=8, num_degree=2, transient_degree=1,
                              den_degree=3, n_experiments=2)
    ref = local_model_criterion(U, Y, layout, criterion=criterion)
    assert ref.n_invalid == 0 and np.isfinite(ref.value)
    U_in, Y_in = U.copy(), Y.copy()
    for u_exp, y_exp in [(600, 0), (-600, 0), (0, 600), (0, -600), (-500, 500)]:
        U_s, Y_s = np.ldexp(1.0, u_exp) * U, np.ldexp(1.0, y_exp) * Y
        got = local_model_criterion(U_s, Y_s, layout, criterion=criterion)
        assert got.n_invalid == 0
        # per window: squared outputs, exact up to the power of two (beyond
        # the float range inf or 0, as the estimators' variances)
        with np.errstate(over="ignore", under="ignore"):
            per_bin, value = (np.ldexp(ref.per_bin, 2 * y_exp),
                              np.ldexp(ref.value, 2 * y_exp))
        np.testing.assert_array_equal(got.per_bin, per_bin)
        if criterion in ("aicc", "gaic"):  # logs of a squared output
            assert got.value == pytest.approx(
                ref.value + 2 * y_exp * np.log(2.0), rel=1e-13, abs=1e-12)
        else:
            assert got.value == value
    # the caller's arrays are not modified
    np.testing.assert_array_equal(U, U_in)
    np.testing.assert_array_equal(Y, Y_in)


# --- the criterion is an exact leave-one-out ------------------------------------


@pytest.mark.parametrize("P", [1, 2])
def test_press_equals_brute_force_leave_one_out(P):
    rng = np.random.default_rng(0)
    U, Y = _dfts(*_data(rng, P=P))
    layout = LocalModelLayout(F=F, half_window=8, num_degree=2, transient_degree=1,
                              den_degree=3, n_experiments=P)
    bins = [0, 1, 37, M // 2]
    centre_rows = [p * layout.window + layout.half_window for p in range(P)]
    brute = _brute_force_loo(U, Y, layout, bins, centre_rows)
    per_bin = local_model_criterion(U, Y, layout, criterion="press").per_bin
    np.testing.assert_allclose(per_bin[bins], brute.sum(axis=1) / (P * M),
                               rtol=1e-8)


def test_press_value_is_mean_over_all_slow_bins():
    """Solving bins 0..M//2 and weighting the mirrors equals the mean over all M
    windows (periodic windows + real data: window M-k mirrors window k)."""
    rng = np.random.default_rng(1)
    for n_samples in (N, N + F):  # M even and odd
        U, Y = _dfts(*_data(rng, n_samples=n_samples))
        m = Y.shape[1]
        layout = LocalModelLayout(F=F, half_window=6, num_degree=1,
                                  transient_degree=1, den_degree=2)
        every_bin = _brute_force_loo(U, Y, layout, np.arange(m), [6])[:, 0] / m
        value = local_model_criterion(U, Y, layout, criterion="press").value
        assert value == pytest.approx(every_bin.mean(), rel=1e-8)


def test_press_of_noise_only_data_is_the_noise_variance():
    """G = 0, R_e = 0: the centre LOO error of a linear smoother with fixed
    regressors has expectation sigma_V^2 (1 + E[h_cc/(1-h_cc)]) >= sigma_V^2;
    in time-domain units (divide by M) the noise variance sigma^2, inflated by
    about p/L = 9/25 at most. We check sigma^2 <= value <= 1.5 sigma^2 with a
    Monte-Carlo SE of ~1/sqrt(100 bins) = 10 %."""
    rng = np.random.default_rng(2)
    sigma = 0.5
    u = rng.standard_normal(N)
    y = sigma * rng.standard_normal(M)
    layout = LocalModelLayout(F=F, half_window=12, num_degree=1, transient_degree=2,
                              den_degree=0)
    value = local_model_criterion(*_dfts(u, y), layout, criterion="press").value
    assert 0.8 * sigma**2 < value < 1.5 * sigma**2


def test_gcv_and_aicc_from_the_window_residuals():
    rng = np.random.default_rng(3)
    for n_samples in (N, N + F):  # M even and odd
        u, y = _data(rng, n_samples=n_samples)
        m = n_samples // F
        est = LRMBeyondNyquist(half_window=10, num_degree=2, transient_degree=2,
                               den_degree=3).fit(u, y, F)
        layout = est.layout_
        L, p = layout.n_equations, layout.n_params
        gcv = local_model_criterion(*_dfts(u, y), layout, criterion="gcv")
        residual = est.local_fit_.rss / L / m
        np.testing.assert_allclose(gcv.per_bin, residual, rtol=1e-10)
        # Mean over all M windows: bins 1..(M-1)//2 stand for their mirrors.
        weights = np.ones(m // 2 + 1)
        weights[1 : (m + 1) // 2] = 2
        mean = np.sum(weights * residual) / m
        assert gcv.value == pytest.approx(mean / (1 - p / L) ** 2, rel=1e-10)
        aicc = local_model_criterion(*_dfts(u, y), layout, criterion="aicc")
        assert aicc.value == pytest.approx(np.log(mean) + (L + p) / (L - p - 1),
                                           rel=1e-10)
        # GAIC: the same weights on the log of each window's residual variance
        gaic = local_model_criterion(*_dfts(u, y), layout, criterion="gaic")
        np.testing.assert_allclose(gaic.per_bin, residual, rtol=1e-10)
        log_mean = np.sum(weights * np.log(residual)) / m
        assert gaic.value == pytest.approx(
            log_mean + GAIC_PENALTY * p / (L - p - 1), rel=1e-10)


def _brute_force_bands(U, Y, layout, bins):
    """Band values and Lemma-2 variances of each window by numpy's lstsq."""
    A, b = local_regressor(U, Y, np.asarray(bins), layout)
    systems, variances = [], []
    for w in range(len(bins)):
        theta, rss = np.linalg.lstsq(A[w], b[w], rcond=None)[:2]
        gram_inv = np.linalg.inv(A[w].conj().T @ A[w])
        s2 = float(rss[0]) / layout.dof
        systems.append(layout.F * theta[: layout.n_bands])
        variances.append(layout.F**2 * np.real(np.diag(gram_inv))[: layout.n_bands]
                         * s2)
    return np.array(systems), np.array(variances)


def test_pmse_from_brute_force_band_values():
    """PMSE (the default): with G_r, var_r the band values and Lemma-2
    variances of the widest, richest candidate, each candidate's criterion is
    the median over band values (DC excluded) of
    (max(|G_c - G_r|^2 - var_r, 0) + 2 var_c) / |G_r|^2, recomputed here with
    numpy's lstsq and an explicit inverse."""
    rng = np.random.default_rng(11)
    u, y = _data(rng)
    U, Y = _dfts(u, y)
    grid = {"half_windows": (8, 12), "num_degrees": (1, 2), "den_degrees": (2,)}
    cv = LRMBeyondNyquistCV(**grid).fit(u, y, F)
    params = cv.cv_results_["params"]
    bins = np.arange(M // 2 + 1)
    bands = [_brute_force_bands(U, Y, LocalModelLayout(F=F, **p), bins)
             for p in params]
    ref = params.index({"half_window": 12, "num_degree": 2, "transient_degree": 2,
                        "den_degree": 2})
    G_r, var_r = bands[ref]
    for i, (G_c, var_c) in enumerate(bands):
        rel = (np.maximum(np.abs(G_c - G_r) ** 2 - var_r, 0) + 2 * var_c) \
            / np.abs(G_r) ** 2
        rel[0, 0] = np.nan
        assert cv.cv_results_["criterion"][i] == pytest.approx(
            np.nanmedian(rel), rel=1e-8)
    assert cv.best_index_ == int(np.argmin(cv.cv_results_["criterion"]))


@pytest.mark.parametrize("n_outputs", [1, 2])
def test_pmse_ingredients_equal_the_qr_solve(n_outputs):
    """PMSE's band values and Lemma-2 variances come from the estimator's
    closed form (normal equations); the QR solve with leverages gives the same
    values (1e-9 relative), variances (1e-6) and well-posed windows, for one
    output and for two output rows (two experiments, two inputs)."""
    from lrmfrf.estimators.selection import _local_criteria, _pmse_ingredients

    rng = np.random.default_rng(21)
    if n_outputs == 1:
        U, Y = _dfts(*_data(rng))
        layout = LocalModelLayout(F=F, half_window=12, num_degree=2,
                                  transient_degree=2, den_degree=4)
        rows = [Y]
    else:
        u = rng.standard_normal((2, 2, N))
        mix = np.array([[1.0, 0.5], [0.7, -1.0]])  # output rows from the inputs
        y = np.stack([mix @ simulate_resonant(u[p], F, 0.0, rng) for p in range(2)])
        y = y + 0.01 * rng.standard_normal(y.shape)
        U = np.fft.fft(u, axis=-1).reshape(2, 2 * N)
        Y = np.fft.fft(y, axis=-1)  # (P, n_y, M)
        layout = LocalModelLayout(F=F, n_experiments=2, n_inputs=2,
                                  half_window=12, num_degree=2,
                                  transient_degree=2, den_degree=2)
        rows = [Y[:, o] for o in range(2)]
    system, var, ok = _pmse_ingredients(U, Y, layout)
    assert system.shape == (n_outputs, M // 2 + 1, layout.n_bands)
    for o, Y_o in enumerate(rows):
        _, ok_qr, system_qr, var_qr = _local_criteria(U, Y_o, layout,
                                                      variance=True)
        np.testing.assert_array_equal(ok[o], ok_qr)
        assert ok_qr.sum() > M // 4
        np.testing.assert_allclose(system[o][ok_qr], system_qr[ok_qr], rtol=1e-9)
        np.testing.assert_allclose(var[o][ok_qr], var_qr[ok_qr], rtol=1e-6)
        assert np.isnan(system[o][~ok_qr]).all()


def test_pmse_ingredients_mark_unexcited_windows_invalid():
    """Windows with a band the input hardly excites (its DFT scaled by 1e-9
    within N/10 of N/2: band 1 of the upper windows) have no PMSE value:
    mask False, band values and variances NaN, the same mask as the QR
    solve's."""
    from lrmfrf.estimators.selection import _local_criteria, _pmse_ingredients

    rng = np.random.default_rng(23)
    u, y = _data(rng)
    U, Y = _dfts(u, y)
    U[:, N // 2 - N // 10 : N // 2 + N // 10 + 1] *= 1e-9
    layout = LocalModelLayout(F=F, half_window=12, num_degree=2,
                              transient_degree=2, den_degree=2)
    system, var, ok = _pmse_ingredients(U, Y, layout)
    _, ok_qr, _, _ = _local_criteria(U, Y, layout, variance=True)
    np.testing.assert_array_equal(ok[0], ok_qr)
    assert 0.2 < np.mean(ok[0]) < 0.8  # both kinds of window present
    assert np.isnan(system[0][~ok[0]]).all() and np.isnan(var[0][~ok[0]]).all()
    assert np.isfinite(system[0][ok[0]]).all() and np.isfinite(var[0][ok[0]]).all()


def test_pmse_has_no_value_for_one_layout():
    rng = np.random.default_rng(12)
    layout = LocalModelLayout(F=F, half_window=8, num_degree=1,
                              transient_degree=1, den_degree=2)
    with pytest.raises(ValueError, match="'pmse' criterion compares each "
                                         "candidate.*LRMBeyondNyquistCV"):
        local_model_criterion(*_dfts(*_data(rng)), layout, criterion="pmse")


# --- the estimators ----------------------------------------------------------------


def test_cv_results_structure_and_best_candidate():
    rng = np.random.default_rng(4)
    u, y = _data(rng)
    cv = LRMBeyondNyquistCV(**SMALL_GRID, criterion="gaic").fit(u, y, F)
    results = cv.cv_results_
    n_candidates = 2 * 2 * 2
    assert len(results["params"]) == n_candidates
    for key in ("param_half_window", "param_num_degree", "param_transient_degree",
                "param_den_degree", "n_params", "dof", "identifiable",
                "n_invalid_bins", "criterion", "rank"):
        assert results[key].shape == (n_candidates,), key
    # No key pretends to be a held-out score.
    assert not [key for key in results if "test" in key or "score" in key]
    # R_t = R_g when transient_degrees is None.
    assert all(p["transient_degree"] == p["num_degree"] for p in results["params"])
    assert sorted(results["rank"]) == list(range(1, n_candidates + 1))
    assert results["rank"][cv.best_index_] == 1
    assert cv.best_params_ == results["params"][cv.best_index_]
    # The best has the lowest criterion of those with the fewest invalid bins.
    fewest = results["n_invalid_bins"] == results["n_invalid_bins"].min()
    assert cv.best_criterion_ == np.min(results["criterion"][fewest])
    # The criterion of each candidate is the standalone function's value.
    layout = LocalModelLayout(F=F, **cv.best_params_)
    assert cv.best_criterion_ == pytest.approx(
        local_model_criterion(*_dfts(u, y), layout, criterion="gaic").value,
        rel=1e-12)


@pytest.mark.parametrize("CV", [LRMBeyondNyquistCV, LPMBeyondNyquistCV])
def test_old_score_names_warn_and_keep_their_values(CV):
    """best_score_ and cv_results_["mean_test_score"/"rank_test_score"] were a
    negated criterion, not held-out scores: kept one release with a
    FutureWarning, with their old values."""
    rng = np.random.default_rng(18)
    u, y = _data(rng)
    cv = CV(half_windows=(8, 12)).fit(u, y, F)
    assert "best_score_" not in vars(cv)
    with pytest.warns(FutureWarning, match="`best_score_` is deprecated.*Use "
                                           "`best_criterion_`"):
        assert cv.best_score_ == -cv.best_criterion_
    results = cv.cv_results_
    with pytest.warns(FutureWarning, match=r"cv_results_\['mean_test_score'\] is "
                                           "deprecated.*criterion"):
        np.testing.assert_array_equal(results["mean_test_score"],
                                      -results["criterion"])
    with pytest.warns(FutureWarning, match=r"cv_results_\['rank_test_score'\] is "
                                           r"deprecated.*cv_results_\['rank'\]"):
        np.testing.assert_array_equal(results["rank_test_score"], results["rank"])
    # Hidden from listings, and other keys are still missing.
    assert "mean_test_score" not in results and "rank_test_score" not in list(
        results)
    with pytest.raises(KeyError, match="no_such_key"):
        results["no_such_key"]
    # An unfitted estimator has no best_score_ (hasattr is False, no warning).
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not hasattr(CV(), "best_score_")


def test_refit_is_the_plain_estimator_with_best_params():
    rng = np.random.default_rng(5)
    u, y = _data(rng)
    cv = LRMBeyondNyquistCV(**SMALL_GRID).fit(u, y, F, sample_time=0.5e-3)
    plain = LRMBeyondNyquist(**cv.best_params_).fit(u, y, F, sample_time=0.5e-3)
    assert isinstance(cv.best_estimator_, LRMBeyondNyquist)
    for name in ("frequencies_", "frf_", "frf_std_", "valid_", "noise_variance_",
                 "transient_", "slow_frequencies_"):
        np.testing.assert_array_equal(getattr(cv, name), getattr(plain, name))
    assert cv.dof_ == plain.dof_ and cv.n_params_ == plain.n_params_
    np.testing.assert_array_equal(cv.predict(u), plain.predict(u))
    assert cv.score(u, y) == plain.score(u, y)
    frd = cv.to_frd()
    assert isinstance(frd, control.FrequencyResponseData)
    np.testing.assert_allclose(frd.omega, 2 * np.pi * plain.frequencies_)


def test_clone_and_get_params_follow_scikit_learn():
    est = LRMBeyondNyquistCV(half_windows=(9,), criterion="gcv", n_jobs=2)
    params = est.get_params()
    assert params["half_windows"] == (9,) and params["criterion"] == "gcv"
    # PMSE generalised best on random stages (issue 15,
    # benchmarks/generalisation_selection.py); LPM keeps AICc (not measured)
    assert LRMBeyondNyquistCV().criterion == "pmse"
    assert LPMBeyondNyquistCV().criterion == "aicc"
    assert clone(est).get_params() == params


@pytest.mark.parametrize("criterion", ["aicc", "gcv", "press", "gaic", "pmse"])
def test_rejects_a_polynomial_model_on_a_resonant_system(criterion):
    """den_degree 0 (polynomial) is bias-limited at 1 %-damped resonances over a
    25-bin window: the criterion must prefer R_e = 4, and the chosen setting's
    true error is the lower one."""
    rng = np.random.default_rng(6)
    b, a = resonant_system()
    G = frf_of(b, a, N)
    u, y = _data(rng, noise_std=0.002)
    cv = LRMBeyondNyquistCV(half_windows=(12,), num_degrees=(2,),
                            den_degrees=(0, 4), criterion=criterion).fit(u, y, F)
    assert cv.best_params_["den_degree"] == 4
    lpm_like = LRMBeyondNyquist(half_window=12, num_degree=2, transient_degree=2,
                                den_degree=0).fit(u, y, F)
    assert np.median(np.abs(cv.frf_ - G)) < 0.5 * np.median(np.abs(lpm_like.frf_ - G))


def test_selected_setting_is_near_the_best_of_the_grid():
    """Fast version of benchmarks/selection.py on the two-mode test system:
    over 4 realisations, the median true error of the selected settings is
    within 1.5x of the best fixed setting (on the same realisations).
    1.5x (not the benchmark's 1.1x) because 4 realisations of a 600-sample
    record leave the choice noisy."""
    b, a = resonant_system()
    G = frf_of(b, a, N)
    grid = {"half_windows": (8, 12, 16), "num_degrees": (1, 2),
            "den_degrees": (2, 4)}
    rng = np.random.default_rng(7)
    selected, per_candidate = [], []
    for _ in range(4):
        u, y = _data(rng, noise_std=0.005)
        cv = LRMBeyondNyquistCV(**grid).fit(u, y, F)
        errors = []
        for params, ok in zip(cv.cv_results_["params"],
                              cv.cv_results_["identifiable"], strict=True):
            if not ok:
                errors.append(np.inf)
                continue
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                est = LRMBeyondNyquist(**params).fit(u, y, F)
            errors.append(np.median(np.abs(est.frf_ - G) / np.abs(G)))
        per_candidate.append(errors)
        selected.append(errors[cv.best_index_])
    best_fixed = np.min(np.median(per_candidate, axis=0))
    assert np.median(selected) < 1.5 * best_fixed


def test_multi_experiment_cv_counts_equations_of_all_experiments():
    rng = np.random.default_rng(8)
    u, y = _data(rng, P=3)
    # n = 4: 9 bins; (2+1)*3 + P*(2+1) + 2 = 20 parameters > 9 for P = 1 but
    # < 27 equations with P = 3.
    cv = LRMBeyondNyquistCV(half_windows=(4,), num_degrees=(2,),
                            den_degrees=(2,)).fit(list(u), list(y), F)
    assert cv.n_experiments_ == 3 and cv.cv_results_["dof"][0] == 27 - 20
    assert cv.transient_.shape == (3, M // 2 + 1)


def test_lpm_cv_refits_the_polynomial_estimator():
    rng = np.random.default_rng(9)
    u, y = _data(rng)
    cv = LPMBeyondNyquistCV(half_windows=(6, 12), num_degrees=(1, 2)).fit(u, y, F)
    assert isinstance(cv.best_estimator_, LPMBeyondNyquist)
    assert set(cv.best_params_) == {"half_window", "num_degree", "transient_degree"}
    plain = LPMBeyondNyquist(**cv.best_params_).fit(u, y, F)
    np.testing.assert_array_equal(cv.frf_, plain.frf_)
    assert (cv.cv_results_["param_transient_degree"]
            == cv.cv_results_["param_num_degree"]).all()


def test_lpm_cv_degrees_is_a_deprecated_alias_of_num_degrees():
    rng = np.random.default_rng(9)
    u, y = _data(rng)
    new = LPMBeyondNyquistCV(half_windows=(6, 12), num_degrees=(1, 2)).fit(u, y, F)
    old = LPMBeyondNyquistCV(half_windows=(6, 12), degrees=(1, 2))
    with pytest.warns(FutureWarning, match="renamed `num_degrees`") as record:
        old.fit(u, y, F)
    assert record[0].filename == __file__  # points at the caller of fit
    assert old.best_params_ == new.best_params_
    np.testing.assert_array_equal(old.frf_, new.frf_)
    with pytest.raises(ValueError, match="Pass num_degrees only"):
        LPMBeyondNyquistCV(num_degrees=(3,), degrees=(1, 2)).fit(u, y, F)


def test_infeasible_candidates_are_reported_and_ranked_last():
    rng = np.random.default_rng(10)
    u, y = _data(rng)
    # n = 3 (7 bins) cannot hold (2+1)*3 + 3 + 4 = 16 parameters.
    cv = LRMBeyondNyquistCV(half_windows=(3, 12), num_degrees=(2,),
                            den_degrees=(4,)).fit(u, y, F)
    results = cv.cv_results_
    assert list(results["identifiable"]) == [False, True]
    assert results["criterion"][0] == np.inf and results["rank"][0] == 2
    assert cv.best_params_["half_window"] == 12


def test_n_jobs_gives_identical_results():
    rng = np.random.default_rng(11)
    u, y = _data(rng)
    serial = LRMBeyondNyquistCV(**SMALL_GRID).fit(u, y, F)
    # Threads keep the test fast; process-based backends are tested in
    # tests/test_parallel.py.
    with joblib.parallel_config(backend="threading"):
        parallel = LRMBeyondNyquistCV(**SMALL_GRID, n_jobs=2).fit(u, y, F)
    np.testing.assert_array_equal(serial.cv_results_["criterion"],
                                  parallel.cv_results_["criterion"])
    assert serial.best_params_ == parallel.best_params_


def test_input_is_not_modified():
    rng = np.random.default_rng(12)
    u, y = _data(rng)
    u0, y0 = u.copy(), y.copy()
    LRMBeyondNyquistCV(**SMALL_GRID).fit(u, y, F)
    np.testing.assert_array_equal(u, u0)
    np.testing.assert_array_equal(y, y0)


# --- bad input ------------------------------------------------------------------------


def test_empty_grid_is_rejected():
    rng = np.random.default_rng(13)
    u, y = _data(rng)
    with pytest.raises(ValueError, match="grid is empty: `half_windows` has no"):
        LRMBeyondNyquistCV(half_windows=()).fit(u, y, F)
    with pytest.raises(ValueError, match="grid is empty: `num_degrees` has no"):
        LPMBeyondNyquistCV(num_degrees=[]).fit(u, y, F)


def test_grid_without_identifiable_candidate_is_rejected():
    rng = np.random.default_rng(14)
    u, y = _data(rng)
    with pytest.raises(ValueError, match="No candidate of the grid is identifiable"):
        LRMBeyondNyquistCV(half_windows=(2, 3), num_degrees=(4,),
                           den_degrees=(4,)).fit(u, y, F)
    # Square local problems (n = 4: 9 bins; (1+1)*3 + (0+1) + 2 = 9
    # parameters) leave no residual to score.
    with pytest.raises(ValueError, match="0 residual dof, the 'press' criterion "
                                         "needs at least 1"):
        LRMBeyondNyquistCV(half_windows=(4,), num_degrees=(1,), criterion="press",
                           transient_degrees=(0,), den_degrees=(2,)).fit(u, y, F)
    # AICc and GAIC (the default) need L - p - 1 > 0.
    for criterion in ("aicc", "gaic"):
        with pytest.raises(ValueError, match=f"1 residual dof, the '{criterion}' "
                                             "criterion needs at least 2"):
            LRMBeyondNyquistCV(half_windows=(4,), num_degrees=(1,),
                               criterion=criterion, transient_degrees=(0,),
                               den_degrees=(1,)).fit(u, y, F)


def test_input_exciting_no_band_is_rejected():
    """A single sine leaves every window rank-deficient."""
    n = np.arange(N)
    u = np.sin(2 * np.pi * 10 * n / N)
    y = simulate_resonant(u, F, 0.0, np.random.default_rng(15))
    with pytest.raises(ValueError, match="every local problem .* rank-deficient"):
        LRMBeyondNyquistCV(**SMALL_GRID).fit(u, y, F)


def test_bad_criterion_and_grid_values_are_rejected():
    rng = np.random.default_rng(16)
    u, y = _data(rng)
    with pytest.raises(ValueError, match="`criterion` must be one of.*'loo'"):
        LRMBeyondNyquistCV(criterion="loo").fit(u, y, F)
    with pytest.raises(TypeError, match=r"`half_windows\[1\]` must be an integer"):
        LRMBeyondNyquistCV(half_windows=(12, 2.5)).fit(u, y, F)
    with pytest.raises(TypeError, match="`den_degrees` must be a sequence"):
        LRMBeyondNyquistCV(den_degrees=None).fit(u, y, F)
    with pytest.raises(ValueError, match=r"`num_degrees\[0\]` must be an integer >= 0"):
        LRMBeyondNyquistCV(num_degrees=(-1,)).fit(u, y, F)
    layout = LocalModelLayout(F=F, half_window=4, num_degree=1, transient_degree=0,
                              den_degree=2)
    with pytest.raises(ValueError, match="needs at least 1 residual degree"):
        local_model_criterion(*_dfts(u, y), layout, criterion="gcv")
    with pytest.raises(ValueError, match="`criterion` must be one of"):
        local_model_criterion(*_dfts(u, y), layout, criterion="aic")


def test_unequal_records_and_mismatched_experiments_are_rejected():
    rng = np.random.default_rng(17)
    u, y = _data(rng, P=2)
    with pytest.raises(ValueError, match="must have equal length"):
        LRMBeyondNyquistCV(**SMALL_GRID).fit([u[0], u[1][:-3]], list(y), F)
    with pytest.raises(ValueError, match="u_h holds 2 experiment.*y_l holds 1"):
        LRMBeyondNyquistCV(**SMALL_GRID).fit(list(u), list(y[:1]), F)


# --- scikit-learn contract and declared parameter checks -------------------------

CV_ESTIMATORS = [LRMBeyondNyquistCV, LPMBeyondNyquistCV]


@pytest.mark.parametrize("CV", CV_ESTIMATORS)
def test_every_parameter_has_one_declared_check(CV):
    assert set(CV._parameter_checks) == set(CV().get_params())


@pytest.mark.parametrize("CV, params, exc, match", [
    (LRMBeyondNyquistCV, {"criterion": "loo"}, ValueError,
     r"`criterion` must be one of \('aicc', 'gcv', 'press', 'gaic', 'pmse'\). "
     "Got 'loo'"),
    (LRMBeyondNyquistCV, {"half_windows": (12, 0)}, ValueError,
     r"`half_windows\[1\]` must be an integer >= 1. Got 0"),
    (LRMBeyondNyquistCV, {"num_degrees": "24"}, TypeError,
     "`num_degrees` must be a sequence of integers. Got '24'"),
    (LRMBeyondNyquistCV, {"transient_degrees": (1.5,)}, TypeError,
     r"`transient_degrees\[0\]` must be an integer"),
    (LRMBeyondNyquistCV, {"den_degrees": ()}, ValueError,
     "grid is empty: `den_degrees` has no values"),
    (LRMBeyondNyquistCV, {"n_jobs": 0}, ValueError,
     "`n_jobs` must be None or a non-zero integer. Got 0"),
    (LRMBeyondNyquistCV, {"verbose": "yes"}, TypeError,
     "`verbose` must be True or False. Got 'yes'"),
    (LPMBeyondNyquistCV, {"degrees": (-1,)}, ValueError,
     r"`degrees\[0\]` must be an integer >= 0. Got -1"),
    (LPMBeyondNyquistCV, {"n_jobs": 1.5}, ValueError,
     "`n_jobs` must be None or a non-zero integer. Got 1.5"),
    (LPMBeyondNyquistCV, {"criterion": None}, ValueError,
     "`criterion` must be one of .*Got None"),
])
def test_parameters_are_checked_before_the_data(CV, params, exc, match):
    """scikit-learn convention: parameters are validated at the start of fit.
    The data are also bad here (N != F*M); the parameter error must come
    first, and the constructor itself must not complain."""
    u, y = _data(np.random.default_rng(19))
    est = CV(**params)
    with pytest.raises(exc, match=match):
        est.fit(u[:-1], y, F)


def test_one_integer_is_a_grid_of_one_and_duplicates_are_dropped():
    u, y = _data(np.random.default_rng(20))
    cv = LRMBeyondNyquistCV(half_windows=12, num_degrees=(2, 2.0),
                            den_degrees=(4,)).fit(u, y, F)
    assert cv.cv_results_["params"] == [
        {"half_window": 12, "num_degree": 2, "transient_degree": 2, "den_degree": 4}]
    # The parameters themselves are stored as given (scikit-learn's clone).
    assert cv.get_params()["num_degrees"] == (2, 2.0)


def test_fitted_cv_pickles_with_its_results():
    u, y = _data(np.random.default_rng(21))
    cv = LRMBeyondNyquistCV(**SMALL_GRID).fit(u, y, F)
    again = pickle.loads(pickle.dumps(cv))
    np.testing.assert_array_equal(again.cv_results_["criterion"],
                                  cv.cv_results_["criterion"])
    assert again.best_criterion_ == cv.best_criterion_
    np.testing.assert_array_equal(again.predict(u), cv.predict(u))
    with pytest.warns(FutureWarning):
        again.cv_results_["rank_test_score"]


def test_docstring_examples_run():
    import doctest

    import lrmfrf.estimators.selection as module

    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0
    assert result.failed == 0


# --- GAIC, the default criterion (issue 15) ----------------------------------------


@pytest.mark.parametrize("criterion", ["gaic", "pmse"])
def test_gaic_prefers_the_true_degrees_on_in_class_data(criterion):
    """A first-order system is exactly a local rational model with R_e = 1:
    with noise, R_e = 6 only fits noise, so GAIC (and PMSE) must keep R_e = 1
    on every seed, and that choice has the lower true error."""
    from scipy.signal import lfilter

    b, a = [0.2, 0.1], [1.0, -0.5]
    G = frf_of(np.asarray(b), np.asarray(a), N)
    for seed in range(3):
        rng = np.random.default_rng(100 + seed)
        u = multisine(N, rng=rng)
        y = lfilter(b, a, u)[::F]
        y = y + 0.01 * np.std(y) * rng.standard_normal(y.size)
        cv = LRMBeyondNyquistCV(half_windows=(12,), num_degrees=(1,),
                                den_degrees=(1, 6),
                                criterion=criterion).fit(u, y, F)
        assert cv.best_params_["den_degree"] == 1
        over = LRMBeyondNyquist(half_window=12, num_degree=1, transient_degree=1,
                                den_degree=6).fit(u, y, F)
        assert (np.median(np.abs(cv.frf_ - G)) < np.median(np.abs(over.frf_ - G)))


def test_gaic_is_finite_on_noise_free_in_class_data():
    """An exact fit (rss = 0 up to round-off) in some windows must not make the
    criterion -inf: the log is floored at round-off of the mean."""
    from scipy.signal import lfilter

    u = multisine(N, rng=np.random.default_rng(5))
    y = lfilter([0.2, 0.1], [1.0, -0.5], u)[::F]
    layout = LocalModelLayout(F=F, half_window=8, num_degree=1, transient_degree=1,
                              den_degree=1)
    value = local_model_criterion(*_dfts(u, y), layout, criterion="gaic").value
    assert np.isfinite(value)


@pytest.mark.slow
def test_default_picks_near_the_oracle_on_held_out_random_stages():
    """Slow version of benchmarks/generalisation_selection.py on two held-out
    stages (seeds 2000-2001, closed loop, outputs y4 and z; M = 400, 30-45 dB):
    the mean over the 4 records of (pick error / best of the grid) of the
    default criterion is at most 1.25, the issue's bound on the worst record
    applied to the mean of a few records (the benchmark's 82 held-out records
    average 1.05 with PMSE)."""
    from lrmfrf.plants import random_stage
    from lrmfrf.simulate import simulate, true_frf

    ratios = []
    for k, seed in enumerate((2000, 2001)):
        stage, draw = random_stage(seed)
        F_s = draw.downsampling_factor
        n_s = 400 * F_s
        for name in ("G_y4", "G_z"):
            system = getattr(stage, name)
            rng = np.random.default_rng(31 + 2 * k + (name == "G_z"))
            u = multisine(n_s, rng=rng)
            y = simulate(system, u, F_s, snr_db=rng.uniform(30, 45), rng=rng).y_l
            G = true_frf(system, n_s)[1:]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                cv = LRMBeyondNyquistCV().fit(u, y, F_s)
                errors = [
                    np.nanmedian(np.abs(LRMBeyondNyquist(**p).fit(u, y, F_s).frf_[1:]
                                        - G) / np.abs(G))
                    for p, ok in zip(cv.cv_results_["params"],
                                     cv.cv_results_["identifiable"], strict=True)
                    if ok
                ]
            picked = np.nanmedian(np.abs(cv.frf_[1:] - G) / np.abs(G))
            ratios.append(picked / min(errors))
    assert np.mean(ratios) <= 1.25


# --- several inputs and outputs (issue 13 convention, issue 15 item 3) ---------


def _mimo_record(rng, n_samples=N, noise_std=0.005):
    """One record of two inputs (independent multisines) and two outputs:
    output 0 the resonant test system of input 0 plus 0.5 x input 1 through
    it, output 1 the reverse (channels first)."""
    u = np.array([multisine(n_samples, rng=rng) for _ in range(2)])
    y0 = simulate_resonant(u, F, 0.0, rng)  # (2, M), one row per input
    noise = noise_std * rng.standard_normal((2, n_samples // F))
    y = np.array([y0[0] + 0.5 * y0[1], 0.5 * y0[0] + y0[1]]) + noise
    return u, y


def test_mimo_criterion_pools_the_output_rows():
    """Each output row is scored as its own local problem: the per-window
    values of a two-output record are those of each output alone; with the
    same output twice the pooled criterion equals the one-output criterion
    (a mean over twice the same windows), and swapping the outputs swaps the
    rows and leaves the criterion unchanged."""
    rng = np.random.default_rng(5)
    u, y = _mimo_record(rng)
    U = np.fft.fft(u, axis=-1).reshape(1, 2 * N)
    Y = np.fft.fft(y, axis=-1)[None]  # (P, n_y, M)
    layout = LocalModelLayout(F=F, half_window=12, num_degree=1,
                              transient_degree=1, den_degree=2, n_inputs=2)
    for criterion in ("gaic", "aicc", "gcv", "press"):
        both = local_model_criterion(U, Y, layout, criterion=criterion)
        rows = [local_model_criterion(U, Y[:, o], layout, criterion=criterion)
                for o in range(2)]
        assert both.per_bin.shape == (2, M // 2 + 1)
        for o in range(2):
            np.testing.assert_array_equal(both.per_bin[o], rows[o].per_bin)
        assert both.n_invalid == rows[0].n_invalid + rows[1].n_invalid
        twice = local_model_criterion(U, Y[:, [0, 0]], layout,
                                      criterion=criterion)
        assert twice.value == pytest.approx(rows[0].value, rel=1e-12)
        swapped = local_model_criterion(U, Y[:, ::-1], layout,
                                        criterion=criterion)
        assert swapped.value == pytest.approx(both.value, rel=1e-12)
        assert min(r.value for r in rows) <= both.value + 1e-12 * abs(both.value)
        assert both.value <= max(r.value for r in rows) + 1e-12 * abs(both.value)


def test_mimo_cv_refits_the_chosen_setting_on_the_whole_matrix():
    rng = np.random.default_rng(6)
    u, y = _mimo_record(rng)
    cv = LRMBeyondNyquistCV(**SMALL_GRID).fit(u, y, F)
    ref = LRMBeyondNyquist(**cv.best_params_).fit(u, y, F)
    assert cv.frf_.shape == (2, 2, N // 2 + 1)
    np.testing.assert_array_equal(cv.frf_, ref.frf_)
    np.testing.assert_array_equal(cv.frf_std_, ref.frf_std_)
    # the chosen setting has the lowest criterion among the identifiable ones
    crit = cv.cv_results_["criterion"]
    assert cv.best_criterion_ == crit[np.isfinite(crit)].min()
    # a list of one record and the (1, n_u, N) array are the same data
    listed = LRMBeyondNyquistCV(**SMALL_GRID).fit([u], [y], F)
    np.testing.assert_array_equal(listed.cv_results_["criterion"], crit)
    assert listed.best_params_ == cv.best_params_


@pytest.mark.parametrize("criterion", ["gaic", "aicc", "pmse"])
def test_mimo_cv_rejects_a_polynomial_model_on_a_resonant_system(criterion):
    """As the SISO test: on two experiments of a 2x2 system of 1 %-damped
    resonances, R_e = 4 beats the polynomial and the criterion picks it,
    and its true error over all four entries is the lower one."""
    rng = np.random.default_rng(9)
    b, a = resonant_system()
    G = frf_of(b, a, N)
    G_true = np.array([[G, 0.5 * G], [0.5 * G, G]])
    records = [_mimo_record(rng, noise_std=0.002) for _ in range(2)]
    u = np.stack([r[0] for r in records])
    y = np.stack([r[1] for r in records])
    grid = {"half_windows": (12,), "num_degrees": (2,), "den_degrees": (0, 4)}
    cv = LRMBeyondNyquistCV(**grid, criterion=criterion).fit(u, y, F)
    assert cv.best_params_["den_degree"] == 4
    poly = LRMBeyondNyquist(half_window=12, num_degree=2, transient_degree=2,
                            den_degree=0).fit(u, y, F)
    err = np.median(np.abs(cv.frf_ - G_true))
    assert err < 0.5 * np.median(np.abs(poly.frf_ - G_true))


def test_mimo_cv_counts_inputs_in_identifiability():
    """Two inputs need twice the system columns: a grid identifiable for one
    input is refused for two with the count of inputs in the message."""
    rng = np.random.default_rng(7)
    u, y = _mimo_record(rng, n_samples=90)  # M = 30 slow samples
    grid = {"half_windows": (6,), "num_degrees": (1,), "den_degrees": (2,)}
    # 13 equations; one input: 2*3 + 2 + 2 = 10 params, two: 16
    LRMBeyondNyquistCV(**grid).fit(u[0], y[0], F)
    with pytest.raises(ValueError, match="n_u=2"):
        LRMBeyondNyquistCV(**grid).fit(u, y, F)


def test_cv_passes_std_method_on():
    rng = np.random.default_rng(8)
    u, y = _data(rng)
    cv = LRMBeyondNyquistCV(**SMALL_GRID, std_method="eiv").fit(u, y, F)
    assert cv.best_estimator_.std_method == "eiv"
    ref = LRMBeyondNyquist(**cv.best_params_, std_method="eiv").fit(u, y, F)
    np.testing.assert_array_equal(cv.frf_std_, ref.frf_std_)
    lemma2 = LRMBeyondNyquistCV(**SMALL_GRID, std_method="lemma2").fit(u, y, F)
    assert lemma2.best_params_ == cv.best_params_  # it does not enter the choice
    assert not np.allclose(lemma2.frf_std_, cv.frf_std_)
    with pytest.raises(ValueError, match="std_method"):
        LRMBeyondNyquistCV(std_method="bogus").fit(u, y, F)


def test_cv_with_the_robust_std_route():
    """``std_method="eiv_robust"`` reaches the refitted estimator (the same
    choice as with ``"eiv"``, the robust route's std), and the per-band blend
    weights by it."""
    rng = np.random.default_rng(8)
    u, y = _data(rng)
    eiv = LRMBeyondNyquistCV(**SMALL_GRID, std_method="eiv").fit(u, y, F)
    cv = LRMBeyondNyquistCV(**SMALL_GRID, std_method="eiv_robust").fit(u, y, F)
    assert cv.best_estimator_.std_method == "eiv_robust"
    assert cv.best_params_ == eiv.best_params_
    ref = LRMBeyondNyquist(**cv.best_params_, std_method="eiv_robust").fit(u, y, F)
    np.testing.assert_array_equal(cv.frf_std_, ref.frf_std_)
    assert not np.allclose(cv.frf_std_, eiv.frf_std_, equal_nan=True)
    blend = LRMBeyondNyquistCV(**SMALL_GRID, std_method="eiv_robust",
                               per_band=True).fit(u, y, F)
    blend_eiv = LRMBeyondNyquistCV(**SMALL_GRID, std_method="eiv",
                                   per_band=True).fit(u, y, F)
    # every blended candidate, not only the best one, carries the route
    assert len(blend.band_estimators_) > 1
    assert all(e.std_method == "eiv_robust" for e in blend.band_estimators_)
    valid = blend.valid_
    assert valid.mean() > 0.9
    assert np.all(np.isfinite(blend.frf_[valid]))
    assert np.all(np.isfinite(blend.frf_std_[valid]) & (blend.frf_std_[valid] > 0))
    # other weights, another blend
    assert not np.allclose(blend.frf_[valid], blend_eiv.frf_[valid])


def test_pmse_grid_on_the_compiled_kernel_selects_as_numpy(monkeypatch):
    """A default grid on a short record (N = 1200, 201 windows) solves every
    candidate with the compiled kernel (the grid's work 7.5e6 is above the
    threshold, no candidate's alone is), and selects what the numpy solver
    selects: the same candidate and FRF, the criterion equal up to the
    normal equations' round-off (1e-6 relative: cond ~1e9 times eps)."""
    pytest.importorskip("numba")
    from conftest import random_stage_record

    from lrmfrf import _compiled
    from lrmfrf.estimators import selection

    if not _compiled.AVAILABLE:  # pragma: no cover
        pytest.skip("numba not importable")
    used = []
    fit = selection.fit_local_models

    def spy(*args, **kwargs):
        used.append(kwargs.get("backend", "auto"))
        return fit(*args, **kwargs)

    u, y = random_stage_record()
    monkeypatch.setattr(selection, "fit_local_models", spy)
    compiled = LRMBeyondNyquistCV().fit(u, y, 3)
    assert used and set(used) == {"numba"}
    used.clear()
    monkeypatch.setenv("LRMFRF_DISABLE_NUMBA", "1")
    plain = LRMBeyondNyquistCV().fit(u, y, 3)
    assert used and set(used) == {"numpy"}
    assert compiled.best_params_ == plain.best_params_
    np.testing.assert_array_equal(compiled.frf_, plain.frf_)
    criterion = compiled.cv_results_["criterion"]
    want = plain.cv_results_["criterion"]
    np.testing.assert_array_equal(np.isfinite(criterion), np.isfinite(want))
    finite = np.isfinite(want)
    np.testing.assert_allclose(criterion[finite], want[finite], rtol=1e-6)


@pytest.mark.parametrize(
    "cls, kwargs",
    [
        (LRMBeyondNyquistCV, {**SMALL_GRID, "criterion": "pmse"}),
        (LRMBeyondNyquistCV, {**SMALL_GRID, "criterion": "gaic"}),
        (LRMBeyondNyquistCV, {**SMALL_GRID, "per_band": True}),
        (LRMBeyondNyquistCV, {**SMALL_GRID, "per_band": True, "bands": 2,
                              "criterion": "gcv"}),
        (LPMBeyondNyquistCV, {"half_windows": (8, 12), "num_degrees": (1, 2)}),
    ],
)
def test_cv_is_scale_invariant(cls, kwargs):
    """As the estimators (README: any finite scale of ``u_h`` and ``y_l``;
    records outside 2**-64..2**64 normalised by exact powers of two), the CV
    classes choose the same candidates, rank them alike and give the same FRF
    scaled back, bit for bit, at any scale of the input and the output (the
    criterion of records at 2**600 once overflowed to inf: "no candidate
    identifiable"), and leave the caller's arrays alone."""
    rng = np.random.default_rng(3)
    u, y = _data(rng, P=2)
    ref = cls(**kwargs).fit(u, y, F)
    for su, sy in [(-600, -600), (600, 600), (-100, -100), (-600, -300),
                   (100, 400), (0, 600)]:
        us, ys = u * 2.0**su, y * 2.0**sy
        copies = us.copy(), ys.copy()
        est = cls(**kwargs).fit(us, ys, F)
        np.testing.assert_array_equal(us, copies[0])
        np.testing.assert_array_equal(ys, copies[1])
        assert est.best_params_ == ref.best_params_
        np.testing.assert_array_equal(est.cv_results_["rank"],
                                      ref.cv_results_["rank"])
        np.testing.assert_array_equal(est.cv_results_["identifiable"],
                                      ref.cv_results_["identifiable"])
        np.testing.assert_array_equal(est.frf_ * 2.0 ** (su - sy), ref.frf_)
        np.testing.assert_array_equal(est.valid_, ref.valid_)
        if "band_params_" in vars(ref):
            assert est.band_params_ == ref.band_params_
