"""Per-band choice of the local-model setting (``LRMBeyondNyquistCV(per_band=True)``).

A slow bin ``k`` (window centre, ``0..M//2``) fixes the ``F`` aliased fast
bins ``k + fM`` at once (one local problem), so a choice per slow bin covers
every fast frequency that aliases onto it. Two ways to choose:

- Per slow bin by the predicted std (``bands=None``, :func:`std_scores`,
  :func:`score_weights`): every candidate is fitted, its score at slow bin
  ``k`` is the mean of ``log frf_std_`` over the fast bins (and matrix
  entries) of ``k``, averaged over ``2 h + 1`` neighbouring slow bins, and the
  candidates are weighted by ``exp(-beta (score - best score))``. The
  output residual cannot tell how well a window separates the aliased bands
  (a low-order model fits their sum about as well), the band covariance
  can: on the cluster stages of ``benchmarks/generalisation_selection.py``
  the candidates that separate three modes aliasing onto one slow frequency
  best ranked 38-48 of 52 by the criterion over the cluster's windows.
- Per region (``bands`` given, :func:`region_bounds`): contiguous regions,
  each with the candidate whose criterion over the region's windows is
  lowest, blended linearly over a ramp around each edge.

Either way the FRFs are blended with weights that sum to one at every slow
bin (:func:`blend`), so the estimate is continuous where the choice changes.
"""

from __future__ import annotations

import numbers

import numpy as np

from ..local_models import one_sided_fast_grid, scale_by_power_of_two

#: Per-slow-bin choice (``bands=None``): scores averaged over ``2 h + 1`` slow
#: bins and weights ``exp(-beta (score - best))``. Chosen on the cluster
#: stages (seeds 1-8, both outputs, 40 dB) of
#: ``benchmarks/generalisation_selection.py --per-band`` among h = 2..25 and
#: beta = 3..1000, and checked on seeds 11-18; beta -> inf is the hard choice
#: per bin, a smaller beta averages candidates whose std is within a few %.
SCORE_HALF_WIDTH = 5
SCORE_SHARPNESS = 30.0

#: Residual degrees of freedom a candidate needs to enter the per-bin blend
#: (``bands=None``): a std estimated from one residual dof (the noise level of
#: Lemma 2 and of the default eiv route alike) is too noisy to weigh by. The
#: ``"pmse"`` criterion (the default) identifies candidates with one
#: (``"gaic"`` needs two); with them in the blend, the cluster stages of
#: ``benchmarks/generalisation_selection.py --per-band`` (SISO, seeds 1-8 /
#: 11-18) went from 0.862x / 0.857x to 0.903x / 0.887x the best single
#: setting's RMS error (``benchmarks/per_band_scores.py --siso``).
SCORE_MIN_DOF = 2


def region_bounds(bands, n_half: int, slow_frequencies: np.ndarray) -> np.ndarray:
    """Slow-bin boundaries ``0 = b_0 < b_1 < ... < b_R = n_half`` of the regions.

    Parameters
    ----------
    bands : int or sequence of float
        Number of equal regions, or the edges between regions as slow
        frequencies (units of ``slow_frequencies``), strictly inside
        ``(0, slow_frequencies[-1])`` and increasing.
    n_half : int
        ``M//2 + 1`` slow bins.
    slow_frequencies : ndarray of shape (n_half,)

    Returns
    -------
    ndarray of int, shape (R+1,)
    """
    if isinstance(bands, numbers.Integral):
        count = int(bands)
        if not 1 <= count <= n_half:
            raise ValueError(
                f"`bands` must be between 1 and {n_half} regions for this record "
                f"(M//2+1 = {n_half} slow bins). Got {count} instead."
            )
        return np.round(np.linspace(0, n_half, count + 1)).astype(int)
    edges = np.asarray(bands, dtype=float)
    top = float(slow_frequencies[-1])
    if (edges.ndim != 1 or not edges.size or not np.all(np.isfinite(edges))
            or np.any(np.diff(edges) <= 0) or edges[0] <= 0 or edges[-1] >= top):
        raise ValueError(
            f"`bands` edges must be increasing slow frequencies strictly between 0 "
            f"and the slow Nyquist frequency {top:g} (the units of "
            f"slow_frequencies_). Got {bands!r} instead."
        )
    inner = np.searchsorted(slow_frequencies, edges)
    bounds = np.unique(np.concatenate([[0], inner, [n_half]]))
    return bounds


