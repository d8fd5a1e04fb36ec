"""Error metrics for estimated frequency response functions.

Plain functions on arrays: ``G_true`` and ``G_hat`` are complex arrays on the
same frequency grid, usually the one-sided fast DFT grid ``k = 0..N//2`` of an
estimator's ``frf_`` (with ``frequencies_`` in Hz and the boolean ``valid_``
mask). Bins that an estimator could not identify hold NaN; pass ``valid`` to
exclude them, otherwise NaN raises.

The cumulative error is the paper's eq. (CPSD),

.. math:: e_{cum}(n) = \\frac{1}{N} \\sum_{k=1}^{n} |G(\\Omega_k) -
          \\widehat{G}(\\Omega_k)|,

which starts at ``k = 1`` (the DC bin is skipped, as in the paper: a closed
loop with integral action has ``G(0) = 0``).
"""

from __future__ import annotations

import math
import numbers

import numpy as np

__all__ = [
    "band_mask",
    "cumulative_error",
    "error_summary",
    "relative_error",
    "resonance_mask",
    "std_ratio",
]


def cumulative_error(
    G_true: np.ndarray,
    G_hat: np.ndarray,
    n_samples: int | None = None,
    *,
    valid: np.ndarray | None = None,
) -> np.ndarray:
    """Cumulative absolute FRF error, paper eq. (CPSD).

    Parameters
    ----------
    G_true, G_hat : array_like of complex, shape (K,)
        True and estimated FRF on the same grid (bin ``k`` at index ``k``).
    n_samples : int, optional
        Record length ``N`` of the normalisation ``1/N``. ``K`` must be
        ``N//2 + 1`` (one-sided grid) or ``N`` (two-sided). Default
        ``2 (K - 1)``: a one-sided grid of an even-length record.
    valid : array_like of bool, shape (K,), optional
        Bins to include; excluded bins add zero error (so compare methods on a
        common mask). Without it, NaN or inf in either FRF raises.

    Returns
    -------
    ndarray of shape (K,)
        ``out[n] = (1/N) sum_{k=1}^{n} |G(k) - G_hat(k)|`` (``out[0] = 0``),
        in the units of ``G``.

    Examples
    --------
    >>> cumulative_error(np.zeros(4), np.full(4, 0.5), 6)
    array([0.        , 0.08333333, 0.16666667, 0.25      ])
    """
    true, estimate, mask = _check_pair(G_true, G_hat, valid)
    n = _check_record_length(n_samples, true.size)
    errors = np.zeros(true.size)
    errors[mask] = np.abs(true[mask] - estimate[mask])
    errors[0] = 0.0  # eq. (CPSD) starts at k = 1
    return np.cumsum(errors) / n


def relative_error(G_true: np.ndarray, G_hat: np.ndarray) -> np.ndarray:
    """Per-bin relative error ``|G - G_hat| / |G|``.

    Parameters
    ----------
    G_true, G_hat : array_like of complex, shape (K,)
        True and estimated FRF on the same grid.

    Returns
    -------
    ndarray of shape (K,)
        Relative error (dimensionless); NaN where either FRF is NaN and
        ``inf`` where ``G_true`` is exactly zero and the error is not.

    Examples
    --------
    >>> relative_error(np.array([2.0, 1j]), np.array([1.0, 1j]))
    array([0.5, 0. ])
    """
    true = _as_frf(G_true, "G_true")
    estimate = _as_frf(G_hat, "G_hat")
    _check_same_shape(true, estimate)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(true - estimate) / np.abs(true)


def band_mask(
    frequencies: np.ndarray,
    *,
    low: float | None = None,
    high: float | None = None,
) -> np.ndarray:
    """Boolean mask of bins with ``low < f <= high`` (bounds optional).

    Parameters
    ----------
    frequencies : array_like of shape (K,)
        Frequencies in Hz.
    low, high : float, optional
        Exclusive lower and inclusive upper bound in Hz.

    Returns
    -------
    ndarray of bool, shape (K,)

    Examples
    --------
    >>> band_mask(np.array([0.0, 100.0, 333.3, 400.0]), low=0.0, high=333.3)
    array([False,  True,  True, False])
    """
    freqs = _as_frequencies(frequencies)
    mask = np.ones(freqs.shape, dtype=bool)
    if low is not None:
        mask &= freqs > low
    if high is not None:
        mask &= freqs <= high
    return mask


