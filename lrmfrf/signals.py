"""Excitation signals."""

from __future__ import annotations

import numpy as np

from ._validation import check_nonnegative_int

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
        Excited DFT bins in ``1..N//2``. Default: all of them (no DC), the
        paper's "all frequencies" excitation. The Nyquist bin, if excited, gets
        a random sign (its phase can only be 0 or pi).
    rng : int, numpy.random.Generator or None
        Seed or generator for the random phases.

    Returns
    -------
    ndarray of shape (n_samples,)

    Examples
    --------
    >>> from lrmfrf.signals import multisine
    >>> u = multisine(1200, rms=1.44, rng=0)
    >>> round(float(u.std()), 6)
    1.44
    """
    N = check_nonnegative_int(n_samples, "n_samples", minimum=2)
    if not np.isfinite(rms) or rms <= 0:
        raise ValueError(f"`rms` must be a positive number. Got {rms!r}.")
    rng = np.random.default_rng(rng)
    if bins is None:
        bins = np.arange(1, N // 2 + 1)
    bins = np.unique(np.asarray(bins, dtype=int))
    if bins.size == 0 or bins.min() < 1 or bins.max() > N // 2:
        raise ValueError(
            f"`bins` must be non-empty DFT bins in 1..N//2 = 1..{N // 2}. "
            "DC and bins above N//2 (their mirror images) cannot be set."
        )
    spectrum = np.zeros(N // 2 + 1, dtype=complex)
    spectrum[bins] = np.exp(2j * np.pi * rng.random(bins.size))
    if N % 2 == 0 and bins[-1] == N // 2:
        spectrum[N // 2] = rng.choice([-1.0, 1.0])
    u = np.fft.irfft(spectrum, n=N)
    return u * (rms / np.sqrt(np.mean(u**2)))
