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

from lrmfrf import LRMBeyondNyquist
from lrmfrf._compiled import AVAILABLE
from lrmfrf.local_models import dft, fit_local_models
from lrmfrf.plants import mimo_wafer_stage, random_stage
from lrmfrf.signals import multisine, orthogonal_multisines
from lrmfrf.simulate import simulate
from lrmfrf.uncertainty import (
    band_covariance,
    calibrated_local_fit,
    eiv_terms,
    variance_terms,
)
from lrmfrf.windows import LocalModelLayout, local_regressor

pytestmark = pytest.mark.skipif(not AVAILABLE, reason="needs numba")

EPS = np.finfo(float).eps


@pytest.fixture(scope="module")
def record():
    """A random stage (seed 3000), F = 3, 40 dB, M = 400."""
    stage, _ = random_stage(3000, downsampling_factor=3)
    u = multisine(1200, rms=1.44, rng=1)
    sim = simulate(stage.G_z, u, 3, snr_db=40, rng=2)
    return u, sim.y_l


def _diag(cov):
    return np.real(np.diagonal(cov, axis1=1, axis2=2))


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
    scale = np.sqrt(_diag(dense.eiv_lead))
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
    var_err = np.max(np.abs(_diag(lead) / _diag(dense.eiv_lead) - 1), axis=1)
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
    return np.sqrt(_diag(cov))


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
