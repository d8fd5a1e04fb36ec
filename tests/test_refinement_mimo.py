"""Iterative refinement of MIMO fits: one local problem per output row."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
from scipy.signal import dlsim

from lrmfrf import LRMBeyondNyquist, _compiled
from lrmfrf.local_models import dft, fit_local_models
from lrmfrf.refinement import refine_local_models
from lrmfrf.signals import orthogonal_multisines
from lrmfrf.testing import in_class_mimo_data
from lrmfrf.windows import LocalModelLayout

DEG = {"num_degree": 2, "transient_degree": 2, "den_degree": 2}
BACKENDS = ["numpy"] + (["numba"] if _compiled.AVAILABLE else [])


def _stage_records(N=3600, snr=1e-3, seed=0):
    """Two channels of the MIMO stage's closed-loop G, P = 2 orthogonal
    multisines, periodic steady state, output noise ``snr`` of its std."""
    from lrmfrf.plants import mimo_wafer_stage

    stage = mimo_wafer_stage()
    system, F = stage.G[0:2, 0:2], stage.downsampling_factor
    A, B, C, D = (np.asarray(m) for m in (system.A, system.B, system.C, system.D))
    rng = np.random.default_rng(seed)
    u = orthogonal_multisines(2, N, rng=rng)
    clean = []
    for p in range(2):
        _, y, _ = dlsim((A, B, C, D, system.dt), np.tile(u[p], 3).T)
        clean.append(y[-N:].T[:, ::F])
    clean = np.stack(clean)
    y = clean + snr * clean.std(axis=(0, 2), keepdims=True) * rng.standard_normal(
        clean.shape
    )
    z = np.exp(2j * np.pi * np.arange(N // 2 + 1) / N)
    X = np.linalg.solve(z[:, None, None] * np.eye(A.shape[0]) - A,
                        np.broadcast_to(B, (z.size,) + B.shape))
    return u, y, F, np.moveaxis(C @ X + D, 0, -1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_in_class_mimo_data_stay_exact_under_refinement(backend):
    """Noise-free in-class 2x2 data (P = 2): every row's windows are exact, SK
    leaves them (the FRF at the in-class centres to 1e-8 relative)."""
    F, P, n_u, n_y, n = 2, 2, 2, 2, 8
    layout = LocalModelLayout(F=F, half_window=n, n_experiments=P, n_inputs=n_u,
                              **DEG)
    u, y, centres, G = in_class_mimo_data(layout, 240, n_y, 3)
    U = dft(u).reshape(P, n_u * F * 240)
    Y = dft(y)
    for o in range(n_y):
        closed = fit_local_models(U, Y[:, o], layout)
        with warnings.catch_warnings():  # windows off the centres are not
            warnings.simplefilter("ignore")  # in class: their cost drops
            result = refine_local_models(U, Y[:, o], layout, closed,
                                         sk_iterations=4, backend=backend)
        rows = np.searchsorted(result.local_fit.slow_bins, centres)
        np.testing.assert_allclose(
            result.local_fit.system[rows], G[:, o].reshape(len(centres), -1),
            rtol=1e-8, atol=1e-10,
        )
        assert result.converged[rows].all()


@pytest.mark.skipif(not _compiled.AVAILABLE, reason="needs numba")
def test_compiled_mimo_sk_equals_numpy_sk():
    """Per output row of the 2x2 stage (P = 2), the compiled SK gives the numpy
    SK's FRF, costs and histories to 1e-8 relative and its variances to 1e-5
    (the closed form's normal-equation accuracy, see test_fast_solver)."""
    u, y, F, _ = _stage_records(N=1800, seed=1)
    P, n_u, N = u.shape
    layout = LocalModelLayout(F=F, half_window=12, n_experiments=P, n_inputs=n_u,
                              num_degree=3, transient_degree=3, den_degree=4)
    U = dft(u).reshape(P, n_u * N)
    Y = dft(y)
    for o in range(y.shape[1]):
        closed = fit_local_models(U, Y[:, o], layout, return_cov=True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref, new = (
                refine_local_models(U, Y[:, o], layout, closed, sk_iterations=6,
                                    tol=0.0, backend=b)
                for b in ("numpy", "numba")
            )
        np.testing.assert_array_equal(ref.guarded, new.guarded)
        a, b = ref.local_fit, new.local_fit
        np.testing.assert_allclose(b.system, a.system, rtol=1e-8)
        np.testing.assert_allclose(b.rss, a.rss, rtol=1e-8)
        np.testing.assert_allclose(b.system_var, a.system_var, rtol=1e-5)
        np.testing.assert_allclose(b.system_cov, a.system_cov, rtol=1e-5,
                                   atol=1e-5 * np.nanmax(np.abs(a.system_cov)))
        np.testing.assert_allclose(new.cost_history, ref.cost_history, rtol=1e-8)
        assert ref.sk_iterations == new.sk_iterations == 6


def test_mimo_sk_against_the_truth_and_attributes():
    """SK on the 2x2 stage (noise 1e-3 of the output std): the mean cost drops,
    the FRF stays as close to the truth as the closed form's (median error
    above the slow Nyquist frequency per entry within 10 % of it; SK is a
    correction within the noise), and frf_std_, frf_cov_ are the refined ones."""
    u, y, F, G = _stage_records()
    N = u.shape[-1]
    above = np.arange(N // 2 + 1) > N // (2 * F)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        closed = LRMBeyondNyquist().fit(u, y, F)
        refined = LRMBeyondNyquist(sk_iterations=10).fit(u, y, F)
    err = {name: np.nanmedian(np.abs(est.frf_ - G)[..., above]
                              / np.abs(G[..., above]), axis=-1)
           for name, est in (("closed", closed), ("sk", refined))}
    assert np.all(err["sk"] <= 1.1 * err["closed"]), err
    assert refined.cost_history_[-1] < refined.cost_history_[0]
    assert refined.cost_history_.shape == (1 + refined.n_sk_iter_,)
    assert 1 <= refined.n_sk_iter_ <= 10
    assert len(refined.local_fit_) == 2
    # the refined variance, covariance diagonal and std agree with each other
    np.testing.assert_allclose(
        np.real(np.diagonal(refined.frf_cov_, axis1=1, axis2=2)).transpose(0, 2, 1),
        refined.frf_std_**2, rtol=1e-10,
    )
    change = np.abs(refined.frf_std_ / closed.frf_std_ - 1)
    assert np.nanmedian(change) > 1e-3  # linearised at the refined estimate


def test_mimo_histories_pool_the_output_rows():
    """cost_history_ of a 2x2 fit is the window-weighted mean of the two rows'
    histories (each padded with its last value), n_guarded_ their sum."""
    u, y, F, _ = _stage_records(N=1800, seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = LRMBeyondNyquist(sk_iterations=4, **DEG, half_window=12).fit(u, y, F)
        rows = [
            LRMBeyondNyquist(sk_iterations=4, **DEG, half_window=12).fit(
                u, y[:, o : o + 1], F
            )
            for o in range(2)
        ]
    n_ok = [np.count_nonzero(r.local_fit_[0].well_posed) for r in rows]
    length = max(r.cost_history_.size for r in rows)
    expected = sum(
        k * np.pad(r.cost_history_, (0, length - r.cost_history_.size), mode="edge")
        for k, r in zip(n_ok, rows, strict=True)
    ) / sum(n_ok)
    np.testing.assert_allclose(est.cost_history_, expected, rtol=1e-12)
    assert est.n_sk_iter_ == max(r.n_sk_iter_ for r in rows)
    assert est.n_guarded_ == sum(r.n_guarded_ for r in rows)


def test_a_mimo_fit_warns_once_per_kind_and_names_the_rows():
    """Refinement warnings of a 2-row fit: one of each kind, at the caller,
    with the rows named and the guard counts adding up to ``n_guarded_`` (each
    row warned on its own before, "1 of 201 windows" twice, naming no row)."""
    from sklearn.exceptions import ConvergenceWarning

    from lrmfrf.refinement import RefinementGuardWarning

    u, y, F, _ = _stage_records(N=1200)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est = LRMBeyondNyquist(lm_iterations=20).fit(list(u), list(y), F)
    conv = [w for w in caught if w.category is ConvergenceWarning]
    guard = [w for w in caught if w.category is RefinementGuardWarning]
    assert len(conv) == 1 and len(guard) == 1, [str(w.message) for w in caught]
    assert "(output rows 0, 1)" in str(conv[0].message)
    assert est.n_guarded_ > 0
    message = str(guard[0].message)
    assert f"in {est.n_guarded_} of " in message
    counts = [int(c) for c in re.findall(r"row \d: (\d+) of \d+", message)]
    assert len(counts) == 2 and sum(counts) == est.n_guarded_, message
    assert {w.filename for w in conv + guard} == {__file__}