def resonance_mask(
    frequencies: np.ndarray,
    resonances: np.ndarray,
    *,
    rel_band: float = 0.05,
) -> np.ndarray:
    """Bins within ``+/- rel_band * f_r`` of any resonance frequency ``f_r``.

    Parameters
    ----------
    frequencies : array_like of shape (K,)
        Frequencies in Hz.
    resonances : array_like of shape (n_resonances,)
        Resonance frequencies in Hz, > 0.
    rel_band : float, default 0.05
        Relative half-width of each band, > 0.

    Returns
    -------
    ndarray of bool, shape (K,)

    Examples
    --------
    >>> resonance_mask(np.array([90.0, 96.0, 104.0, 110.0]), [100.0])
    array([False,  True,  True, False])
    """
    freqs = _as_frequencies(frequencies)
    centres = np.atleast_1d(np.asarray(resonances, dtype=float))
    if centres.ndim != 1 or not np.all(np.isfinite(centres)) or np.any(centres <= 0):
        raise ValueError(
            f"resonances must be a 1-D sequence of finite frequencies > 0 Hz; got "
            f"{resonances!r}."
        )
    if not (isinstance(rel_band, numbers.Real) and 0 < rel_band < math.inf):
        raise ValueError(f"rel_band must be a finite number > 0; got {rel_band!r}.")
    distance = np.abs(freqs[:, np.newaxis] - centres[np.newaxis, :])
    return np.any(distance <= rel_band * centres[np.newaxis, :], axis=1)


def error_summary(
    G_true: np.ndarray,
    G_hat: np.ndarray,
    frequencies: np.ndarray,
    *,
    slow_nyquist: float,
    resonances: np.ndarray | None = None,
    rel_band: float = 0.05,
    valid: np.ndarray | None = None,
    n_samples: int | None = None,
) -> dict[str, float]:
    """Median and RMS relative errors per band and the total cumulative error.

    Bands: "below" is ``0 < f <= slow_nyquist``, "above" is
    ``f > slow_nyquist``, "resonance" is within ``+/- rel_band * f_r`` of a
    resonance. The DC bin (``f = 0``) and invalid bins are excluded
    everywhere. RMS is ``sqrt(mean(rel^2))``. A band without bins gives NaN.

    Parameters
    ----------
    G_true, G_hat : array_like of complex, shape (K,)
        True and estimated FRF.
    frequencies : array_like of shape (K,)
        Bin frequencies in Hz (e.g. :func:`lrmfrf.simulate.frequency_grid`).
    slow_nyquist : float
        Nyquist frequency of the slow output in Hz, ``1 / (2 F Ts)``.
    resonances : array_like of float, optional
        Resonance frequencies in Hz.
    rel_band : float, default 0.05
        Relative half-width of the resonance bands.
    valid : array_like of bool, shape (K,), optional
        Bins to include (e.g. an estimator's ``valid_``).
    n_samples : int, optional
        Record length for the cumulative error; see :func:`cumulative_error`.

    Returns
    -------
    dict of str to float
        Keys ``median_relative_{all,below,above,resonance}``,
        ``rms_relative_{all,below,above,resonance}``,
        ``n_bins_{all,below,above,resonance}`` and ``cumulative_error``
        (total of eq. (CPSD), units of ``G``).
    """
    true, estimate, mask = _check_pair(G_true, G_hat, valid)
    freqs = _as_frequencies(frequencies)
    if freqs.shape != true.shape:
        raise ValueError(
            f"frequencies must have the FRF's shape {true.shape}; got {freqs.shape}."
        )
    if not (isinstance(slow_nyquist, numbers.Real) and 0 < slow_nyquist < math.inf):
        raise ValueError(
            f"slow_nyquist must be a finite frequency > 0 Hz; got {slow_nyquist!r}. "
            "Use 1 / (2 * F * sample_time)."
        )
    included = mask & (freqs > 0)
    relative = np.full(true.shape, np.nan)
    relative[included] = relative_error(true[included], estimate[included])
    bands = {
        "all": included,
        "below": included & band_mask(freqs, high=slow_nyquist),
        "above": included & band_mask(freqs, low=slow_nyquist),
    }
    if resonances is not None:
        bands["resonance"] = included & resonance_mask(
            freqs, resonances, rel_band=rel_band
        )
    else:
        bands["resonance"] = np.zeros(true.shape, dtype=bool)
    summary: dict[str, float] = {}
    for name, band in bands.items():
        values = relative[band]
        summary[f"median_relative_{name}"] = (
            float(np.median(values)) if values.size else math.nan
        )
        summary[f"rms_relative_{name}"] = (
            float(np.sqrt(np.mean(values**2))) if values.size else math.nan
        )
        summary[f"n_bins_{name}"] = int(values.size)
    summary["cumulative_error"] = float(
        cumulative_error(true, estimate, n_samples, valid=mask)[-1]
    )
    return summary


