"""Per-region choice of the local-model setting (``LRMBeyondNyquistCV(per_band=True)``).

The slow bins ``0..M//2`` (window centres) are cut into contiguous regions;
each region gets the candidate whose criterion, summed over the region's
windows, is lowest, and the FRFs of neighbouring regions are blended linearly
over a ramp around each edge, so the estimate is continuous there. A slow bin
``k`` fixes the ``F`` aliased fast bins ``k + fM`` at once (one local problem),
so a region of slow bins covers every fast frequency that aliases onto it.
"""

from __future__ import annotations

import numbers

import numpy as np

from ..local_models import one_sided_fast_grid


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


def blend(estimators, weights: np.ndarray, n_samples: int, F: int) -> dict:
    """FRF, std, covariance and validity of the regions' fits, blended.

    ``std`` is blended like the FRF (``w_a s_a + w_b s_b``: the two estimates
    come from the same data and are treated as fully correlated, an upper
    bound). The covariance within an output row is the blend ``sum_a w_a
    C_a`` rescaled to that std (its correlations kept), so ``frf_std_ ==
    sqrt(diag(frf_cov_))`` holds in the ramps too. A fast bin is valid when
    every fit with weight there is.
    """
    fast_w = np.stack([to_fast_grid(w, n_samples, F) for w in weights])  # (R, K)
    frf = np.zeros_like(estimators[0].frf_)
    std = np.zeros_like(estimators[0].frf_std_)
    cov = np.zeros_like(estimators[0].frf_cov_)
    valid = np.ones_like(estimators[0].valid_)
    noise = np.zeros_like(estimators[0].noise_variance_)
    for est, w, w_slow in zip(estimators, fast_w, weights, strict=True):
        used = w > 0
        valid &= ~used | est.valid_
        frf = frf + np.where(used, w * est.frf_, 0.0)
        std = std + np.where(used, w * est.frf_std_, 0.0)
        cov = cov + np.where(used, w * est.frf_cov_, 0.0)
        noise = noise + np.where(w_slow > 0, w_slow * est.noise_variance_, 0.0)
    frf = np.where(valid, frf, np.nan)
    std = np.where(valid, std, np.nan)
    # (n_y, n_u, n_u, K): scale entry (i, j) by std_i std_j / sqrt(C_ii C_jj)
    std_rows = std.reshape(cov.shape[0], cov.shape[1], -1)
    diag = np.real(np.diagonal(cov, axis1=1, axis2=2))  # (n_y, K, n_u)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = std_rows / np.sqrt(np.moveaxis(diag, -1, 1))  # (n_y, n_u, K)
    cov = cov * scale[:, :, None, :] * scale[:, None, :, :]
    return {"frf_": frf, "frf_std_": std, "frf_cov_": cov, "valid_": valid,
            "noise_variance_": noise}