def region_values(per_bin: np.ndarray, bounds: np.ndarray, combine) -> np.ndarray:
    """Criterion of one candidate in each region.

    ``combine(per_bin, well_posed)`` is the candidate's criterion on the
    windows marked well posed (the global one with all windows); windows of
    other regions are masked out. ``per_bin`` is ``(M//2+1,)``, or
    ``(n_y, M//2+1)`` with one row per output (a region is the same slow bins
    in every row).
    """
    out = np.empty(bounds.size - 1)
    finite = np.isfinite(per_bin)
    for r in range(out.size):
        mask = np.zeros(per_bin.shape, dtype=bool)
        mask[..., bounds[r] : bounds[r + 1]] = True
        out[r] = combine(per_bin, finite & mask)
    return out


def region_weights(bounds: np.ndarray, ramp: int) -> np.ndarray:
    """Weights ``(R, n_half)`` of each region at each slow bin, summing to 1.

    Region ``r`` has weight 1 inside and ramps linearly to 0 over ``ramp``
    bins centred on each of its inner edges (a partition of unity).
    """
    n_half = int(bounds[-1])
    R = bounds.size - 1
    k = np.arange(n_half) + 0.5  # bin centres; edges at integer positions
    weights = np.zeros((R, n_half))
    half = max(ramp, 1) / 2.0
    # cumulative "right of edge e" indicators, ramped
    steps = [np.clip((k - e) / (2 * half) + 0.5, 0.0, 1.0) for e in bounds[1:-1]]
    for r in range(R):
        left = steps[r - 1] if r > 0 else np.ones(n_half)
        right = steps[r] if r < R - 1 else np.zeros(n_half)
        weights[r] = left - right
    return np.clip(weights, 0.0, 1.0)


def to_fast_grid(slow_values: np.ndarray, n_samples: int, F: int) -> np.ndarray:
    """Per-slow-bin (``0..M//2``) real values on the fast grid ``0..N//2``."""
    return one_sided_fast_grid(np.repeat(slow_values[:, None], F, axis=1),
                               n_samples, F, conj=False)


