"""Excitation signals."""

from __future__ import annotations

import numpy as np

from ._validation import check_nonnegative_int, check_positive_float

__all__ = ["multisine"]


def multisine(
    n_samples: int,
    *,
    rms: float = 1.0,
    bins=None,
    rng: int | np.random.Generator | None = None,
) -> np.ndarray:
    """Random-phase multisine with a flat amplitude spectrum (one period).

    Parameters
    ----------
    n_samples : int
        Period ``N`` in samples.
    rms : float, default=1.0
        Root-mean-square value of the signal.
    bins : array-like of int, optional
        Excited DFT bins in ``1..N//2`` (bin ``k`` is the frequency
        ``k / (N T_s)``). Default: all of them (no DC), the paper's "all
        frequencies" excitation. Repeated bins count once. The Nyquist bin, if
        excited, gets a random sign (its phase can only be 0 or pi).
    rng : int, numpy.random.Generator or None
        Seed or generator for the random phases.

    Returns
    -------
    ndarray of shape (n_samples,)
        One period; every excited bin has the same DFT magnitude.

    Raises
    ------
    TypeError, ValueError
        For ``n_samples < 2``, a non-positive ``rms``, or ``bins`` that are not
        whole numbers in ``1..N//2``.

    Examples
    --------
    >>> from lrmfrf.signals import multisine
    >>> u = multisine(1200, rms=1.44, rng=0)
    >>> round(float(u.std()), 6)
    1.44
    """
    N = check_nonnegative_int(n_samples, "n_samples", minimum=2)
    rms = check_positive_float(rms, "rms", allow_none=False)
    bins = np.arange(1, N // 2 + 1) if bins is None else _check_bins(bins, N)
    rng = np.random.default_rng(rng)
    spectrum = np.zeros(N // 2 + 1, dtype=complex)
    spectrum[bins] = np.exp(2j * np.pi * rng.random(bins.size))
    if N % 2 == 0 and bins[-1] == N // 2:
        spectrum[N // 2] = rng.choice([-1.0, 1.0])
    u = np.fft.irfft(spectrum, n=N)
    return u * (rms / np.sqrt(np.mean(u**2)))


def _check_bins(bins, n_samples: int) -> np.ndarray:
    """Sorted unique excited bins, whole numbers in ``1..N//2``."""
    top = n_samples // 2
    values = np.asarray(bins)
    if values.ndim != 1 or values.size == 0:
        raise ValueError(
            f"`bins` must be a non-empty 1-D sequence of DFT bins in 1..N//2 = "
            f"1..{top}. Got shape {values.shape} instead. Pass e.g. "
            f"bins=range(1, {top + 1}) (all of them)."
        )
    if not (
        np.issubdtype(values.dtype, np.integer)
        or (
            np.issubdtype(values.dtype, np.floating)
            and np.all(np.isfinite(values))
            and np.all(values == np.round(values))
        )
    ):
        raise TypeError(
            f"`bins` must hold whole numbers (DFT bin indices). Got dtype "
            f"{values.dtype} with values such as {values[:3].tolist()} instead. "
            "Round frequencies to bins first: k = round(f * N * sample_time)."
        )
    values = np.unique(values.astype(int))
    if values[0] < 1 or values[-1] > top:
        raise ValueError(
            f"`bins` must be DFT bins in 1..N//2 = 1..{top}. Got bins from "
            f"{values[0]} to {values[-1]} instead. DC and bins above N//2 (their "
            "mirror images) cannot be set."
        )
    return values
