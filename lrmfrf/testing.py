"""Data generators with known answers, for tests and benchmarks."""

from __future__ import annotations

import numpy as np

from .windows import LocalModelLayout, band_indices

__all__ = ["in_class_data", "in_class_mimo_data"]


def in_class_data(layout: LocalModelLayout, n_slow: int, rng=None):
    """Records whose DFT is exactly in the local model class at some windows.

    Non-overlapping windows in the lower half of the slow grid each get their
    own random rational local model: ``Y = (sum_f n_f(x) U_f + t(x)) / e(x)``
    on the window, with ``|e(x) - 1| <= 0.5`` on ``[-1, 1]`` (no poles there).
    Mirror bins are set to the conjugate so the time records are real.

    Parameters
    ----------
    layout : LocalModelLayout
        Degrees, window and number of experiments of the model class.
    n_slow : int
        ``M``; the records have ``N = F M`` fast samples.
    rng : int, numpy.random.Generator or None

    Returns
    -------
    u : ndarray of shape (P, N)
        ``P`` SISO records: pass ``list(u)`` (or ``u[:, None]``) to ``fit``,
        since a 2-D array is one record with channels first.
    y : ndarray of shape (P, M)
    centres : ndarray of int
        Window centres where the data are in class.
    G : ndarray of shape (len(centres), F)
        True ``G(k + fM)`` at those centres.
    """
    rng = np.random.default_rng(rng)
    F, n, P = layout.F, layout.half_window, layout.n_experiments
    M, N = n_slow, layout.F * n_slow
    u = rng.standard_normal((P, N))
    U = np.fft.fft(u, axis=1)
    Y = np.fft.fft(rng.standard_normal((P, M)), axis=1)
    r = np.arange(-n, n + 1)
    x = r / n
    powers = x[:, None] ** np.arange(layout.num_degree + 1)  # (L, Rg+1)
    centres = np.arange(n + 1, M // 2 - n, 2 * n + 1)
    G = np.empty((centres.size, F), dtype=complex)
    for i, k in enumerate(centres):
        num = _complex_normal(rng, layout.num_degree + 1, F)  # x^s, band f
        e = _complex_normal(rng, layout.den_degree)
        e *= 0.5 / max(np.abs(e).sum(), 1e-300)  # |e(x) - 1| <= 0.5 on [-1, 1]
        den = np.polyval(np.concatenate([[1.0], e])[::-1], x)
        for p in range(P):
            t = np.polyval(_complex_normal(rng, layout.transient_degree + 1), x)
            u_window = U[p, (k + r[:, None] + M * np.arange(F)) % N]  # (L, F)
            numer = np.einsum("ls,sf,lf->l", powers, num, u_window)
            Y[p, k + r] = (numer + t) / den
            Y[p, M - (k + r)] = np.conj(Y[p, k + r])
        G[i] = F * num[0]
    Y[:, 0] = Y[:, 0].real
    if M % 2 == 0:
        Y[:, M // 2] = Y[:, M // 2].real
    return u, np.fft.ifft(Y, axis=1).real, centres, G


def in_class_mimo_data(layout: LocalModelLayout, n_slow: int, n_outputs: int,
                       rng=None):
    """MIMO records whose DFT is exactly in the local model class at some windows.

    As :func:`in_class_data`, per output row: each output ``o`` gets, on each
    window, its own random rational local model over the ``F n_u`` bands of
    all inputs, ``Y_o = (sum_{i,f} n_{oif}(x) U_i(k+r+fM) + t_o(x)) / e_o(x)``
    (one denominator per output row, one transient per experiment and
    output), which is the model class of :class:`lrmfrf.LRMBeyondNyquist`.

    Parameters
    ----------
    layout : LocalModelLayout
        Degrees, window, number of experiments ``P`` and of inputs ``n_u``.
    n_slow : int
        ``M``; the records have ``N = F M`` fast samples.
    n_outputs : int
        ``n_y``.
    rng : int, numpy.random.Generator or None

    Returns
    -------
    u : ndarray of shape (P, n_u, N)
    y : ndarray of shape (P, n_y, M)
    centres : ndarray of int
        Window centres where the data are in class.
    G : ndarray of shape (len(centres), n_y, n_u, F)
        True ``G_oi(k + fM)`` at those centres.
    """
    rng = np.random.default_rng(rng)
    F, n, P = layout.F, layout.half_window, layout.n_experiments
    n_u, n_b = layout.n_inputs, layout.n_bands
    M, N = n_slow, layout.F * n_slow
    u = rng.standard_normal((P, n_u, N))
    U = np.fft.fft(u, axis=-1).reshape(P, n_u * N)
    Y = np.fft.fft(rng.standard_normal((P, n_outputs, M)), axis=-1)
    r = np.arange(-n, n + 1)
    x = r / n
    powers = x[:, None] ** np.arange(layout.num_degree + 1)  # (L, Rg+1)
    centres = np.arange(n + 1, M // 2 - n, 2 * n + 1)
    G = np.empty((centres.size, n_outputs, n_u, F), dtype=complex)
    for c, k in enumerate(centres):
        u_window = U[:, band_indices(k + r, layout, M)]  # (P, L, n_bands)
        for o in range(n_outputs):
            num = _complex_normal(rng, layout.num_degree + 1, n_b)
            e = _complex_normal(rng, layout.den_degree)
            e *= 0.5 / max(np.abs(e).sum(), 1e-300)  # |e(x) - 1| <= 0.5
            den = np.polyval(np.concatenate([[1.0], e])[::-1], x)
            for p in range(P):
                t = np.polyval(_complex_normal(rng, layout.transient_degree + 1), x)
                numer = np.einsum("ls,sb,lb->l", powers, num, u_window[p])
                Y[p, o, k + r] = (numer + t) / den
                Y[p, o, M - (k + r)] = np.conj(Y[p, o, k + r])
            G[c, o] = F * num[0].reshape(n_u, F)
    Y[..., 0] = Y[..., 0].real
    if M % 2 == 0:
        Y[..., M // 2] = Y[..., M // 2].real
    return u, np.fft.ifft(Y, axis=-1).real, centres, G


def _complex_normal(rng, *shape):
    return rng.standard_normal(shape) + 1j * rng.standard_normal(shape)
