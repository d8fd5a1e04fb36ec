"""The compiled, streamed errors-in-variables route against the numpy one.

``lrmfrf.uncertainty.eiv_terms`` (numba kernel of
``lrmfrf._compiled_uncertainty``) must give the terms of
``lrmfrf.uncertainty.variance_terms`` (the dense regressor) up to round-off,
and the estimator's streamed ``frf_std_`` must be the numpy route on the whole
fit. Both invert a Gram matrix ``A^H A``, so their round-off is about
``eps cond(A_eq)^2`` per window (``A_eq``: the column-equilibrated regressor):
on well-conditioned windows that is below 1e-10 relative, on the default
layout's worst windows (``cond(A_eq) ~ 2e4``) about 1e-8 for either route
(checked against a QR reference in the development notes of the report).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CACHE_HINT, band_variances, random_stage_record

from lrmfrf import LRMBeyondNyquist
from lrmfrf._compiled import AVAILABLE
from lrmfrf._compiled_uncertainty import eiv_windows
from lrmfrf.local_models import dft, fit_local_models
from lrmfrf.plants import mimo_wafer_stage
from lrmfrf.signals import multisine, orthogonal_multisines
from lrmfrf.simulate import simulate
from lrmfrf.solvers import (
    CHOLESKY_FALLBACK_TOL,
    _kernel_tables,
    solve_local_normal_equations,
)
from lrmfrf.uncertainty import (
    _eiv_terms_compiled,
    _weighted_tables,
    band_covariance,
    calibrated_local_fit,
    eiv_terms,
    eiv_terms_rows,
    variance_terms,
)
from lrmfrf.windows import LocalModelLayout, local_regressor, window_offsets

pytestmark = pytest.mark.skipif(not AVAILABLE, reason="needs numba")

EPS = np.finfo(float).eps


@pytest.fixture(scope="module")
def record():
    """A random stage (seed 3000), F = 3, 40 dB, M = 400."""
    return random_stage_record()


def _both(u, y, layout):
    U, Y = dft(u)[None], dft(y)[None]
    fit = fit_local_models(U, Y, layout, return_cov=True)
    dense = variance_terms(U, Y, layout, fit.theta, fit.slow_bins, with_hc=False)
    lead, trace = eiv_terms(U, Y, layout, fit.theta, fit.slow_bins,
                            backend="numba")
    return U, Y, fit, dense, lead, trace


def test_compiled_terms_equal_numpy_on_a_well_conditioned_layout(record):
    """den_degree 2: cond(A_eq)^2 eps is far below 1e-10; every window and
    every entry of the band block agree to 1e-10 relative."""
    u, y = record
    layout = LocalModelLayout(F=3, half_window=12, num_degree=2,
                              transient_degree=2, den_degree=2)
    _, _, _, dense, lead, trace = _both(u, y, layout)
    np.testing.assert_allclose(trace, dense.eiv_trace, rtol=1e-10)
    scale = np.sqrt(band_variances(dense.eiv_lead))
    err = np.abs(lead - dense.eiv_lead) / (scale[:, :, None] * scale[:, None, :])
    assert np.max(err) <= 1e-10


def test_compiled_terms_equal_numpy_within_the_conditioning(record):
    """The default layout (den_degree 7): per window within 10 eps
    cond(A_eq)^2 (the accuracy of either Gram inverse), median 1e-10."""
    u, y = record
    layout = LRMBeyondNyquist().fit(u, y, 3).layout_
    U, Y, fit, dense, lead, trace = _both(u, y, layout)
    A, _ = local_regressor(U, Y, fit.slow_bins, layout)
    cond = np.linalg.cond(A / np.linalg.norm(A, axis=1, keepdims=True))
    bound = 10 * EPS * cond**2
    var_err = np.max(
        np.abs(band_variances(lead) / band_variances(dense.eiv_lead) - 1), axis=1
    )
    trace_err = np.abs(trace / dense.eiv_trace - 1)
    assert np.all(var_err <= bound) and np.all(trace_err <= bound)
    assert np.median(var_err) <= 1e-10 and np.median(trace_err) <= 1e-10


def test_compiled_numpy_backends_agree_on_the_fallback_path(record):
    """backend="numpy" is the dense route itself (the compiled kernel's
    fallback for windows whose pivot check fails)."""
    u, y = record
    layout = LRMBeyondNyquist().fit(u, y, 3).layout_
    U, Y = dft(u)[None], dft(y)[None]
    fit = fit_local_models(U, Y, layout, return_cov=True)
    dense = variance_terms(U, Y, layout, fit.theta, fit.slow_bins, with_hc=False)
    lead, trace = eiv_terms(U, Y, layout, fit.theta, fit.slow_bins, backend="numpy")
    np.testing.assert_array_equal(trace, dense.eiv_trace)
    np.testing.assert_array_equal(lead, dense.eiv_lead)


def _numpy_route_std(U, Y, layout):
    """frf_std_ at the window centres by the numpy route on the whole fit:
    (B, n_bands)."""
    fit = fit_local_models(U, Y, layout, return_cov=True)
    terms = variance_terms(U, Y, layout, fit.theta, fit.slow_bins, with_hc=False)
    cov = band_covariance(terms, layout, "eiv")
    cov[~fit.well_posed] = np.nan
    return np.sqrt(band_variances(cov))


def test_streamed_estimator_std_is_the_numpy_route(record):
    """The estimator streams the eiv route chunk by chunk (compiled); its
    frf_std_ at the band bins k + fM equals the numpy route on the whole
    fit (median 1e-10, all within 1e-7: the conditioning above)."""
    u, y = record
    est = LRMBeyondNyquist(std_method="eiv").fit(u, y, 3)
    U, Y = dft(u)[None], dft(y)[None]
    ref = _numpy_route_std(U, Y, est.layout_)  # (201, 3): bins k + 400 f
    N, M = 1200, 400
    k = np.arange(M // 2 + 1)
    got = np.stack([est.frf_std_[k + f * M] for f in range(2)], axis=1)
    err = np.abs(got / ref[:, :2] - 1)
    assert np.median(err) <= 1e-10 and np.max(err) <= 1e-7
    assert N // 2 + 1 == est.frf_std_.size


def test_streamed_std_equals_calibrated_local_fit(record):
    """local_fit_ (computed on first access, streamed) and the estimator use
    the same route: its system_var is frf_std_**2 at the band bins, and equal
    to calibrated_local_fit on the full spectra."""
    u, y = record
    est = LRMBeyondNyquist(std_method="eiv").fit(u, y, 3)
    U, Y = dft(u)[None], dft(y)[None]
    whole = calibrated_local_fit(
        U, Y, est.layout_, fit_local_models(U, Y, est.layout_, return_cov=True),
        "eiv",
    )
    np.testing.assert_allclose(est.local_fit_.system_var, whole.system_var,
                               rtol=1e-12)
    k = np.arange(201)
    np.testing.assert_allclose(est.frf_std_[k], np.sqrt(whole.system_var[:, 0]),
                               rtol=1e-12)


def test_streamed_eiv_is_scale_invariant(record):
    """Records far outside the ordinary range (scaled by powers of two) are
    normalised exactly: frf_std_ scales as the output over the input."""
    u, y = record
    a = LRMBeyondNyquist(std_method="eiv").fit(u, y, 3)
    b = LRMBeyondNyquist(std_method="eiv").fit(u * 2.0**-80, y * 2.0**500, 3)
    np.testing.assert_allclose(b.frf_std_, a.frf_std_ * 2.0**580,
                               rtol=1e-13)


def test_mimo_rows_stream_the_numpy_route():
    """2x2 with two experiments: each output row's frf_std_ is the numpy
    route on that row's whole fit."""
    system = mimo_wafer_stage().G[0:2, 0:2]
    rng = np.random.default_rng(0)
    u = orthogonal_multisines(2, 1200, rms=1.44, rng=rng)
    y = np.stack([simulate(system, u[p], 3, snr_db=45, rng=rng).y_l
                  for p in range(2)])
    est = LRMBeyondNyquist(std_method="eiv").fit(u, y, 3)
    U = np.stack([np.concatenate([dft(u[p, i]) for i in range(2)])
                  for p in range(2)])
    k = np.arange(201)
    for o in range(2):
        Y = np.stack([dft(y[p, o]) for p in range(2)])
        ref = _numpy_route_std(U, Y, est.layout_)  # (B, 2 F): band b = i F + f
        for i in range(2):
            err = np.abs(est.frf_std_[o, i, k] / ref[:, i * 3] - 1)
            assert np.median(err) <= 1e-10 and np.max(err) <= 1e-7, (o, i)


