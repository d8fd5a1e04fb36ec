"""Spectral analysis (H1, Hann-windowed segments) of zero-stuffed slow data."""

from __future__ import annotations

import warnings
from functools import partial

import numpy as np
from scipy.signal import get_window

from .._validation import check_nonnegative_int, check_records, check_sample_time
from ..exceptions import IdentifiabilityWarning
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
    y_l : ndarray of shape (..., M)
    F : int

    Returns
    -------
    ndarray of shape (..., F*M)
    """
    M = y_l.shape[-1]
    out = np.zeros(y_l.shape[:-1] + (F * M,))
    out[..., ::F] = F * y_l
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
    frf_ : ndarray of shape (L//2+1,) or (n_y, n_u, L//2+1), complex
        H1 estimate ``S_yu S_uu^-1`` from the cross-spectral matrices summed
        over segments and experiments (units of ``y_l`` per unit of ``u_h``);
        NaN where the input has no energy. (L//2+1,) when ``n_u = n_y = 1``.
    frf_std_ : ndarray of shape (L//2+1,) or (n_y, n_u, L//2+1)
        Standard deviation of the complex estimate, ``sqrt(E|G_hat - G|^2)``,
        from the coherence: ``|G| sqrt((1 - coh) / (n_avg coh))`` (Bendat and
        Piersol's random error, whose magnitude and phase parts each carry
        half of it), ignoring the correlation between overlapping segments.
        It is evaluated as ``sqrt((S_yy - |S_yu|^2 / S_uu) / (n_avg S_uu))``,
        the same quantity, which is also defined where the output is zero (a
        std of 0). It is not the aliasing bias above the slow Nyquist
        frequency, but the coherence counts the aliased images in the
        zero-stuffed output as noise: with a fixed broadband input (e.g. one
        multisine record, noise 0.3x the output std) it was 1.6x the
        Monte-Carlo std over noise realisations below the slow Nyquist
        frequency and 3.2x above (SISO, 200 runs; 2.3-2.4x below on a 2x2
        system), and 0.94-0.98x when the input, too, is drawn anew in every
        run (or lies below the slow Nyquist frequency;
        ``benchmarks/spectral_std_aliasing.py``). With a single segment
        (``n_segments_ == 1``) the coherence is 1 by construction and says
        nothing about the noise:
        ``frf_std_`` is then NaN everywhere (with a warning), while ``frf_``
        and ``valid_`` are as usual. MIMO: the multivariate form of the same
        formula (Bendat and Piersol, multiple-input H1; Pintelon and
        Schoukens), ``var H_oi = [S_uu^-1]_ii (S_yy,o - S_yu,o S_uu^-1
        S_uy,o) / n_avg`` per output row ``o`` (``n_avg`` as in SISO, not
        ``n_avg - n_u``).
    coherence_ : ndarray of shape (L//2+1,) or (n_y, L//2+1)
        Magnitude-squared coherence of ``u_h`` and the zero-stuffed output;
        MIMO: the multiple coherence of each output with all inputs.
    valid_ : ndarray of shape (L//2+1,) or (n_y, n_u, L//2+1), bool
        False where the input has no energy: the smallest eigenvalue of the
        summed ``S_uu`` (SISO: ``S_uu``) is below ``1e-12`` of the average
        input power over all bins (round-off or window leakage of a zero;
        e.g. all bins but the first two for a constant input; MIMO: also
        inputs that are linearly dependent at that bin, e.g. one a multiple
        of another, with an ``IdentifiabilityWarning``; fewer segments than
        inputs are refused). ``frf_`` is NaN there.
    n_inputs_, n_outputs_ : int
        ``n_u`` and ``n_y``.
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
    ``predict`` interpolates ``frf_`` linearly onto the fast DFT grid; a fast
    bin next to an invalid segment bin is invalid (an input that excites it
    is refused).

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
        u_h : array-like of shape (N,), (n_u, N) or (P, n_u, N), or list
            Fast-rate input(s), real: one record (1-D, or 2-D channels first)
            or ``P`` experiments (3-D, or a list of records).
        y_l : array-like of shape (M,), (n_y, M) or (P, n_y, M), or list
            Slow-rate output(s) likewise, ``y_l(m) = y_h(m F) + noise``.
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
        records = check_records(u_h, y_l, F)
        F = records.F
        sample_time = check_sample_time(sample_time)
        u, y = records.u, records.y  # (P, n_u, N), (P, n_y, M): new arrays
        P, n_u, N = u.shape
        n_y = y.shape[1]
        if L > N:
            raise ValueError(
                f"`segment_length` exceeds the record length. Got segment_length="
                f"{L} and N={N} samples instead. Use shorter segments."
            )
        step = L - overlap
        starts = np.arange(0, N - L + 1, step)
        n_avg = P * starts.size
        if n_avg < n_u:
            raise ValueError(
                f"H1 with {n_u} inputs needs at least {n_u} segments in all to "
                f"invert the input cross-spectral matrix; got {n_avg} (P={P} "
                f"experiment(s) of {starts.size} segment(s)). Use shorter "
                "segments (segment_length) or more experiments." + records.hint()
            )
        taper = get_window(self.window, L)
        # The FRF is a ratio: normalise by powers of two (exact; none for
        # ordinary data) and undo it on frf_ and frf_std_.
        u_exponent = _normalise_in_place(u)
        y_exponent = _normalise_in_place(y)
        y_fast = zero_stuff(y, F)
        idx = starts[:, None] + np.arange(L)
        Useg = np.fft.rfft(u[:, :, idx] * taper, axis=-1)  # (P, n_u, S, L//2+1)
        Yseg = np.fft.rfft(y_fast[:, :, idx] * taper, axis=-1)
        # cross-spectral sums over segments and experiments, bin first
        Suu = np.einsum("pisk,pjsk->kij", Useg, np.conj(Useg))
        Syu = np.einsum("pisk,pjsk->kij", Yseg, np.conj(Useg))
        Syy = np.sum(np.abs(Yseg) ** 2, axis=(0, 2)).T  # (K, n_y)
        # a bin is valid where the smallest eigenvalue of S_uu is not
        # negligible against the average input power (n_u = 1: S_uu itself)
        power = np.real(np.trace(Suu, axis1=1, axis2=2)) / n_u
        smallest = np.linalg.eigvalsh(Suu)[:, 0] if n_u > 1 else power
        valid = smallest > EXCITATION_TOL * power.mean()
        dependent = ~valid & (power > EXCITATION_TOL * power.mean())
        if n_u > 1 and dependent.any():
            warnings.warn(
                f"At {int(dependent.sum())} of {valid.size} bins the input "
                f"cross-spectral matrix of the {n_u} inputs is singular although "
                "they have power there (an input without power, or inputs that "
                "are linearly dependent, e.g. one a multiple of another): H1 "
                "cannot separate them, so frf_ is NaN and valid_ is False. "
                "Excite the inputs independently (lrmfrf.signals."
                "orthogonal_multisines) or add experiments with other inputs.",
                IdentifiabilityWarning,
                stacklevel=2,
            )
        safe = np.where(valid[:, None, None], Suu, np.eye(n_u))
        Suu_inv = np.linalg.inv(safe)
        with np.errstate(invalid="ignore", divide="ignore"):
            frf = Syu @ Suu_inv  # (K, n_y, n_u): H1 = S_yu S_uu^-1
            # noise power per output: S_yy - S_yu S_uu^-1 S_uy, >= 0
            explained = np.real(np.einsum("koi,koi->ko", frf, np.conj(Syu)))
            residual_power = np.maximum(Syy - explained, 0.0)
            coherence = np.where(
                valid[:, None] & (Syy > 0), explained / np.where(Syy > 0, Syy, 1), 0
            )
            inv_diag = np.real(np.diagonal(Suu_inv, axis1=1, axis2=2))  # (K, n_u)
            # var H1_oi = sigma_o^2 [S_uu^-1]_ii, sigma_o^2 = residual_o / n_avg
            std = np.sqrt(residual_power[:, :, None] * inv_diag[:, None, :] / n_avg)
        frf = np.where(valid[:, None, None], frf, np.nan)
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
        std = np.where(valid[:, None, None], std, np.nan)
        system_exponent = y_exponent - u_exponent
        siso = n_u == 1 and n_y == 1
        # to (n_y, n_u, K), or (K,) for SISO
        frf = np.moveaxis(frf, 0, -1)
        std = np.moveaxis(std, 0, -1)
        coherence = coherence.T
        valid_all = np.broadcast_to(valid, (n_y, n_u, valid.size)).copy()
        self.n_samples_ = N
        self.n_slow_ = N // F
        self.n_experiments_ = P
        self.n_inputs_ = n_u
        self.n_outputs_ = n_y
        self.downsampling_factor_ = F
        self.sample_time_ = sample_time
        self.n_segments_ = n_avg
        self.frequencies_ = np.arange(L // 2 + 1) / (L * sample_time)
        self.frf_ = scale_by_power_of_two(frf[0, 0] if siso else frf, system_exponent)
        self.frf_std_ = scale_by_power_of_two(
            std[0, 0] if siso else std, system_exponent
        )
        self.coherence_ = coherence[0] if siso else coherence
        self.valid_ = valid if siso else valid_all
        return self

    def _fast_frf(self, n_samples: int) -> np.ndarray:
        """Linear interpolation of the segment-grid FRF onto the fast grid.

        A fast bin between two segment bins (or on one) of which one is
        invalid is NaN: ``predict`` then refuses an input that excites it, as
        for the local models (the interpolation used to bridge invalid bins,
        or extend the last valid one to the fast Nyquist frequency, silently).
        """
        f_fast = np.arange(n_samples // 2 + 1) / (n_samples * self.sample_time_)
        keep = np.asarray(self.valid_)
        keep = keep if keep.ndim == 1 else keep.all(axis=(0, 1))
        if not keep.any():
            dependent = (
                " or the inputs were linearly dependent at every bin, e.g. one a "
                "multiple of another" if self._n_channels()[1] > 1 else ""
            )
            raise ValueError(
                "The spectral-analysis FRF has no valid bin (`valid_` is False "
                f"everywhere: the training input had no energy{dependent}), so "
                "there is nothing to predict with. Refit with an input that "
                "excites the band of interest, e.g. lrmfrf.signals.multisine"
                + (" (independent inputs: lrmfrf.signals.orthogonal_multisines)"
                   if dependent else "") + "."
            )
        frf = np.asarray(self.frf_)
        entries = frf.reshape(-1, frf.shape[-1])
        half = np.stack([
            np.interp(f_fast, self.frequencies_[keep], entry[keep].real)
            + 1j * np.interp(f_fast, self.frequencies_[keep], entry[keep].imag)
            for entry in entries
        ]).reshape(frf.shape[:-1] + (f_fast.size,))
        # the segment bins on either side of each fast bin (the same one on a
        # node, and beyond the last node, e.g. for an odd segment length)
        # (positions in segment bins, a fast bin on a node to round-off)
        position = f_fast / self.frequencies_[1]
        last = self.frequencies_.size - 1
        below = np.clip(np.floor(position + 1e-9).astype(int), 0, last)
        above = np.clip(np.ceil(position - 1e-9).astype(int), 0, last)
        half[..., ~(keep[below] & keep[above])] = np.nan
        mirror = np.conj(half[..., 1 : n_samples - n_samples // 2][..., ::-1])
        return np.concatenate([half, mirror], axis=-1)
