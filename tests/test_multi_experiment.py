"""Several experiments in one fit: shared system, own transients, pooled noise.

Also held-out scoring and scikit-learn's GridSearchCV over experiments.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import frf_of, resonant_system, simulate_resonant
from scipy.signal import lfilter
from sklearn.model_selection import GridSearchCV, KFold

from lrmfrf import LPMBeyondNyquist, LRMBeyondNyquist, multisine
from lrmfrf.testing import in_class_data
from lrmfrf.windows import LocalModelLayout

N, F = 600, 3
M = N // F
SMALL = {"half_window": 12, "num_degree": 2, "transient_degree": 2, "den_degree": 4}


def _experiments(P, rng, noise_std=0.0, n_samples=N):
    """P SISO experiments as 3-D arrays (P, 1, N) and (P, 1, M)."""
    u = np.array([multisine(n_samples, rng=rng) for _ in range(P)])
    return u[:, None], simulate_resonant(u, F, noise_std, rng)[:, None]


def _steady_experiments(P, rng, noise_std):
    """Periodic steady state: 6 periods from rest, keep the last (the slowest
    mode decays by exp(-5 * 600 * 0.5e-3 * 0.01 * 2 pi 120) = 1e-5)."""
    b, a = resonant_system()
    u = np.array([multisine(N, rng=rng) for _ in range(P)])
    y_h = lfilter(b, a, np.tile(u, 6), axis=1)[:, -N:]
    y = y_h[:, ::F]
    y = y + noise_std * rng.standard_normal(y.shape)
    return u[:, None], y[:, None]


def _fitted_arrays(est):
    return est.frf_, est.frf_std_, est.noise_variance_, est.transient_


# --- the same data in different containers ------------------------------------


def test_3d_array_list_and_tuple_give_identical_fits():
    rng = np.random.default_rng(0)
    u, y = _experiments(3, rng, noise_std=0.01)
    reference = LRMBeyondNyquist(**SMALL).fit(u, y, F)
    for u_in, y_in in [(list(u), list(y)), (tuple(u), tuple(y)),
                       ([list(r[0]) for r in u], [list(r[0]) for r in y]),
                       (list(u[:, 0]), list(y[:, 0]))]:
        other = LRMBeyondNyquist(**SMALL).fit(u_in, y_in, F)
        for a, b in zip(_fitted_arrays(reference), _fitted_arrays(other), strict=True):
            np.testing.assert_array_equal(a, b)
    assert reference.n_experiments_ == 3
    assert reference.transient_.shape == (3, M // 2 + 1)


def test_one_experiment_in_a_list_equals_the_1d_fit():
    rng = np.random.default_rng(1)
    u, y = _experiments(1, rng, noise_std=0.01)
    single = LRMBeyondNyquist(**SMALL).fit(u[0], y[0], F)
    listed = LRMBeyondNyquist(**SMALL).fit([u[0]], [y[0]], F)
    for a, b in zip(_fitted_arrays(single), _fitted_arrays(listed), strict=True):
        np.testing.assert_array_equal(a, b)
    assert single.transient_.shape == (M // 2 + 1,)


def test_experiment_order_only_permutes_the_transients():
    rng = np.random.default_rng(2)
    u, y = _experiments(4, rng, noise_std=0.01)
    perm = [2, 0, 3, 1]
    a = LRMBeyondNyquist(**SMALL).fit(u, y, F)
    b = LRMBeyondNyquist(**SMALL).fit(u[perm], y[perm], F)
    # Same least-squares problem with rows and transient columns permuted:
    # equal up to round-off of the QR (relative 1e-9 is ~1e6 eps).
    np.testing.assert_allclose(b.frf_, a.frf_, rtol=1e-9, atol=0)
    np.testing.assert_allclose(b.noise_variance_, a.noise_variance_, rtol=1e-9)
    np.testing.assert_allclose(b.transient_, a.transient_[perm], rtol=1e-8,
                               atol=1e-9 * np.abs(a.transient_).max())


def test_dof_counts_equations_of_all_experiments():
    rng = np.random.default_rng(3)
    for P in (1, 2, 5):
        u, y = _experiments(P, rng, noise_std=0.01)
        est = LRMBeyondNyquist(**SMALL).fit(u, y, F)
        n, rg, rt, re = SMALL.values()
        assert est.n_params_ == (rg + 1) * F + P * (rt + 1) + re
        assert est.dof_ == P * (2 * n + 1) - est.n_params_


# --- known answers ---------------------------------------------------------------


def test_in_class_experiments_with_own_transients_recovered_through_fit():
    """Shared system, a different random transient per experiment (in class)."""
    rng = np.random.default_rng(4)
    layout = LocalModelLayout(F=F, half_window=8, num_degree=2, transient_degree=2,
                              den_degree=2, n_experiments=3)
    u, y, centres, G = in_class_data(layout, M, rng)
    est = LRMBeyondNyquist(half_window=8, num_degree=2, transient_degree=2,
                           den_degree=2).fit(list(u), list(y), F)
    fast = (centres[:, None] + M * np.arange(F)).ravel()
    estimate = np.where(fast <= N // 2, est.frf_[np.minimum(fast, N // 2)], np.nan)
    expected = G.ravel()
    ok = fast <= N // 2
    # In-class data: exact up to round-off of a ~1e5-conditioned QR.
    np.testing.assert_allclose(estimate[ok], expected[ok], rtol=1e-8)


def test_pure_noise_noise_variance_pools_all_experiments():
    """With G = 0 and R_e = 0 the residual is the noise projected on the
    orthogonal complement of fixed regressors: E[rss] = dof * M sigma^2 exactly
    (unnormalised DFT of white noise has variance M sigma^2 per bin)."""
    rng = np.random.default_rng(5)
    sigma = 0.3
    for P in (1, 4):
        u = rng.standard_normal((P, N))
        y = sigma * rng.standard_normal((P, M))
        est = LPMBeyondNyquist(half_window=12, num_degree=2).fit(list(u), list(y), F)
        ratio = np.mean(est.noise_variance_) / (M * sigma**2)
        # The window estimates overlap; ~M/(2n+1) = 8 independent windows of
        # 2*dof real dof each give a relative SE below 1/sqrt(8 * 2 * dof) <= 6 %
        # for P = 1 (dof = 16); 4 SE = 25 %.
        assert abs(ratio - 1.0) < 0.25, (P, ratio)
        assert est.dof_ == P * 25 - (3 * F + 3 * P)


def test_error_falls_as_inverse_sqrt_of_experiments():
    """Error with P = 2 vs 8 experiments: ratio near sqrt(4) = 2.

    Least squares with regressors fixed: the shared system parameters see P
    times the information, so their std scales as 1/sqrt(P); the transients
    are per experiment and the denominator shared, so the exact Lemma 2 ratio
    differs slightly from 2 (it is computed below). Tolerance: the Monte-Carlo
    RMS over 6 runs x 301 bins estimates each std to a few %; we allow +-25 %.
    """
    rng = np.random.default_rng(6)
    b, a = resonant_system()
    G = frf_of(b, a, N)
    rms_error, rms_predicted = {}, {}
    for P in (2, 8):
        sq_err, var = [], []
        for _ in range(6):
            u = rng.standard_normal((P, N))
            y = simulate_resonant(u, F, 0.02, rng)
            est = LRMBeyondNyquist(**SMALL).fit(list(u), list(y), F)
            sq_err.append(np.abs(est.frf_ - G) ** 2)
            var.append(est.frf_std_**2)
        rms_error[P] = np.median(np.sqrt(np.mean(sq_err, axis=0)))
        rms_predicted[P] = np.median(np.sqrt(np.mean(var, axis=0)))
    ratio = rms_error[2] / rms_error[8]
    predicted = rms_predicted[2] / rms_predicted[8]
    assert 1.5 < ratio < 2.5, ratio
    assert abs(ratio / predicted - 1) < 0.25, (ratio, predicted)


@pytest.mark.slow
def test_error_falls_as_inverse_sqrt_of_experiments_1_to_8():
    rng = np.random.default_rng(7)
    b, a = resonant_system()
    G = frf_of(b, a, N)
    rms = {}
    for P in (1, 2, 4, 8):
        sq = []
        for _ in range(40):
            u = rng.standard_normal((P, N))
            y = simulate_resonant(u, F, 0.02, rng)
            est = LRMBeyondNyquist(**SMALL).fit(list(u), list(y), F)
            sq.append(np.abs(est.frf_ - G) ** 2)
        rms[P] = np.median(np.sqrt(np.mean(sq, axis=0)))
    # From P to 8P the error falls by sqrt(8) = 2.83 for fixed regressors; at
    # P = 1 (dof 9 of 25 equations) the noise-fitting of the rational model
    # makes it fall faster, so the bound is one-sided there.
    assert 2.83 * 0.8 < rms[1] / rms[8] < 2.83 * 1.6, rms
    assert 2.0 * 0.8 < rms[2] / rms[8] < 2.0 * 1.25, rms


# --- held-out scoring ------------------------------------------------------------


def test_score_is_r2_of_predicted_slow_output_on_held_out_experiments():
    rng = np.random.default_rng(8)
    u, y = _steady_experiments(5, rng, noise_std=0.002)
    est = LRMBeyondNyquist(**SMALL).fit(u[:3], y[:3], F)
    prediction = est.predict(u[3:])
    expected = 1 - np.sum((y[3:] - prediction) ** 2) / np.sum(
        (y[3:] - y[3:].mean()) ** 2)
    assert est.score(u[3:], y[3:]) == pytest.approx(expected, rel=1e-12)
    assert est.score(list(u[3:]), list(y[3:])) == pytest.approx(expected, rel=1e-12)
    # Steady-state data: the prediction misses only the noise (0.2 % of the
    # output RMS... up to the FRF error): R^2 above 0.99 for a good model.
    assert expected > 0.99


def test_score_ranks_a_badly_wrong_model_lower():
    rng = np.random.default_rng(9)
    u, y = _steady_experiments(4, rng, noise_std=0.002)
    good = LRMBeyondNyquist(**SMALL).fit(u[:2], y[:2], F)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bad = LPMBeyondNyquist(half_window=12, num_degree=0).fit(u[:2], y[:2], F)
    assert good.score(u[2:], y[2:]) > bad.score(u[2:], y[2:]) + 0.1


# --- GridSearchCV over experiments ---------------------------------------------------


def test_grid_search_over_experiments_picks_the_rational_model():
    """A polynomial local model (R_e = 0, degree 0) cannot follow 1 %-damped
    resonances over a 25-bin window; the grid search must reject it."""
    rng = np.random.default_rng(10)
    u, y = _experiments(6, rng, noise_std=0.002)
    grid = {"den_degree": [0, 4], "num_degree": [0, 2], "transient_degree": [2]}
    search = GridSearchCV(LRMBeyondNyquist(half_window=12), grid, cv=KFold(3))
    search.fit(list(u), list(y), F=F)
    assert search.best_params_ == {"den_degree": 4, "num_degree": 2,
                                   "transient_degree": 2}
    scores = search.cv_results_["mean_test_score"]
    worst = search.cv_results_["params"].index(
        {"den_degree": 0, "num_degree": 0, "transient_degree": 2})
    assert scores.max() > scores[worst] + 0.1
    # Refitted on all six experiments.
    assert search.best_estimator_.n_experiments_ == 6
    # Sensible: the held-out R^2 picks the candidate whose FRF is truly best
    # (fitted on all experiments, median relative error against the exact G).
    G = frf_of(*resonant_system(), N)
    true_error = []
    for params in search.cv_results_["params"]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est = LRMBeyondNyquist(half_window=12, **params).fit(u, y, F)
        true_error.append(np.median(np.abs(est.frf_ - G) / np.abs(G)))
    assert search.best_index_ == int(np.argmin(true_error)), true_error
    # A 3-D array of experiments works the same way.
    search_2d = GridSearchCV(LRMBeyondNyquist(half_window=12), grid, cv=KFold(3))
    search_2d.fit(u, y, F=F)
    np.testing.assert_allclose(search_2d.cv_results_["mean_test_score"], scores,
                               rtol=1e-10)


# --- bad input ---------------------------------------------------------------------


def test_records_of_unequal_length_are_rejected():
    rng = np.random.default_rng(11)
    u, y = _experiments(2, rng)
    with pytest.raises(ValueError, match=r"equal length. Got lengths \[597, 600\]"):
        LRMBeyondNyquist(**SMALL).fit([u[0], u[1][:, :-3]], list(y), F)
    with pytest.raises(ValueError, match=r"`y_l` must have equal length"):
        LRMBeyondNyquist(**SMALL).fit(list(u), [y[0], y[1][:, :-1]], F)


def test_2d_stack_of_siso_experiments_is_one_record_and_the_error_says_so():
    """Breaking change of issue 13: a 2-D array is ONE record, channels first;
    the old (P, N) stack of SISO experiments is read as P input channels and
    the error says several experiments go in a list or a 3-D array."""
    rng = np.random.default_rng(12)
    u, y = _experiments(3, rng)
    with pytest.raises(ValueError, match="list of records or a 3-D array"):
        LRMBeyondNyquist(**SMALL).fit(u[:, 0], y[:, 0], F)


def test_number_of_experiments_must_match():
    rng = np.random.default_rng(12)
    u, y = _experiments(3, rng)
    with pytest.raises(ValueError, match="u_h holds 3 experiment.*y_l holds 2"):
        LRMBeyondNyquist(**SMALL).fit(u, y[:2], F)
    with pytest.raises(ValueError, match="u_h holds 2 experiment.*y_l holds 3"):
        LRMBeyondNyquist(**SMALL).fit(list(u[:2]), list(y), F)