# --- the row-shared pass (eiv_terms_rows) -----------------------------------------


def _mimo_spectra(n_u, n_y, P, half_window, seed=0):
    """DFTs of P experiments through n_y x n_u channels of the MIMO stage
    (45 dB): U (P, n_u N), Y (P, n_y M), M = 400, and the layout."""
    system = mimo_wafer_stage().G[0:n_y, 0:n_u]
    rng = np.random.default_rng(seed)
    u = np.stack([np.stack([multisine(1200, rms=1.44, rng=rng) for _ in range(n_u)])
                  for _ in range(P)])
    y = np.stack([simulate(system, u[p], 3, snr_db=45, rng=rng).y_l
                  for p in range(P)])
    U = np.stack([np.concatenate([dft(u[p, i]) for i in range(n_u)])
                  for p in range(P)])
    Y = np.stack([np.stack([dft(y[p, o]) for o in range(n_y)]) for p in range(P)])
    layout = LocalModelLayout(F=3, n_experiments=P, n_inputs=n_u,
                              half_window=half_window, num_degree=2,
                              transient_degree=2, den_degree=2)
    return U, Y, layout


def _lead_error(lead, reference):
    """Largest error of a band block relative to ``sqrt(ref_aa ref_bb)``."""
    scale = np.sqrt(band_variances(reference))
    err = np.abs(lead - reference) / (scale[:, :, None] * scale[:, None, :])
    return np.max(err)