def std_ratio(
    predicted_std: np.ndarray,
    monte_carlo_estimates: np.ndarray,
    G_true: np.ndarray | None,
) -> float:
    """Median over bins of predicted std / Monte-Carlo std.

    The std of a complex estimate is ``sqrt(E |G_hat - centre|^2)``. The
    Monte-Carlo std is taken about ``G_true`` (RMS error: bias included,
    ``ddof = 0``) when it is given, else about the sample mean (``ddof =
    1``). A ratio below 1 means the predicted std is too optimistic. Bins
    where any run or the prediction is not finite, or the Monte-Carlo std is
    zero, are skipped.

    Parameters
    ----------
    predicted_std : array_like of shape (K,) or (R, K)
        Predicted std per bin (e.g. ``frf_std_``); per-run predictions are
        combined as ``sqrt(mean_r std_r^2)``.
    monte_carlo_estimates : array_like of complex, shape (R, K)
        Estimates from ``R >= 2`` independent noise realisations.
    G_true : array_like of complex, shape (K,), or None
        True FRF, or None to measure the spread about the sample mean.

    Returns
    -------
    float
        Median ratio (dimensionless).

    Examples
    --------
    >>> estimates = np.array([[1.0, 2.0], [3.0, 4.0]])
    >>> std_ratio(np.array([1.0, 2.0]), estimates, np.array([2.0, 3.0]))
    1.5
    """
    runs = np.asarray(monte_carlo_estimates)
    if runs.ndim != 2 or runs.shape[0] < 2:
        raise ValueError(
            "monte_carlo_estimates must have shape (R, K) with R >= 2 runs; got "
            f"shape {runs.shape}. Stack the estimates with np.stack."
        )
    runs = runs.astype(complex)
    predicted = np.asarray(predicted_std, dtype=float)
    if predicted.shape == runs.shape:
        predicted = np.sqrt(np.mean(predicted**2, axis=0))
    elif predicted.shape != runs.shape[1:]:
        raise ValueError(
            f"predicted_std must have shape ({runs.shape[1]},) or {runs.shape}; "
            f"got {predicted.shape}."
        )
    if G_true is None:
        centre = np.mean(runs, axis=0)
        ddof = 1
    else:
        centre = _as_frf(G_true, "G_true")
        if centre.shape != runs.shape[1:]:
            raise ValueError(
                f"G_true must have shape ({runs.shape[1]},); got {centre.shape}."
            )
        ddof = 0
    with np.errstate(invalid="ignore"):
        spread = np.sqrt(
            np.sum(np.abs(runs - centre) ** 2, axis=0) / (runs.shape[0] - ddof)
        )
    usable = np.isfinite(spread) & np.isfinite(predicted) & (spread > 0)
    if not np.any(usable):
        raise ValueError(
            "no bin has a finite, non-zero Monte-Carlo std and a finite "
            "prediction; check the estimates for NaN or identical runs."
        )
    return float(np.median(predicted[usable] / spread[usable]))


# ---------------------------------------------------------------------------
# Private helpers
# ---------------------------------------------------------------------------


def _as_frf(values, name: str) -> np.ndarray:
    array = np.asarray(values)
    if array.ndim != 1:
        raise ValueError(f"{name} must be 1-D of shape (K,); got shape {array.shape}.")
    if not np.issubdtype(array.dtype, np.number):
        raise TypeError(f"{name} must be numeric; got dtype {array.dtype}.")
    return array.astype(complex)


def _as_frequencies(frequencies) -> np.ndarray:
    freqs = np.asarray(frequencies, dtype=float)
    if freqs.ndim != 1 or not np.all(np.isfinite(freqs)):
        raise ValueError(
            "frequencies must be a 1-D array of finite values in Hz; got shape "
            f"{freqs.shape}."
        )
    return freqs


def _check_same_shape(true: np.ndarray, estimate: np.ndarray) -> None:
    if true.shape != estimate.shape:
        raise ValueError(
            f"G_true and G_hat must have the same shape; got {true.shape} and "
            f"{estimate.shape}. Evaluate both on the same frequency grid."
        )


def _check_pair(G_true, G_hat, valid):
    true = _as_frf(G_true, "G_true")
    estimate = _as_frf(G_hat, "G_hat")
    _check_same_shape(true, estimate)
    if true.size == 0:
        raise ValueError("G_true and G_hat are empty; pass at least one bin.")
    if valid is None:
        mask = np.ones(true.shape, dtype=bool)
    else:
        mask = np.asarray(valid)
        if mask.dtype != bool or mask.shape != true.shape:
            raise ValueError(
                f"valid must be a boolean array of shape {true.shape}; got dtype "
                f"{mask.dtype} and shape {mask.shape}."
            )
    finite = np.isfinite(true) & np.isfinite(estimate)
    if np.any(mask & ~finite):
        bad = np.flatnonzero(mask & ~finite)
        raise ValueError(
            f"{bad.size} bin(s) hold NaN or inf (first at index {bad[0]}). "
            "Pass valid=estimator.valid_ (or a finite mask) to exclude them."
        )
    return true, estimate, mask


def _check_record_length(n_samples, n_bins: int) -> int:
    if n_samples is None:
        return max(2 * (n_bins - 1), 1)
    if isinstance(n_samples, bool) or not isinstance(n_samples, numbers.Integral):
        raise TypeError(
            f"n_samples must be an int; got {n_samples!r} of type "
            f"{type(n_samples).__name__}."
        )
    if n_samples < 1 or (n_samples // 2 + 1 != n_bins and n_samples != n_bins):
        raise ValueError(
            f"n_samples={n_samples} does not match the {n_bins} bins: expected "
            f"N with N//2 + 1 == {n_bins} (one-sided grid) or N == {n_bins} "
            "(two-sided grid)."
        )
    return int(n_samples)
