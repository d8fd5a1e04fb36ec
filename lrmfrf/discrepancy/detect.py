"""Is the measurement different from the model, where, and how sure are we?

The whitened residual ``w(k) = (G_meas(k) - G_model(k)) / (kappa(k) std(k))``
is about standard complex normal where the model is right, so ``|w|^2`` is
about ``Exp(1)``. Three things spoil a naive chi-square test and are
calibrated here by simulating the estimator on model-generated data
(:func:`calibrate`):

- the estimator's ``std`` is off by a frequency-dependent factor (Lemma 2
  underestimates the LRM error, by 20-50 % on the closed-loop wafer stage);
- the estimator is biased at sharp resonances (noise-induced bias of local
  rational models, up to ~10 std at a 0.8 %-damped mode). The bias depends on
  the model, so it is not subtracted but counted as error in ``kappa``;
- neighbouring bins are strongly correlated (overlapping local windows), so
  ``K`` bins carry only ``K / c`` independent chi-square terms. The inflation
  ``c`` is measured from the run-to-run variance of band averages.

With these, ``mean |w|^2`` is approximately ``Gamma(n_eff, 1/n_eff)``
(global test) and the moving mean over ``smoothing_bins`` bins (the discrepancy
spectrum) approximately ``Gamma(a, 1/a)`` with ``a`` measured too; its
maximum is tested with a Bonferroni correction over ``n_eff`` bins.

MIMO (``n_y x n_u`` entries). Each entry has its own bias and ``kappa``; the
whitened residual is all entries' bins, and the statistics work on the bin
power ``m(k)``, the mean over entries of ``|w_ij(k)|^2`` (:func:`bin_power`;
``|w(k)|^2`` for SISO). The inflation ``c`` is counted against the
``n_entries K`` terms (``K n_entries / c`` independent ones: ``c`` is about
the SISO bin correlation when the entries' errors are independent, larger when
they are correlated), so ``mean m`` is approximately
``Gamma(n_eff, 1/n_eff)`` with ``n_eff = n_entries K / c``, and the cost
``sum |w|^2 / c`` a chi-square as in SISO. The discrepancy spectrum is the
moving mean of ``m`` (the sum over entries of the smoothed whitened squared
residual, divided by ``n_entries``); its Gamma shape ``a`` is measured from
the simulated runs as in SISO (bounded by ``n_entries * smoothing_bins``) and
its maximum is tested over the ``K / c`` positions. All of it is calibrated
by the same simulation (the MIMO model, the measured inputs, each output's
measured noise spectrum), so no independence between entries is assumed.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.ndimage
import scipy.stats
from sklearn.base import clone

from .._validation import renamed_keyword

__all__ = [
    "Calibration",
    "GlobalTest",
    "bin_power",
    "calibrate",
    "uncalibrated",
    "discrepancy_spectrum",
    "global_test",
]


@dataclass(frozen=True)
class Calibration:
    """How the estimator's errors behave under the model (null hypothesis).

    Attributes
    ----------
    bias : ndarray of shape (K,), complex
        Mean estimator error ``E[G_hat] - G_model`` at the compared bins
        (e.g. the noise-induced bias of local rational models at sharp
        resonances); zero when not calibrated. It depends on the model, so it
        is not subtracted; it is counted as error in ``scale``.
    scale : ndarray of shape (K,)
        ``kappa(k)``: the RMS estimator error (bias included) is
        ``kappa * std``.
    inflation : float
        Correlation inflation ``c >= 1``: ``K`` bins count as ``K / c``
        independent ones.
    spectrum_shape : float
        Gamma shape ``a`` of the discrepancy spectrum (a
        ``smoothing_bins``-bin mean).
    smoothing_bins : int
        Bins in the discrepancy-spectrum moving average (called ``window``
        before issue 12; ``window`` still reads it, with a FutureWarning).
    n_runs : int
        Simulated experiments used (0: not calibrated).
    null_gaps : ndarray of shape (n_runs,)
        Whitened RMS gap of each simulated run, bias and scale applied.
    method : str
        ``"simulation"`` or ``"uncalibrated"``.
    noise_scale : ndarray of shape (K,) or None
        Scale of the error of ``G_meas - bias`` (bias not counted, the noise
        of its ``n_runs``-run estimate counted), for the bias-corrected refit;
        ``None`` when not calibrated.
    n_entries : int, default 1
        ``n_y * n_u`` of a MIMO measurement (``bias``, ``scale`` and
        ``noise_scale`` then have shape ``(n_y, n_u, K)``; ``inflation`` counts
        against ``n_entries * K`` terms, see the module docstring).
    """

    bias: np.ndarray
    scale: np.ndarray
    inflation: float
    spectrum_shape: float
    smoothing_bins: int
    n_runs: int
    null_gaps: np.ndarray
    method: str = "simulation"
    noise_scale: np.ndarray | None = None
    n_entries: int = 1

    @property
    def window(self) -> int:
        """Deprecated name of :attr:`smoothing_bins` (removed in the next release)."""
        warnings.warn(
            "`Calibration.window` was renamed to `smoothing_bins` (issue 12) and "
            "will be removed in the next release. Use calibration.smoothing_bins.",
            FutureWarning, stacklevel=2,
        )
        return self.smoothing_bins

    @property
    def std_scale(self) -> float:
        """RMS of ``scale`` over the bins (a single summary number)."""
        return float(np.sqrt(np.mean(self.scale**2)))


@dataclass(frozen=True)
class GlobalTest:
    """Result of the global and local tests on one whitened residual.

    Attributes
    ----------
    gap : float
        Whitened RMS gap ``sqrt(mean |w|^2)``.
    statistic : float
        ``mean |w|^2``.
    p_value : float
        Of the global (mean) test.
    spectrum : ndarray of shape (K,)
        Discrepancy spectrum (moving mean of ``|w|^2``).
    spectrum_threshold : float
        Level the spectrum exceeds anywhere with probability ``alpha / 2``
        under the model.
    bin_p_values : ndarray of shape (K,)
        Per-bin p-values ``exp(-|w|^2)``.
    significant : bool
        Global or local test rejects at level ``alpha``.
    """

    gap: float
    statistic: float
    p_value: float
    spectrum: np.ndarray
    spectrum_threshold: float
    bin_p_values: np.ndarray
    significant: bool


def discrepancy_spectrum(w2: np.ndarray, smoothing_bins: int | None = None, *,
                         window: int | None = None) -> np.ndarray:
    """Moving mean of ``|w|^2`` over ``smoothing_bins`` bins (edges: shorter).

    Parameters
    ----------
    w2 : ndarray of shape (..., K)
    smoothing_bins : int
        Width of the moving mean in bins.
    window : int, optional
        Deprecated name of ``smoothing_bins``.

    Returns
    -------
    ndarray of shape (..., K)
    """
    width = renamed_keyword(smoothing_bins, window, new="smoothing_bins",
                            old="window")
    if width is None:
        raise TypeError("discrepancy_spectrum() needs `smoothing_bins`, the "
                        "width of the moving mean in bins, e.g. smoothing_bins=9.")
    w2 = np.asarray(w2, dtype=float)
    if width <= 1:
        return w2.copy()
    ones = np.ones(w2.shape[-1])
    total = scipy.ndimage.uniform_filter1d(w2, width, axis=-1, mode="constant")
    count = scipy.ndimage.uniform_filter1d(ones, width, mode="constant")
    return total / count


def bin_power(w: np.ndarray) -> np.ndarray:
    """Mean over entries of ``|w|^2`` per bin: shape (K,) from (..., K).

    ``|w|^2`` itself for SISO ``w`` of shape (K,).
    """
    w2 = np.abs(np.asarray(w)) ** 2
    if w2.ndim == 1:
        return w2
    return w2.reshape(-1, w2.shape[-1]).mean(axis=0)


def n_effective(n_bins: int, calibration: Calibration) -> float:
    """Effective number of independent terms ``n_entries * n_bins / inflation``."""
    return max(n_bins * calibration.n_entries / calibration.inflation, 1.0)


def global_test(w2: np.ndarray, calibration: Calibration, alpha: float) -> GlobalTest:
    """Global (mean) and local (spectrum maximum) tests, each at ``alpha / 2``.

    Parameters
    ----------
    w2 : ndarray of shape (K,)
        ``|w|^2`` with the calibrated std (``kappa`` applied); for MIMO the
        bin power (:func:`bin_power`).
    calibration : Calibration
    alpha : float
        Family-wise false-alarm level.

    Returns
    -------
    GlobalTest
    """
    w2 = np.asarray(w2, dtype=float)
    K = w2.size
    statistic = float(np.mean(w2))
    n_eff = n_effective(K, calibration)
    p_value = float(scipy.stats.gamma.sf(statistic * n_eff, n_eff))
    spectrum = discrepancy_spectrum(w2, calibration.smoothing_bins)
    threshold = spectrum_threshold(K, calibration, alpha / 2)
    local = bool(np.any(spectrum > threshold))
    return GlobalTest(
        gap=math.sqrt(statistic),
        statistic=statistic,
        p_value=p_value,
        spectrum=spectrum,
        spectrum_threshold=threshold,
        bin_p_values=np.exp(-w2),
        significant=bool(p_value < alpha / 2 or local),
    )


def spectrum_threshold(n_bins: int, calibration: Calibration, alpha: float) -> float:
    """Level of the discrepancy spectrum with family-wise exceedance ``alpha``.

    Bonferroni over the ``n_bins / inflation`` effectively independent bins
    (the moving mean is evaluated at every bin, so counting only
    non-overlapping windows would be too lenient). For MIMO the positions are
    the ``n_bins / inflation`` bins, not the entries.
    """
    n_tests = max(n_bins / calibration.inflation, 1.0)
    a = calibration.spectrum_shape
    return float(scipy.stats.gamma.isf(alpha / n_tests, a) / a)


def uncalibrated(n_bins: int, smoothing_bins: int = 9, inflation: float = 1.0, *,
                 window: int | None = None, entry_shape: tuple = ()) -> Calibration:
    """Calibration that trusts the estimator's std, no bias, given inflation.

    Used when simulation is switched off (``calibration_runs=0``); the tests
    are then only as good as the estimator's std and ``inflation``.
    ``window`` is the deprecated name of ``smoothing_bins``; ``entry_shape``
    is ``(n_y, n_u)`` for a MIMO measurement.
    """
    smoothing_bins = renamed_keyword(smoothing_bins, window, new="smoothing_bins",
                                     old="window", default=9)
    shape = max(smoothing_bins / max(inflation, 1.0), 1.0)
    full = tuple(entry_shape) + (n_bins,)
    n_entries = int(np.prod(entry_shape, dtype=int))
    return Calibration(np.zeros(full, complex), np.ones(full), float(inflation),
                       float(shape * n_entries), int(smoothing_bins), 0, np.zeros(0),
                       method="uncalibrated", n_entries=n_entries)


def calibrate(
    estimator,
    model_system,
    u: np.ndarray,
    F: int,
    sample_time: float,
    noise_variance: np.ndarray,
    bins: np.ndarray,
    model_frf: np.ndarray,
    *,
    n_runs: int = 10,
    smoothing_bins: int = 9,
    n_bands: int = 8,
    rng: np.random.Generator,
    window: int | None = None,
    steady_state: bool = False,
) -> Calibration:
    """Calibrate the tests by fitting the estimator to model-generated data.

    Each run simulates ``model_system`` from rest (or, with ``steady_state``,
    in the periodic steady state of each input) with the measured inputs,
    adds slow-rate noise with the measured noise spectrum, fits a clone of
    the estimator and compares its FRF with the model's. The mean error is
    the estimator bias, the RMS whitened error about it (smoothed over
    ``2 smoothing_bins + 1`` bins) the std scale, and the run-to-run variance
    of band means the correlation inflation.

    Parameters
    ----------
    estimator : estimator
        Unfitted template (cloned per run).
    model_system : control.StateSpace
        Discrete model of the measured system (closed loop if a controller).
    u : ndarray of shape (P, N) (SISO) or (P, n_u, N)
        Inputs of the experiments.
    F : int
    sample_time : float
    noise_variance : ndarray of shape (M//2+1,) or (n_y, M//2+1)
        Variance of the slow output noise DFT per slow bin (unnormalised DFT),
        per output for MIMO.
    bins : ndarray of int, shape (K,)
        Fast bins (``0..N//2``) compared.
    model_frf : ndarray of shape (K,) or (n_y, n_u, K), complex
        Model FRF at ``bins``.
    n_runs, smoothing_bins, n_bands : int
        Simulated runs, width of the discrepancy-spectrum moving mean (bins)
        and number of bands for the correlation inflation.
    rng : numpy.random.Generator
    window : int, optional
        Deprecated name of ``smoothing_bins`` (removed in the next release).
    steady_state : bool, default False
        Simulate the periodic steady state (:func:`lrmfrf.simulate.
        periodic_state`) instead of starting at rest: as the measured records
        were taken (the estimator's bias differs between the two).

    Returns
    -------
    Calibration
    """
    from ..simulate import periodic_state, simulate

    width = renamed_keyword(smoothing_bins, window, new="smoothing_bins",
                            old="window", default=9)
    P, N = u.shape[0], u.shape[-1]
    M = N // F
    clean = np.stack([
        simulate(model_system, u[p], F,
                 x0=periodic_state(model_system, u[p]) if steady_state else None
                 ).y_l_clean
        for p in range(P)
    ])  # (P, M) or (P, n_y, M)
    noise_variance = np.asarray(noise_variance, dtype=float)
    if clean.ndim == 2:
        noise_std_spectrum = _smooth_noise_spectrum(noise_variance, M)
    else:
        noise_variance = noise_variance.reshape(clean.shape[1], -1)
        noise_std_spectrum = np.stack([_smooth_noise_spectrum(v, M)
                                       for v in noise_variance])
    frfs, stds = [], []
    for _ in range(n_runs):
        noise = _coloured_noise(noise_std_spectrum, M, P, rng)
        fitted = clone(estimator)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fitted.fit(list(u), list(clean + noise), F, sample_time=sample_time)
        frfs.append(np.asarray(fitted.frf_)[..., bins])
        stds.append(np.asarray(fitted.frf_std_)[..., bins])
    frfs, stds = np.array(frfs), np.array(stds)
    finite = np.isfinite(frfs) & np.isfinite(stds) & (stds > 0)
    if np.count_nonzero(finite.all(axis=0)) < 2 * n_bands:
        raise ValueError(
            "calibration failed: the estimator returned too few finite bins on "
            "model-generated data. Check the estimator settings."
        )
    errors = np.where(finite, frfs - model_frf, 0.0)
    counts = np.maximum(finite.sum(axis=0), 1)
    bias = errors.sum(axis=0) / counts
    mean_std2 = np.where(finite, stds**2, 0.0).sum(axis=0) / counts
    with np.errstate(divide="ignore", invalid="ignore"):
        w2 = np.where(finite, np.abs(errors - bias) ** 2 / stds**2, np.nan)
        bias2 = np.abs(bias) ** 2 / mean_std2
    correction = n_runs / max(n_runs - 1, 1)  # the bias was estimated
    variance = np.nanmean(w2, axis=0) * correction
    variance = np.where(np.isfinite(variance), variance, np.nanmedian(variance))
    variance = scipy.ndimage.uniform_filter1d(variance, 2 * width + 1,
                                              mode="nearest")
    variance = np.maximum(variance, 0.25)
    # the bias is treated as error (it depends on the model, so it is not
    # subtracted): kept local, less the part due to noise in its estimate
    bias2 = np.where(np.isfinite(bias2), bias2 - variance / n_runs, 0.0)
    bias2 = scipy.ndimage.maximum_filter1d(np.maximum(bias2, 0.0), 3)
    scale2 = variance + bias2
    with np.errstate(divide="ignore", invalid="ignore"):
        w2 = np.where(finite, np.abs(errors) ** 2 / stds**2, np.nan)
    z2 = np.where(np.isfinite(w2), w2 / scale2, 1.0)
    n_entries = int(np.prod(z2.shape[1:-1], dtype=int))
    if n_entries > 1:  # the bin power: mean over entries
        z2 = z2.reshape(n_runs, n_entries, -1).mean(axis=1)
    inflation = _inflation(z2, n_bands, n_entries)
    spectra = discrepancy_spectrum(z2, width)
    var = float(np.mean(np.var(spectra, axis=0, ddof=1)))
    mean = float(np.mean(spectra))
    most = width * n_entries
    shape = float(np.clip(mean**2 / var, 1.0, most)) if var > 0 else float(most)
    return Calibration(
        bias=bias,
        scale=np.sqrt(scale2),
        noise_scale=np.sqrt(variance * (1.0 + 1.0 / n_runs)),
        inflation=inflation,
        spectrum_shape=shape,
        smoothing_bins=int(width),
        n_runs=int(n_runs),
        null_gaps=np.sqrt(np.mean(z2, axis=1)),
        n_entries=n_entries,
    )


def _inflation(w2: np.ndarray, n_bands: int, n_entries: int = 1) -> float:
    """``c`` from the run-to-run variance of band means of ``|w|^2``.

    For ``L`` independent Exp(1) terms the band mean has variance ``1/L``; the
    pooled ratio of observed to independent variance is ``c``. With MIMO bin
    powers (means of ``n_entries`` terms) a band of ``L`` bins holds
    ``n_entries L`` terms.
    """
    n_runs, K = w2.shape
    edges = np.linspace(0, K, n_bands + 1).astype(int)
    ratios, weights = [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        band = w2[:, lo:hi].mean(axis=1)
        mean = band.mean()
        if mean <= 0:
            continue
        ratios.append(band.var(ddof=1) / mean**2 * (hi - lo) * n_entries)
        weights.append(hi - lo)
    if not ratios:
        return 1.0
    return float(max(np.average(ratios, weights=weights), 1.0))


def _smooth_noise_spectrum(noise_variance: np.ndarray, M: int) -> np.ndarray:
    """Standard deviation of ``V_l(k)``, ``k = 0..M//2``, median-smoothed."""
    var = np.asarray(noise_variance, dtype=float).reshape(-1)
    var = np.where(np.isfinite(var) & (var > 0), var, np.nan)
    if np.all(np.isnan(var)):
        raise ValueError("the estimator's noise variance is NaN or zero everywhere.")
    var = np.where(np.isnan(var), np.nanmedian(var), var)
    smooth = scipy.ndimage.median_filter(var, size=9, mode="nearest")
    if smooth.size != M // 2 + 1:
        smooth = np.interp(np.linspace(0, 1, M // 2 + 1),
                           np.linspace(0, 1, smooth.size), smooth)
    return np.sqrt(smooth)


def _coloured_noise(std_spectrum: np.ndarray, M: int, P: int,
                    rng: np.random.Generator) -> np.ndarray:
    """``P`` real noise records whose DFT has ``E|V(k)|^2 = std_spectrum(k)^2``.

    ``std_spectrum`` of shape (M//2+1,) gives (P, M); of shape (n_y, M//2+1)
    (one spectrum per output) gives (P, n_y, M).
    """
    shape = (P,) + std_spectrum.shape
    spectrum = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))
    spectrum *= std_spectrum / math.sqrt(2.0)
    spectrum[..., 0] = std_spectrum[..., 0] * rng.standard_normal(shape[:-1])
    if M % 2 == 0:
        spectrum[..., -1] = std_spectrum[..., -1] * rng.standard_normal(shape[:-1])
    return np.fft.irfft(spectrum, n=M, axis=-1)