def _row_fits(U, Y, layout):
    return [fit_local_models(U, Y[:, o], layout) for o in range(Y.shape[1])]


@pytest.mark.parametrize(
    ("n_u", "n_y", "P", "half_window"),
    [(2, 2, 2, 12), (2, 2, 1, 18), (3, 1, 1, 20), (1, 3, 1, 12), (1, 3, 2, 12)],
)
def test_row_shared_terms_equal_per_row_and_numpy(n_u, n_y, P, half_window):
    """All output rows in one pass (the input and transient block shared):
    each row's terms are those of eiv_terms on that row alone (the same
    arithmetic: equal exactly) and of the dense numpy route to 1e-10
    relative (den_degree 2, well conditioned; measured <= 6.5e-11 for the
    band block, 1.3e-11 for the trace)."""
    U, Y, layout = _mimo_spectra(n_u, n_y, P, half_window)
    fits = _row_fits(U, Y, layout)
    bins = fits[0].slow_bins
    theta = np.stack([fit.theta for fit in fits])
    lead, trace = eiv_terms_rows(U, Y, layout, theta, bins, backend="numba")
    assert lead.shape == (n_y, bins.size, layout.n_bands, layout.n_bands)
    assert trace.shape == (n_y, bins.size)
    for o in range(n_y):
        one_lead, one_trace = eiv_terms(U, Y[:, o], layout, theta[o], bins,
                                        backend="numba")
        np.testing.assert_array_equal(lead[o], one_lead)
        np.testing.assert_array_equal(trace[o], one_trace)
        dense = variance_terms(U, Y[:, o], layout, theta[o], bins, with_hc=False)
        np.testing.assert_allclose(trace[o], dense.eiv_trace, rtol=1e-10)
        assert _lead_error(lead[o], dense.eiv_lead) <= 1e-10, o


