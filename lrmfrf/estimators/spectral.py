"""Spectral analysis (H1, Hann-windowed segments) of zero-stuffed slow data."""

from __future__ import annotations

import numpy as np
from scipy.signal import get_window

from .._validation import check_nonnegative_int, check_records, check_sample_time
from ._base import _BaseFRFEstimator

__all__ = ["SpectralAnalysis", "zero_stuff"]


def zero_stuff(y_l: np.ndarray, F: int) -> np.ndarray:
    """Interpolate slow records with zeros to the fast rate, times ``F``.

    ``[y(0), 0, .., 0, y(1), ..]`` has DFT ``Y_l(k mod M)`` without the ``1/F``
    of eq. (FDomainSlowSampledOutput1), so the factor ``F`` makes it an
    estimate of the fast output's DFT below the slow Nyquist frequency.

    Parameters
    ----------
    y_l : ndarray of shape (P, M)
    F : int

    Returns
    -------
    ndarray of shape (P, F*M)
    """
    P, M = y_l.shape
    out = np.zeros((P, F * M))
    out[:, ::F] = F * y_l
    return out


class SpectralAnalysis(_BaseFRFEstimator):
    """The paper's spectral-analysis baseline, eq. (hann).

    Zero-stuffs ``y_l`` to the fast rate (times ``F``) and averages
    Hann-windowed segments into the H1 estimate
    ``G = sum_i Y_i conj(U_i) / sum_i |U_i|^2`` on the segment grid
    ``p / (L T_s)``, ``p = 0..L//2``.

    Parameters
    ----------
    segment_length : int, default=200
        Samples per segment ``L``.
    overlap : int, default=100
        Samples shared by consecutive segments.
    window : str or tuple, default="hann"
        Any window accepted by ``scipy.signal.get_window`` (periodic).

    Attributes
    ----------
    frequencies_ : ndarray of shape (L//2+1,)
        Segment grid in Hz (coarser than the fast DFT grid by ``N/L``).
    frf_ : ndarray of shape (L//2+1,), complex
    frf_std_ : ndarray of shape (L//2+1,)
        Std from the coherence, ``|G| sqrt((1 - coh) / (2 n_avg coh))`` per
        real and imaginary part combined (Bendat and Piersol), ignoring the
        correlation between overlapping segments.
    coherence_ : ndarray of shape (L//2+1,)
    valid_ : ndarray of shape (L//2+1,), bool
    n_segments_ : int
        Segments averaged (over all experiments).

    Notes
    -----
    Zero stuffing assumes ``Y_h(k + iM) = F Y_l(k)``: above the slow Nyquist
    frequency this estimate is aliased and biased even without noise.
    """

    def __init__(self, *, segment_length: int = 200, overlap: int = 100, window="hann"):
        self.segment_length = segment_length
        self.overlap = overlap
        self.window = window

    def _check_params(self, n_samples: int) -> tuple[int, int]:
        L = check_nonnegative_int(self.segment_length, "segment_length", minimum=2)
        overlap = check_nonnegative_int(self.overlap, "overlap")
        if overlap >= L:
            raise ValueError(
                f"overlap={overlap} must be less than segment_length={L}. "
                "Reduce the overlap (half the segment is usual)."
            )
        if L > n_samples:
            raise ValueError(
                f"segment_length={L} exceeds the record length N={n_samples}. "
                "Use shorter segments."
            )
        return L, overlap

    def fit(self, u_h, y_l, F, *, sample_time: float = 1.0):
        """Estimate the FRF by averaged, windowed segments.

        Parameters
        ----------
        u_h : array-like of shape (N,) or (P, N), or list of P records
        y_l : array-like of shape (M,) or (P, M), or list of P records
        F : int
        sample_time : float, default=1.0
            Fast sample time in seconds.

        Returns
        -------
        self
        """
        u, y, F = check_records(u_h, y_l, F)
        sample_time = check_sample_time(sample_time)
        P, N = u.shape
        L, overlap = self._check_params(N)
        step = L - overlap
        starts = np.arange(0, N - L + 1, step)
        taper = get_window(self.window, L)
        y_fast = zero_stuff(y, F)
        idx = starts[:, None] + np.arange(L)
        Useg = np.fft.rfft(u[:, idx] * taper, axis=-1)  # (P, S, L//2+1)
        Yseg = np.fft.rfft(y_fast[:, idx] * taper, axis=-1)
        Suu = np.sum(np.abs(Useg) ** 2, axis=(0, 1))
        Syy = np.sum(np.abs(Yseg) ** 2, axis=(0, 1))
        Syu = np.sum(Yseg * np.conj(Useg), axis=(0, 1))
        valid = Suu > 0
        n_avg = P * starts.size
        with np.errstate(invalid="ignore", divide="ignore"):
            frf = np.where(valid, Syu / Suu, np.nan)
            coherence = np.where(valid & (Syy > 0), np.abs(Syu) ** 2 / (Suu * Syy), 0)
            std = np.abs(frf) * np.sqrt((1 - coherence) / (2 * n_avg * coherence))
        self.n_samples_ = N
        self.n_slow_ = N // F
        self.n_experiments_ = P
        self.downsampling_factor_ = F
        self.sample_time_ = sample_time
        self.n_segments_ = n_avg
        self.frequencies_ = np.arange(L // 2 + 1) / (L * sample_time)
        self.frf_ = frf
        self.frf_std_ = np.where(valid, std, np.nan)
        self.coherence_ = coherence
        self.valid_ = valid
        return self

    def _fast_frf(self, n_samples: int) -> np.ndarray:
        """Linear interpolation of the segment-grid FRF onto the fast grid."""
        f_fast = np.arange(n_samples // 2 + 1) / (n_samples * self.sample_time_)
        keep = self.valid_
        half = np.interp(f_fast, self.frequencies_[keep], self.frf_[keep].real) + 1j * (
            np.interp(f_fast, self.frequencies_[keep], self.frf_[keep].imag)
        )
        mirror = np.conj(half[1 : n_samples - n_samples // 2][::-1])
        return np.concatenate([half, mirror])