def std_scores(estimators, n_samples: int, F: int) -> np.ndarray:
    """Score ``(C, M//2+1)`` of each fit at each slow bin: the mean of
    ``log(frf_std_ / 2**e)`` over the fast bins aliasing onto the bin (and
    over the entries of an FRF matrix), ``e`` the binary exponent of the
    largest valid std of all fits (a shift common to all scores, which makes
    them the same at any scale of the records); ``inf`` where any of them is
    not valid."""
    M = n_samples // F
    j = np.arange(n_samples // 2 + 1)
    k = j % M
    slow = np.where(k > M // 2, M - k, k)  # the slow bin of each fast bin
    n_half = M // 2 + 1
    counts = np.bincount(slow, minlength=n_half)
    out = np.empty((len(estimators), n_half))
    # the logs of std / 2**e, e the binary exponent of the largest valid std
    # of all fits: the scores, and so the weights, are then the same bit for
    # bit at any scale of the records (a log of the std itself shifts every
    # score by a constant, which rounds their differences differently)
    peak = 0.0
    for est in estimators:
        std = np.asarray(est.frf_std_, dtype=float)
        good = np.asarray(est.valid_) & np.isfinite(std)
        if good.any():
            peak = max(peak, float(np.max(std[good])))
    exponent = int(np.frexp(peak)[1]) if peak > 0.0 else 0
    for c, est in enumerate(estimators):
        std = np.asarray(est.frf_std_, dtype=float)
        good = np.asarray(est.valid_) & np.isfinite(std) & (std > 0)
        std = scale_by_power_of_two(std, -exponent)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_std = np.where(good, np.log(np.where(good, std, 1.0)), np.inf)
        log_std = log_std.reshape(-1, log_std.shape[-1]).mean(axis=0)  # entries
        total = np.bincount(slow, weights=np.where(np.isfinite(log_std), log_std,
                                                   0.0), minlength=n_half)
        bad = np.bincount(slow, weights=~np.isfinite(log_std), minlength=n_half)
        out[c] = np.where(bad > 0, np.inf, total / np.maximum(counts, 1))
    return out


def smooth_scores(scores: np.ndarray, half_width: int, n_slow: int) -> np.ndarray:
    """Mean of each row over ``2 half_width + 1`` neighbouring slow bins.

    The slow bins ``0..M//2`` (``M = n_slow``) of a real record continue by
    symmetry (DFT bin ``b`` is bin ``b mod M``, and bin ``k > M//2`` is
    ``M - k``), so a neighbourhood past either end reads the mirrored bins;
    an ``inf`` (a fit not valid there) spreads to every bin whose
    neighbourhood contains it.
    """
    h = int(half_width)
    n_half = scores.shape[-1]
    if h <= 0:
        return scores.copy()
    index = np.arange(-h, n_half + h) % n_slow
    index = np.where(index > n_slow // 2, n_slow - index, index)
    padded = scores[:, index]
    finite = np.isfinite(padded)
    kernel = np.ones(2 * h + 1)
    sums = np.stack([np.convolve(np.where(f, row, 0.0), kernel, mode="valid")
                     for row, f in zip(padded, finite, strict=True)])
    bad = np.stack([np.convolve((~f).astype(float), kernel, mode="valid")
                    for f in finite])
    return np.where(bad > 0, np.inf, sums / kernel.size)


def score_weights(scores: np.ndarray, sharpness: float,
                  floor: float = 1e-6) -> np.ndarray:
    """Weights ``(C, M//2+1)``: ``exp(-sharpness (s - min_c s))`` per slow
    bin, those below ``floor`` set to 0, normalised to sum to 1; NaN in the
    columns where no score is finite (no fit is valid there)."""
    best = np.min(scores, axis=0)
    finite = np.isfinite(best)
    with np.errstate(invalid="ignore"):
        weights = np.exp(-sharpness * (scores - np.where(finite, best, 0.0)))
    weights = np.where(np.isfinite(scores) & (weights >= floor), weights, 0.0)
    weights = weights / np.where(finite, weights.sum(axis=0), 1.0)
    weights[:, ~finite] = np.nan
    return weights


def blend(estimators, weights: np.ndarray, n_samples: int, F: int) -> dict:
    """FRF, std, covariance and validity of the regions' fits, blended.

    ``std`` is blended like the FRF (``w_a s_a + w_b s_b``: the two estimates
    come from the same data and are treated as fully correlated, an upper
    bound). The covariance within an output row is the blend ``sum_a w_a
    C_a`` rescaled to that std (its correlations kept), so ``frf_std_ ==
    sqrt(diag(frf_cov_))`` holds in the ramps too. A fast bin is valid when
    every fit with weight there is (and its weights are finite: NaN weights
    mark a slow bin no fit identifies).
    """
    fast_w = np.stack([to_fast_grid(w, n_samples, F) for w in weights])  # (R, K)
    frf = np.zeros_like(estimators[0].frf_)
    std = np.zeros_like(estimators[0].frf_std_)
    cov = np.zeros_like(estimators[0].frf_cov_)
    valid = np.ones_like(estimators[0].valid_) & np.all(np.isfinite(fast_w), axis=0)
    noise = np.zeros_like(estimators[0].noise_variance_)
    for est, w, w_slow in zip(estimators, fast_w, weights, strict=True):
        used = w > 0
        valid &= ~used | est.valid_
        # (0 * inf where a weight is 0 and a variance beyond the float range,
        # e.g. records at 2**600: dropped by the where)
        with np.errstate(invalid="ignore"):
            frf = frf + np.where(used, w * est.frf_, 0.0)
            std = std + np.where(used, w * est.frf_std_, 0.0)
            cov = cov + np.where(used, w * est.frf_cov_, 0.0)
            noise = noise + np.where(w_slow > 0, w_slow * est.noise_variance_,
                                     0.0)
    frf = np.where(valid, frf, np.nan)
    std = np.where(valid, std, np.nan)
    noise = np.where(np.all(np.isfinite(weights), axis=0), noise, np.nan)
    # (n_y, n_u, n_u, K): scale entry (i, j) by std_i std_j / sqrt(C_ii C_jj)
    std_rows = std.reshape(cov.shape[0], cov.shape[1], -1)
    diag = np.real(np.diagonal(cov, axis1=1, axis2=2))  # (n_y, K, n_u)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = std_rows / np.sqrt(np.moveaxis(diag, -1, 1))  # (n_y, n_u, K)
    cov = cov * scale[:, :, None, :] * scale[:, None, :, :]
    return {"frf_": frf, "frf_std_": std, "frf_cov_": cov, "valid_": valid,
            "noise_variance_": noise}