def test_row_shared_terms_take_the_dense_fallback_per_row():
    """A row whose output is zero over a stretch of slow bins has exactly
    zero denominator columns there: the kernel's pivot check fails for that
    row only (the other rows keep the compiled terms) and its windows are
    redone by the dense route, which gives them unit pivots."""
    U, Y, layout = _mimo_spectra(2, 2, 2, 12)
    Y = Y.copy()
    Y[:, 1, 60:100] = 0.0
    Y[:, 1, -99:-59] = 0.0  # (the conjugate-symmetric bins)
    fits = _row_fits(U, Y, layout)
    bins = fits[0].slow_bins
    theta = np.stack([fit.theta for fit in fits])
    weights, col_base, tables, _ = _kernel_tables(layout)
    nb = layout.n_bands
    _, x = window_offsets(layout.half_window)
    *_, ok = eiv_windows(
        U.reshape(2, 2, -1), Y, bins, theta[:, :, layout.den_columns],
        x[:, None] ** np.arange(1, 3), weights, col_base, nb, nb + 2,
        tables=tables, weighted_tables=_weighted_tables(layout),
        fallback_tol=CHOLESKY_FALLBACK_TOL,
    )
    fallback = ~ok[1] & np.all(np.isfinite(theta[1]), axis=1)
    assert ok[0].all() and 10 <= fallback.sum() <= 40
    lead, trace = eiv_terms_rows(U, Y, layout, theta, bins, backend="numba")
    for o in range(2):
        dense = variance_terms(U, Y[:, o], layout, theta[o], bins, with_hc=False)
        rows = fallback if o == 1 else slice(None)
        np.testing.assert_allclose(trace[o, rows], dense.eiv_trace[rows],
                                   rtol=1e-10)
        assert _lead_error(lead[o, rows], dense.eiv_lead[rows]) <= 1e-10, o
    # the dense route on exactly those windows: bit for bit
    np.testing.assert_array_equal(trace[1, fallback],
                                  variance_terms(U, Y[:, 1], layout,
                                                 theta[1, fallback],
                                                 bins[fallback],
                                                 with_hc=False).eiv_trace)


def test_row_shared_terms_reject_theta_of_another_shape():
    U, Y, layout = _mimo_spectra(2, 2, 2, 12)
    fits = _row_fits(U, Y, layout)
    with pytest.raises(ValueError, match=r"`theta` must have shape \(n_rows, B"):
        eiv_terms_rows(U, Y, layout, fits[0].theta, fits[0].slow_bins)


# --- the terms fused into the closed-form solve (solve_eiv_windows) --------------


