"""Spectral analysis (H1, Hann-windowed segments) of zero-stuffed slow data."""

from __future__ import annotations

import warnings
from functools import partial

import numpy as np
from scipy.signal import get_window

from .._validation import check_nonnegative_int, check_records, check_sample_time
from ..local_models import scale_by_power_of_two
from ._base import _BaseFRFEstimator, _normalise_in_place

__all__ = ["SpectralAnalysis", "zero_stuff"]

#: A segment-grid bin whose averaged input power is below this fraction of the
#: average over all bins counts as not excited (round-off or window leakage of
#: a zero), as :data:`lrmfrf.local_models.EXCITATION_TOL` for the local models.
EXCITATION_TOL = 1e-12


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


def _check_window(window, name: str):
    """A window specification accepted by ``scipy.signal.get_window``."""
    try:
        get_window(window, 8)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"`{name}` must be a window accepted by scipy.signal.get_window. Got "
            f"{window!r} instead ({exc}). Use e.g. 'hann' (the paper's) or "
            "('tukey', 0.25)."
        ) from exc
    return window


class SpectralAnalysis(_BaseFRFEstimator):
    """The paper's spectral-analysis baseline, eq. (hann).

    Zero-stuffs ``y_l`` to the fast rate (times ``F``) and averages
    Hann-windowed segments into the H1 estimate
    ``G = sum_i Y_i conj(U_i) / sum_i |U_i|^2`` on the segment grid
    ``p / (L T_s)``, ``p = 0..L//2``.

    Parameters
    ----------
    segment_length : int, default=200
        Samples per segment ``L`` (at the fast rate).
    overlap : int, default=100
        Samples shared by consecutive segments, ``0 <= overlap < L``.
    window : str or tuple, default="hann"
        Any window accepted by ``scipy.signal.get_window`` (periodic).

    Attributes
    ----------
    frequencies_ : ndarray of shape (L//2+1,)
        Segment grid ``p / (L T_s)`` in Hz (coarser than the fast DFT grid by
        ``N/L``); in cycles per sample (``p / L``) when ``fit`` got no
        ``sample_time`` (default 1.0).
    frf_ : ndarray of shape (L//2+1,), complex
        H1 estimate (units of ``y_l`` per unit of ``u_h``); NaN where the input
        has no energy.
    frf_std_ : ndarray of shape (L//2+1,)
        Standard deviation of the complex estimate, ``sqrt(E|G_hat - G|^2)``,
        from the coherence: ``|G| sqrt((1 - coh) / (n_avg coh))`` (Bendat and
        Piersol's random error, whose magnitude and phase parts each carry
        half of it), ignoring the correlation between overlapping segments.
        It is evaluated as ``sqrt((S_yy - |S_yu|^2 / S_uu) / (n_avg S_uu))``,
        the same quantity, which is also defined where the output is zero (a
        std of 0). It measures noise only, not the aliasing bias above the slow
        Nyquist frequency. With a single segment (``n_segments_ == 1``) the
        coherence is 1 by construction and says nothing about the noise:
        ``frf_std_`` is then NaN everywhere (with a warning), while ``frf_``
        and ``valid_`` are as usual.
    coherence_ : ndarray of shape (L//2+1,)
        Magnitude-squared coherence of ``u_h`` and the zero-stuffed output.
    valid_ : ndarray of shape (L//2+1,), bool
        False where the input has no energy: its averaged power is below
        ``1e-12`` of the average over all bins (round-off or window leakage of
        a zero; e.g. all bins but the first two for a constant input).
        ``frf_`` is NaN there.
    n_segments_ : int
        Segments averaged (over all experiments).
    n_samples_, n_slow_, n_experiments_, downsampling_factor_ : int
        ``N``, ``M``, ``P`` and ``F`` of the training records.
    sample_time_ : float
        Fast sample time in seconds.

    Notes
    -----
    The records are normalised by powers of two as in
    :meth:`LRMBeyondNyquist.fit` (any finite scale gives the same FRF).
    Zero stuffing assumes ``Y_h(k + iM) = F Y_l(k)``: above the slow Nyquist
    frequency this estimate is aliased and biased even without noise.
    ``predict`` interpolates ``frf_`` linearly onto the fast DFT grid.

    Examples
    --------
    >>> import numpy as np
    >>> from lrmfrf import SpectralAnalysis
    >>> from lrmfrf.signals import multisine
    >>> u = multisine(1200, bins=np.arange(1, 200), rng=0)  # below 1/(6 T_s)
    >>> sa = SpectralAnalysis().fit(u, 2.5 * u[::3], F=3, sample_time=0.5e-3)
    >>> sa.n_segments_, float(sa.frequencies_[1])
    (11, 10.0)
    >>> bool(np.allclose(sa.frf_[2:25], 2.5, rtol=1e-3))  # 20-240 Hz
    True
    """

    _parameter_checks = {
        "segment_length": partial(check_nonnegative_int, minimum=2),
        "overlap": check_nonnegative_int,
        "window": _check_window,
    }

    def __init__(self, *, segment_length: int = 200, overlap: int = 100, window="hann"):
        self.segment_length = segment_length
        self.overlap = overlap
        self.window = window

    def _check_params(self) -> tuple[int, int]:
        """Segment length and overlap, checked (before the data)."""
        params = self._checked_params()
        L, overlap = params["segment_length"], params["overlap"]
        if overlap >= L:
            raise ValueError(
                f"`overlap` must be less than `segment_length`. Got overlap="
                f"{overlap} and segment_length={L} instead. Reduce the overlap "
                "(half the segment is usual)."
            )
        return L, overlap

    def fit(self, u_h, y_l, F, *, sample_time: float = 1.0):
        """Estimate the FRF by averaged, windowed segments.

        Parameters
        ----------
        u_h : array-like of shape (N,) or (P, N), or list of P records
            Fast-rate input(s), real.
        y_l : array-like of shape (M,) or (P, M), or list of P records
            Slow-rate output(s), real, ``y_l(m) = y_h(m F) + noise``.
        F : int
            Downsampling factor, ``N = F M``.
        sample_time : float, default=1.0
            Fast sample time in seconds. With the default 1.0, time is counted
            in samples and ``frequencies_`` are in cycles per (fast) sample.

        Returns
        -------
        self
            The fitted estimator.

        Warns
        -----
        UserWarning
            With one segment in all (``segment_length`` close to the record
            length): ``frf_std_`` is NaN.
        """
        L, overlap = self._check_params()
        u, y, F = check_records(u_h, y_l, F)
        sample_time = check_sample_time(sample_time)
        P, N = u.shape
        if L > N:
            raise ValueError(
                f"`segment_length` exceeds the record length. Got segment_length="
                f"{L} and N={N} samples instead. Use shorter segments."
            )
        step = L - overlap
        starts = np.arange(0, N - L + 1, step)
        taper = get_window(self.window, L)
        # The FRF is a ratio: normalise by powers of two (exact; none for
        # ordinary data) and undo it on frf_ and frf_std_.
        u_exponent = _normalise_in_place(u)
        y_exponent = _normalise_in_place(y)
        y_fast = zero_stuff(y, F)
        idx = starts[:, None] + np.arange(L)
        Useg = np.fft.rfft(u[:, idx] * taper, axis=-1)  # (P, S, L//2+1)
        Yseg = np.fft.rfft(y_fast[:, idx] * taper, axis=-1)
        Suu = np.sum(np.abs(Useg) ** 2, axis=(0, 1))
        Syy = np.sum(np.abs(Yseg) ** 2, axis=(0, 1))
        Syu = np.sum(Yseg * np.conj(Useg), axis=(0, 1))
        valid = Suu > EXCITATION_TOL * Suu.mean()
        n_avg = P * starts.size
        with np.errstate(invalid="ignore", divide="ignore"):
            frf = np.where(valid, Syu / Suu, np.nan)
            coherence = np.where(valid & (Syy > 0), np.abs(Syu) ** 2 / (Suu * Syy), 0)
            # |G|^2 (1 - coh) / (n coh) without dividing by coh (or S_yy)
            residual_power = np.maximum(Syy - np.abs(Syu) ** 2 / Suu, 0.0)
            std = np.sqrt(residual_power / (n_avg * Suu))
        if n_avg == 1:
            warnings.warn(
                f"SpectralAnalysis averaged a single segment (segment_length={L}, "
                f"N={N}): its coherence is 1 by construction, so frf_std_ has no "
                "basis and is NaN. Use segments shorter than half the record "
                "(e.g. segment_length=N//8, overlap=segment_length//2) for a std.",
                UserWarning,
                stacklevel=2,
            )
            std = np.full_like(std, np.nan)
        system_exponent = y_exponent - u_exponent
        self.n_samples_ = N
        self.n_slow_ = N // F
        self.n_experiments_ = P
        self.downsampling_factor_ = F
        self.sample_time_ = sample_time
        self.n_segments_ = n_avg
        self.frequencies_ = np.arange(L // 2 + 1) / (L * sample_time)
        self.frf_ = scale_by_power_of_two(frf, system_exponent)
        self.frf_std_ = scale_by_power_of_two(
            np.where(valid, std, np.nan), system_exponent
        )
        self.coherence_ = coherence
        self.valid_ = valid
        return self

    def _fast_frf(self, n_samples: int) -> np.ndarray:
        """Linear interpolation of the segment-grid FRF onto the fast grid."""
        f_fast = np.arange(n_samples // 2 + 1) / (n_samples * self.sample_time_)
        keep = self.valid_
        if not keep.any():
            raise ValueError(
                "The spectral-analysis FRF has no valid bin (`valid_` is False "
                "everywhere: the training input had no energy), so there is "
                "nothing to predict with. Refit with an input that excites the "
                "band of interest, e.g. lrmfrf.signals.multisine."
            )
        half = np.interp(f_fast, self.frequencies_[keep], self.frf_[keep].real) + 1j * (
            np.interp(f_fast, self.frequencies_[keep], self.frf_[keep].imag)
        )
        mirror = np.conj(half[1 : n_samples - n_samples // 2][::-1])
        return np.concatenate([half, mirror])
