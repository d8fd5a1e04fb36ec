"""Tests for lrmfrf.metrics: known answers and bad input."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrmfrf.metrics import (
    band_mask,
    cumulative_error,
    error_summary,
    relative_error,
    resonance_mask,
    std_ratio,
)

# --- cumulative error, eq. (CPSD) --------------------------------------------


@settings(max_examples=30, deadline=None)
@given(
    n_samples=st.integers(2, 400),
    error=st.floats(1e-6, 1e3),
    phase=st.floats(-np.pi, np.pi),
)
def test_constant_error_accumulates_linearly(n_samples, error, phase):
    n_bins = n_samples // 2 + 1
    rng = np.random.default_rng(n_samples)
    G = rng.standard_normal(n_bins) + 1j * rng.standard_normal(n_bins)
    G_hat = G + error * np.exp(1j * phase)
    expected = np.arange(n_bins) * error / n_samples
    np.testing.assert_allclose(
        cumulative_error(G, G_hat, n_samples), expected, rtol=1e-9, atol=1e-12 * error
    )


def test_dc_bin_is_skipped_and_default_length_is_even_one_sided():
    G = np.zeros(5, dtype=complex)
    G_hat = np.array([100.0, 1.0, 0.0, 2.0, 0.0])
    # default N = 2 * (5 - 1) = 8; the DC error of 100 is not counted
    np.testing.assert_array_equal(
        cumulative_error(G, G_hat), [0.0, 1 / 8, 1 / 8, 3 / 8, 3 / 8]
    )
    np.testing.assert_array_equal(
        cumulative_error(G, G_hat, 9), np.array([0.0, 1.0, 1.0, 3.0, 3.0]) / 9
    )
    np.testing.assert_array_equal(
        cumulative_error(G, G_hat, 5), np.array([0.0, 1.0, 1.0, 3.0, 3.0]) / 5
    )  # two-sided grid


def test_invalid_bins_add_no_error():
    G = np.ones(4)
    G_hat = np.array([1.0, np.nan, 3.0, 1.5])
    valid = np.array([True, False, True, True])
    np.testing.assert_allclose(
        cumulative_error(G, G_hat, 6, valid=valid), [0.0, 0.0, 2 / 6, 2.5 / 6]
    )


# --- relative error and masks ---------------------------------------------------


def test_relative_error_known_answers():
    G = np.array([2.0, 1j, 1 + 1j, 0.0, 0.0])
    G_hat = np.array([1.0, 1j, 0.0, 1.0, np.nan])
    rel = relative_error(G, G_hat)
    np.testing.assert_allclose(rel[:3], [0.5, 0.0, 1.0], rtol=1e-15)
    assert rel[3] == np.inf and np.isnan(rel[4])


def test_band_and_resonance_masks():
    f = np.array([0.0, 100.0, 333.3, 333.4, 900.0])
    np.testing.assert_array_equal(
        band_mask(f, low=0.0, high=333.3), [False, True, True, False, False]
    )
    np.testing.assert_array_equal(
        band_mask(f, low=333.3), [False, False, False, True, True]
    )
    np.testing.assert_array_equal(band_mask(f), [True] * 5)
    freq = np.arange(0.0, 1000.0, 1.0)
    mask = resonance_mask(freq, [100.0, 500.0], rel_band=0.05)
    np.testing.assert_array_equal(
        np.flatnonzero(mask),
        np.concatenate([np.arange(95, 106), np.arange(475, 526)]),
    )


# --- error summary ----------------------------------------------------------------


def test_error_summary_known_answers():
    # N = 20, one-sided 11 bins at 0, 50, ..., 500 Hz; slow Nyquist 250 Hz
    freq = np.arange(11) * 50.0
    G = np.full(11, 2.0 + 0j)
    rel = np.array([9.0, 0.1, 0.1, 0.1, 0.3, 0.1, 0.2, 0.2, 0.2, 0.6, 0.2])
    G_hat = G * (1 + rel)
    out = error_summary(
        G, G_hat, freq, slow_nyquist=250.0, resonances=[200.0, 450.0], rel_band=0.05
    )
    below, above = rel[1:6], rel[6:]
    assert out["n_bins_all"] == 10  # DC excluded
    assert out["n_bins_below"] == 5 and out["n_bins_above"] == 5
    assert out["median_relative_below"] == pytest.approx(0.1, rel=1e-14)
    assert out["median_relative_above"] == pytest.approx(0.2, rel=1e-14)
    assert out["rms_relative_below"] == pytest.approx(
        np.sqrt(np.mean(below**2)), rel=1e-14
    )
    assert out["rms_relative_above"] == pytest.approx(
        np.sqrt(np.mean(above**2)), rel=1e-14
    )
    assert out["n_bins_resonance"] == 2
    assert out["median_relative_resonance"] == pytest.approx(0.45, rel=1e-14)
    assert out["rms_relative_all"] == pytest.approx(
        np.sqrt(np.mean(rel[1:] ** 2)), rel=1e-14
    )
    assert out["cumulative_error"] == pytest.approx(2 * rel[1:].sum() / 20, rel=1e-14)


def test_error_summary_without_resonances_and_with_valid_mask():
    freq = np.arange(5) * 100.0
    G = np.ones(5)
    G_hat = np.array([1.0, 1.1, np.nan, 1.4, 1.2])
    valid = np.isfinite(G_hat)
    out = error_summary(G, G_hat, freq, slow_nyquist=150.0, valid=valid)
    assert out["n_bins_resonance"] == 0 and np.isnan(out["median_relative_resonance"])
    assert out["n_bins_below"] == 1 and out["n_bins_above"] == 2
    assert out["median_relative_above"] == pytest.approx(0.3, rel=1e-14)
    assert out["cumulative_error"] == pytest.approx(0.7 / 8, rel=1e-14)


# --- std ratio ------------------------------------------------------------------------


def test_std_ratio_known_answer_about_truth_and_mean():
    G = np.array([1.0 + 1j, 2.0, -3.0j])
    sigma = np.array([0.1, 0.2, 0.4])
    signs = np.array([[1.0], [-1.0], [1.0], [-1.0]])
    runs = G + signs * sigma  # every run is exactly sigma away from G
    assert std_ratio(0.9 * sigma, runs, G) == pytest.approx(0.9, rel=1e-14)
    # about the mean (= G here), ddof = 1: spread is sigma * sqrt(4 / 3)
    assert std_ratio(sigma, runs, None) == pytest.approx(np.sqrt(3 / 4), rel=1e-14)
    per_run = np.tile(0.5 * sigma, (4, 1))
    assert std_ratio(per_run, runs, G) == pytest.approx(0.5, rel=1e-14)


def test_std_ratio_is_one_for_calibrated_gaussian_estimates():
    # R = 400 complex runs: each bin's std estimate has a relative std of
    # about 1/sqrt(4R) = 2.5 %; the median over 200 bins is within ~0.3 %.
    # A 2 % tolerance is more than 6 sigma.
    rng = np.random.default_rng(0)
    sigma = np.linspace(0.1, 2.0, 200)
    G = rng.standard_normal(200) + 1j * rng.standard_normal(200)
    noise = rng.standard_normal((400, 200)) + 1j * rng.standard_normal((400, 200))
    runs = G + sigma * noise / np.sqrt(2)
    assert std_ratio(sigma, runs, G) == pytest.approx(1.0, abs=0.02)
    assert std_ratio(sigma, runs, None) == pytest.approx(1.0, abs=0.02)


def test_std_ratio_skips_non_finite_bins():
    G = np.zeros(3, dtype=complex)
    runs = np.array([[1.0, np.nan, 1.0], [-1.0, 0.0, -1.0]])
    assert std_ratio(np.array([2.0, 1.0, 2.0]), runs, G) == pytest.approx(2.0)


# --- bad input ----------------------------------------------------------------------


def test_rejects_nan_without_valid_mask():
    with pytest.raises(ValueError, match="hold NaN or inf .* Pass valid="):
        cumulative_error(np.ones(3), np.array([1.0, np.nan, 1.0]))
    with pytest.raises(ValueError, match="hold NaN or inf"):
        error_summary(
            np.array([1.0, np.inf]), np.ones(2), np.array([0.0, 1.0]), slow_nyquist=1.0
        )


def test_rejects_shape_and_type_problems():
    with pytest.raises(ValueError, match="must have the same shape"):
        cumulative_error(np.ones(3), np.ones(4))
    with pytest.raises(ValueError, match="must have the same shape"):
        relative_error(np.ones(3), np.ones(4))
    with pytest.raises(ValueError, match=r"G_true must be 1-D of shape \(K,\)"):
        cumulative_error(np.ones((2, 3)), np.ones((2, 3)))
    with pytest.raises(TypeError, match="G_hat must be numeric"):
        relative_error(np.ones(2), np.array(["a", "b"]))
    with pytest.raises(ValueError, match="are empty"):
        cumulative_error(np.ones(0), np.ones(0))
    with pytest.raises(ValueError, match="valid must be a boolean array"):
        cumulative_error(np.ones(3), np.ones(3), valid=np.ones(3))


def test_rejects_mismatched_record_length():
    with pytest.raises(ValueError, match="does not match the 5 bins"):
        cumulative_error(np.ones(5), np.ones(5), 12)
    with pytest.raises(TypeError, match="n_samples must be an int"):
        cumulative_error(np.ones(5), np.ones(5), 8.0)


def test_rejects_bad_summary_settings():
    G, f = np.ones(4), np.arange(4.0)
    with pytest.raises(ValueError, match="slow_nyquist must be a finite frequency"):
        error_summary(G, G, f, slow_nyquist=0.0)
    with pytest.raises(ValueError, match="frequencies must have the FRF's shape"):
        error_summary(G, G, np.arange(3.0), slow_nyquist=1.0)
    with pytest.raises(ValueError, match="frequencies must be a 1-D array of finite"):
        band_mask(np.array([0.0, np.nan]))
    with pytest.raises(ValueError, match="resonances must be a 1-D sequence"):
        resonance_mask(f, [-5.0])
    with pytest.raises(ValueError, match="rel_band must be a finite number > 0"):
        resonance_mask(f, [1.0], rel_band=0.0)


def test_rejects_bad_std_ratio_input():
    runs = np.ones((3, 4))
    with pytest.raises(ValueError, match=r"shape \(R, K\) with R >= 2"):
        std_ratio(np.ones(4), np.ones((1, 4)), None)
    with pytest.raises(ValueError, match="predicted_std must have shape"):
        std_ratio(np.ones(5), runs, None)
    with pytest.raises(ValueError, match=r"G_true must have shape \(4,\)"):
        std_ratio(np.ones(4), runs, np.ones(3))
    with pytest.raises(ValueError, match="no bin has a finite, non-zero"):
        std_ratio(np.ones(4), runs, None)  # identical runs: zero spread