def _fused(U, Y, layout):
    """The closed form with and without the fused terms, and the terms of the
    separate pass (eiv_terms_rows) on the fused solve's parameters."""
    bins = np.arange(Y.shape[-1] // 2 + 1)
    # (the estimators' rank test: the input and transient columns)
    kwargs = {"backend": "numba",
              "rank_columns": layout.n_system + layout.n_transient}
    fused = solve_local_normal_equations(U, Y, bins, layout, eiv=True, **kwargs)
    plain = solve_local_normal_equations(U, Y, bins, layout, **kwargs)
    theta = np.stack([sol.theta for sol in fused])
    return bins, fused, plain, theta


@pytest.mark.parametrize(
    ("n_u", "n_y", "P", "half_window"),
    [(2, 2, 2, 12), (1, 1, 1, 12), (3, 1, 1, 20), (1, 3, 2, 12)],
)
def test_fused_terms_equal_the_separate_pass(n_u, n_y, P, half_window):
    """The terms computed with the solve (its window data, factor and refined
    denominator) are the separate kernel pass's on the same parameters, bit
    for bit (the same step functions in the same order), and the solve
    itself is unchanged by the fusion."""
    U, Y, layout = _mimo_spectra(n_u, n_y, P, half_window)
    bins, fused, plain, theta = _fused(U, Y, layout)
    for one, two in zip(fused, plain, strict=True):
        np.testing.assert_array_equal(one.theta, two.theta)
        np.testing.assert_array_equal(one.rss, two.rss)
        np.testing.assert_array_equal(one.gram_inv_diag, two.gram_inv_diag)
        assert two.eiv_raw is None
    weights, col_base, tables, _ = _kernel_tables(layout)
    nb = layout.n_bands
    _, x = window_offsets(layout.half_window)
    separate = eiv_windows(
        U.reshape(P, n_u, -1), Y, bins, theta[:, :, layout.den_columns],
        x[:, None] ** np.arange(1, layout.den_degree + 1), weights, col_base,
        nb, nb + P, tables=tables, weighted_tables=_weighted_tables(layout),
        fallback_tol=CHOLESKY_FALLBACK_TOL,
    )
    for o, sol in enumerate(fused):
        *terms, valid = sol.eiv_raw
        assert valid.all()  # (well-conditioned windows: none re-solved by QR)
        for got, want in zip(terms, separate[:5], strict=True):
            np.testing.assert_array_equal(got, want[o], err_msg=CACHE_HINT)
    lead, trace = _eiv_terms_compiled(U, Y, layout, theta, bins,
                                      [sol.eiv_raw for sol in fused])
    want_lead, want_trace = eiv_terms_rows(U, Y, layout, theta, bins,
                                           backend="numba")
    np.testing.assert_array_equal(lead, want_lead, err_msg=CACHE_HINT)
    np.testing.assert_array_equal(trace, want_trace, err_msg=CACHE_HINT)


def test_fused_terms_recomputed_where_qr_resolves():
    """Windows the normal equations leave to QR (here a row whose output is
    zero over a stretch: its pivot check fails) get a new solution, so their
    fused terms are not valid; they are computed again (separate kernel pass,
    then the dense route where its check fails too) and the result is
    eiv_terms_rows on the final parameters exactly."""
    U, Y, layout = _mimo_spectra(2, 2, 2, 12)
    Y = Y.copy()
    Y[:, 1, 60:100] = 0.0
    Y[:, 1, -99:-59] = 0.0
    bins, fused, _, theta = _fused(U, Y, layout)
    valid = np.stack([sol.eiv_raw[-1] for sol in fused])
    redone = ~valid[1] & np.all(np.isfinite(theta[1]), axis=1)
    assert valid[0].all() and 10 <= redone.sum() <= 40
    lead, trace = _eiv_terms_compiled(U, Y, layout, theta, bins,
                                      [sol.eiv_raw for sol in fused])
    want_lead, want_trace = eiv_terms_rows(U, Y, layout, theta, bins,
                                           backend="numba")
    np.testing.assert_array_equal(lead, want_lead, err_msg=CACHE_HINT)
    np.testing.assert_array_equal(trace, want_trace, err_msg=CACHE_HINT)
    assert np.all(np.isfinite(trace[1, redone]))


def test_qr_solve_dense_terms_stand_in_for_the_dense_route(monkeypatch):
    """The rows route (the estimators'): the QR solve hands the dense terms
    of the windows it re-solves, from its own factors, with the kernel's
    (``_solve_normal_rows``' ``eiv_raw`` then ``(lead, trace, done)``); where
    the kernel pass fails on them they replace the dense route's building and
    factoring the windows again, with the same terms: eiv_terms_rows on the
    final parameters to round-off (bit for bit seen; 1e-12 allowed)."""
    from lrmfrf.solvers import _solve_normal_rows

    U, Y, layout = _mimo_spectra(2, 2, 2, 12)
    Y = Y.copy()
    Y[:, 1, 60:100] = 0.0
    Y[:, 1, -99:-59] = 0.0
    bins = np.arange(Y.shape[-1] // 2 + 1)
    _, theta, raw_rows = _solve_normal_rows(
        U, Y, bins, layout, backend="numba", eiv=True,
        rank_columns=layout.n_system + layout.n_transient)
    *kernel, valid, (dense_lead, dense_trace, done) = raw_rows
    good = np.all(np.isfinite(theta), axis=-1)
    np.testing.assert_array_equal(done, good & ~valid)
    assert 10 <= done[1].sum() <= 40 and not done[0].any()
    want_lead, want_trace = eiv_terms_rows(U, Y, layout, theta, bins,
                                           backend="numba")
    np.testing.assert_array_equal(np.isnan(dense_lead[done]), False)
    import lrmfrf.uncertainty as uncertainty

    def no_dense_route(*args):
        raise AssertionError("the dense route built a window again")

    monkeypatch.setattr(uncertainty, "_terms_of_chunk", no_dense_route)
    lead, trace = _eiv_terms_compiled(U, Y, layout, theta, bins,
                                      raw_rows=raw_rows)
    scale = np.abs(want_lead).max(axis=(2, 3), keepdims=True)
    np.testing.assert_allclose(lead / scale, want_lead / scale, rtol=0, atol=1e-12)
    np.testing.assert_allclose(trace, want_trace, rtol=1e-12)
    assert np.all(np.isfinite(trace[1, done[1]]))
