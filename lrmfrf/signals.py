"""Excitation signals."""

from __future__ import annotations

import numpy as np

from ._validation import check_nonnegative_int, check_positive_float

__all__ = ["multisine", "orthogonal_multisines"]


def multisine(
    n_samples: int,
    *,
    rms: float = 1.0,
    bins=None,
    rng: int | np.random.Generator | None = None,
    amplitude=None,
) -> np.ndarray:
    """Random-phase multisine with a flat (or given) amplitude spectrum (one period).

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
    amplitude : array-like of shape (N//2 + 1,), optional
        Relative DFT magnitude of each bin ``0..N//2`` (only the excited bins
        are read; finite, >= 0, not all zero on them); e.g. ``1 / |G(k)|`` of
        a nominal model, for an output with a flat spectrum. Default: flat.

    Returns
    -------
    ndarray of shape (n_samples,)
        One period; every excited bin has the same DFT magnitude (or
        magnitudes proportional to ``amplitude``).

    Raises
    ------
    TypeError, ValueError
        For ``n_samples < 2``, a non-positive ``rms``, ``bins`` that are not
        whole numbers in ``1..N//2``, or an ``amplitude`` of the wrong shape,
        negative, not finite or zero on every excited bin.

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
    scale = None if amplitude is None else _check_amplitude(amplitude, N, bins)
    rng = np.random.default_rng(rng)
    spectrum = np.zeros(N // 2 + 1, dtype=complex)
    spectrum[bins] = np.exp(2j * np.pi * rng.random(bins.size))
    if N % 2 == 0 and bins[-1] == N // 2:
        spectrum[N // 2] = rng.choice([-1.0, 1.0])
    if amplitude is not None:
        spectrum *= scale
    u = np.fft.irfft(spectrum, n=N)
    return u * (rms / np.sqrt(np.mean(u**2)))


def orthogonal_multisines(
    n_inputs: int,
    n_samples: int,
    *,
    rms: float = 1.0,
    bins=None,
    rng: int | np.random.Generator | None = None,
) -> np.ndarray:
    """Orthogonal random-phase multisines for ``n_inputs`` experiments.

    Experiment ``p`` drives input ``i`` with the spectrum
    ``U_i^[p](k) = A exp(j phi_i(k)) T[i, p]``, where ``phi_i(k)`` are random
    phases (one set per input, shared by the experiments) and
    ``T[i, p] = exp(-j 2 pi i p / n_inputs)`` is the DFT matrix (Dobrowiecki,
    Schoukens and Guillaume, 2006). At every excited bin the input matrix
    ``U(k)`` (inputs x experiments) then satisfies ``U(k) U(k)^H = n_inputs A^2
    I``: the experiments excite the inputs in orthogonal directions, the best
    conditioned MIMO excitation with a flat amplitude spectrum. The Nyquist
    bin (even ``N``), whose value must be real, uses ``sqrt(n_inputs) A``
    times a random sign on input ``p`` of experiment ``p`` only, which keeps
    the same orthogonality there.

    Parameters
    ----------
    n_inputs : int
        Number of inputs ``n_u`` (>= 1); as many experiments are returned.
    n_samples : int
        Period ``N`` in samples.
    rms : float, default=1.0
        Root-mean-square value of the signals (exactly, for each signal, when
        the Nyquist bin is not excited; otherwise on average over them).
    bins : array-like of int, optional
        Excited DFT bins in ``1..N//2``; default all of them (no DC).
    rng : int, numpy.random.Generator or None
        Seed or generator for the random phases.

    Returns
    -------
    ndarray of shape (n_inputs, n_inputs, n_samples)
        ``[p, i]`` is the signal of input ``i`` in experiment ``p``: the
        package's ``(P, n_u, N)`` layout for several experiments.

    References
    ----------
    T. Dobrowiecki, J. Schoukens and P. Guillaume, "Optimized excitation
    signals for MIMO frequency response function measurements", IEEE Trans.
    Instrum. Meas. 55(6), 2006.

    Examples
    --------
    >>> from lrmfrf.signals import orthogonal_multisines
    >>> u = orthogonal_multisines(2, 1000, rng=0)
    >>> u.shape
    (2, 2, 1000)
    """
    n_u = check_nonnegative_int(n_inputs, "n_inputs", minimum=1)
    N = check_nonnegative_int(n_samples, "n_samples", minimum=2)
    rms = check_positive_float(rms, "rms", allow_none=False)
    bins = np.arange(1, N // 2 + 1) if bins is None else _check_bins(bins, N)
    rng = np.random.default_rng(rng)
    index = np.arange(n_u)
    dft_matrix = np.exp(-2j * np.pi * np.outer(index, index) / n_u)  # [i, p]
    phases = np.exp(2j * np.pi * rng.random((n_u, bins.size)))  # [i, k]
    spectrum = np.zeros((n_u, n_u, N // 2 + 1), dtype=complex)  # [p, i, k]
    spectrum[:, :, bins] = dft_matrix.T[:, :, np.newaxis] * phases[np.newaxis]
    if N % 2 == 0 and bins[-1] == N // 2:
        signs = rng.choice([-1.0, 1.0], size=n_u)
        spectrum[:, :, N // 2] = np.diag(np.sqrt(n_u) * signs)
    u = np.fft.irfft(spectrum, n=N, axis=-1)
    return u * (rms / np.sqrt(np.mean(u**2)))


def _check_amplitude(amplitude, n_samples: int, bins: np.ndarray) -> np.ndarray:
    values = np.asarray(amplitude)
    K = n_samples // 2 + 1
    if values.shape != (K,) or not np.issubdtype(values.dtype, np.number) \
            or np.iscomplexobj(values):
        raise ValueError(
            f"`amplitude` must be a real array of shape ({K},) (one value per bin "
            f"0..N//2); got shape {values.shape} and dtype {values.dtype}. For a "
            "complex FRF G pass np.abs(G) or 1 / np.abs(G)."
        )
    values = values.astype(float)
    if not np.all(np.isfinite(values)) or np.any(values < 0):
        raise ValueError(
            "`amplitude` must be finite and >= 0; clip it, e.g. "
            "np.minimum(amplitude, limit)."
        )
    if not np.any(values[bins] > 0):
        raise ValueError("`amplitude` is zero on every excited bin; nothing would be "
                         "excited.")
    return values


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
