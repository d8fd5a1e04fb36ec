"""User-facing MIMO surfaces: SpectralAnalysis against an independent H1,
predict at invalid bins, dependent inputs, error messages."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.signal import csd, lfilter

from lrmfrf import IdentifiabilityWarning, SpectralAnalysis
from lrmfrf.signals import multisine


def _three_by_two(u):
    """(2, N) -> (3, N): first-order entries, one of them zero."""
    return np.stack([
        lfilter([0.2, 0.1], [1, -0.5], u[0]) + lfilter([0.5], [1, -0.2], u[1]),
        lfilter([0.3], [1, -0.5], u[1]) - 0.4 * u[0],
        lfilter([0.1, 0.1], [1], u[0]),
    ])


def test_mimo_spectral_analysis_equals_h1_from_scipy_csd():
    """3 outputs, 2 inputs, P = 2 experiments pooled: frf_ and coherence_
    equal H1 = S_yu S_uu^-1 built from scipy.signal.csd of the zero-stuffed
    output (times F), Hann segments of 120 with overlap 60, summed over the
    experiments (scipy's density scaling cancels in the ratio). We see 1e-15
    relative; a transposed S_uu (S_uu[i, j] = sum conj(U_i) U_j) is off by up
    to 22x."""
    rng = np.random.default_rng(3)
    N, F, L = 1200, 3, 120
    u = rng.standard_normal((2, 2, N))
    y = np.stack([_three_by_two(u[p])[:, ::F] for p in range(2)])
    y += 1e-2 * rng.standard_normal(y.shape)
    sa = SpectralAnalysis(segment_length=L, overlap=L // 2).fit(u, y, F)
    K = L // 2 + 1
    Suu, Syu = np.zeros((K, 2, 2), complex), np.zeros((K, 3, 2), complex)
    Syy = np.zeros((K, 3))

    def spectrum(a, b):  # mean over segments of A conj(B) (csd(x, y): conj(X) Y)
        return csd(b, a, window="hann", nperseg=L, noverlap=L // 2,
                   detrend=False)[1]

    for p in range(2):
        stuffed = np.zeros((3, N))
        stuffed[:, ::F] = F * y[p]
        for i in range(2):
            for j in range(2):
                Suu[:, i, j] += spectrum(u[p, i], u[p, j])
            for o in range(3):
                Syu[:, o, i] += spectrum(stuffed[o], u[p, i])
        for o in range(3):
            Syy[:, o] += spectrum(stuffed[o], stuffed[o]).real
    H = Syu @ np.linalg.inv(Suu)
    assert sa.valid_.all()
    np.testing.assert_allclose(sa.frf_, np.moveaxis(H, 0, -1), rtol=1e-12,
                               atol=1e-12 * np.abs(H).max())
    explained = np.real(np.einsum("koi,koi->ko", H, np.conj(Syu)))
    np.testing.assert_allclose(sa.coherence_, (explained / Syy).T, atol=1e-12)


def test_spectral_analysis_predict_refuses_input_at_invalid_bins():
    """A multisine below 0.04 cycles/sample leaves the segment bins near the
    fast Nyquist frequency invalid (power below 1e-12 of the mean). predict
    interpolated over valid bins only, so it extended the last valid bin to
    the fast Nyquist frequency and an input there was predicted silently (R^2
    -2.8e9 for white noise through the true system). Now those fast bins are
    NaN: an input that excites them is refused, as for the local models, and
    the training input (no energy there) is still predicted."""
    N, F = 2400, 3
    u = multisine(N, bins=np.arange(1, 100), rng=0)
    y = lfilter([0.2, 0.1], [1, -0.5], u)[::F]
    sa = SpectralAnalysis().fit(u, y, F)
    assert 0 < (~sa.valid_).sum() < 10 and not sa.valid_[-1]
    white = np.random.default_rng(0).standard_normal(N)
    with pytest.raises(ValueError, match=r"invalid \(NaN\) at \d+ fast DFT bin"):
        sa.predict(white)
    assert np.all(np.isfinite(sa.predict(u)))
    assert sa.score(u, y) > 0.99


def test_spectral_analysis_dependent_inputs_warn_and_say_so():
    """Two inputs of one experiment, the second twice the first: S_uu is
    singular at every bin, so every bin is invalid. That was silent, and
    predict said the training input 'had no energy'. Now fit warns, naming
    the dependence, and predict's error mentions it."""
    rng = np.random.default_rng(1)
    N, F = 1200, 3
    u1 = rng.standard_normal(N)
    y = lfilter([0.2, 0.1], [1, -0.5], u1)[::F]
    with pytest.warns(IdentifiabilityWarning,
                      match="101 of 101 bins.*singular.*linearly dependent"):
        sa = SpectralAnalysis().fit(np.stack([u1, 2 * u1]), y, F)
    assert not sa.valid_.any() and np.all(np.isnan(sa.frf_))
    with pytest.raises(ValueError, match="linearly dependent at every bin"):
        sa.predict(np.stack([u1, 2 * u1]))


def test_spectral_analysis_independent_inputs_do_not_warn():
    """The dependence warning is not raised for independent inputs, nor for
    one input whose unexcited bins are invalid (SISO keeps its silence)."""
    rng = np.random.default_rng(2)
    u = rng.standard_normal((2, 1200))
    y = _three_by_two(u)[:, ::3]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert SpectralAnalysis().fit(u, y, 3).valid_.all()
        siso = SpectralAnalysis().fit(np.ones(1200), np.ones(400), 3)
    assert not siso.valid_.all()


def test_lrm_dependent_inputs_warning_names_the_dependence():
    """One record whose second input is twice the first: every local problem
    is rank-deficient though both inputs excite every band. The warning only
    advised 'an input that excites every band', which these inputs do; it now
    names the dependence and orthogonal_multisines."""
    from lrmfrf import LRMBeyondNyquist

    rng = np.random.default_rng(4)
    u1 = rng.standard_normal(1200)
    y = lfilter([0.2, 0.1], [1, -0.5], u1)[::3]
    with pytest.warns(IdentifiabilityWarning,
                      match=r"\(0 of them because.*linearly dependent.*"
                      "orthogonal_multisines"):
        est = LRMBeyondNyquist(half_window=24).fit(np.stack([u1, 2 * u1]), y, 3)
    assert not est.valid_.any()
