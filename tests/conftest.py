"""Shared fixtures: small systems and data built exactly in the local model class."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import cont2discrete, lfilter

from lrmfrf.windows import LocalModelLayout


def resonant_system(sample_time: float = 0.5e-3):
    """Two lightly damped modes (120 Hz, 1 %; 520 Hz, 0.8 %) as a discrete tf.

    520 Hz lies above the slow Nyquist frequency for F = 3 (333 Hz). Returns
    ``(b, a)`` for ``scipy.signal.lfilter`` (4th order: accurate as a tf).
    """
    modes = [(120.0, 0.01, 1.0), (520.0, 0.008, 0.6)]
    num = np.zeros(1)
    den = np.ones(1)
    for f, z, g in modes:
        w = 2 * np.pi * f
        sec = np.array([1.0, 2 * z * w, w**2])
        num = np.polyadd(np.polymul(num, sec), g * w**2 * den)
        den = np.polymul(den, sec)
    b, a, _ = cont2discrete((num, den), sample_time, method="zoh")
    return np.ravel(b), np.ravel(a)


def frf_of(b, a, n_samples: int) -> np.ndarray:
    """Exact FRF of lfilter(b, a) at z = exp(j 2 pi k / N), k = 0..N//2."""
    z = np.exp(-2j * np.pi * np.arange(n_samples // 2 + 1) / n_samples)
    return np.polyval(b[::-1], z) / np.polyval(a[::-1], z)


@pytest.fixture
def resonant():
    return resonant_system()


def in_class_data(layout: LocalModelLayout, n_slow: int, rng):
    """Records whose DFT is exactly in the local model class at some windows.

    Non-overlapping windows in the lower half of the slow grid each get their
    own random rational local model: ``Y = (sum_f n_f(x) U_f + t(x)) / e(x)``
    on the window, with ``e`` free of roots near ``[-1, 1]``. Mirror bins are
    set to the conjugate so the time records are real.

    Returns
    -------
    u : ndarray of shape (P, N)
    y : ndarray of shape (P, M)
    centres : ndarray of int
        Window centres where the data are in class.
    G : ndarray of shape (len(centres), F)
        True ``G(k + fM)`` at those centres.
    """
    F, n, P = layout.F, layout.half_window, layout.n_experiments
    M, N = n_slow, layout.F * n_slow
    u = rng.standard_normal((P, N))
    U = np.fft.fft(u, axis=1)
    Y = np.fft.fft(rng.standard_normal((P, M)), axis=1)
    r = np.arange(-n, n + 1)
    x = r / n
    centres = np.arange(n + 1, M // 2 - n, 2 * n + 1)
    G = np.empty((centres.size, F), dtype=complex)
    for i, k in enumerate(centres):
        def cplx(*shape):
            return rng.standard_normal(shape) + 1j * rng.standard_normal(shape)

        num = cplx(layout.num_degree + 1, F)  # coefficient of x^s, band f
        e = np.concatenate([[1.0], 0.3 * cplx(layout.den_degree) / 2**np.arange(
            layout.den_degree)])
        den = np.polyval(e[::-1], x)
        for p in range(P):
            t = np.polyval(cplx(layout.transient_degree + 1)[::-1], x)
            Ufast = U[p, (k + r[:, None] + M * np.arange(F)) % N]  # (L, F)
            numer = np.einsum("ls,sf,lf->l", x[:, None] ** np.arange(
                layout.num_degree + 1), num, Ufast)
            Y[p, k + r] = (numer + t) / den
            Y[p, M - (k + r)] = np.conj(Y[p, k + r])
        G[i] = F * num[0]
    Y[:, 0] = Y[:, 0].real
    if M % 2 == 0:
        Y[:, M // 2] = Y[:, M // 2].real
    y = np.fft.ifft(Y, axis=1)
    assert np.abs(y.imag).max() < 1e-12 * np.abs(y).max()
    return u, y.real, centres, G


def simulate_resonant(u, F, noise_std, rng, b=None, a=None):
    """Slow output of the resonant system (at rest before the record) plus noise."""
    if b is None:
        b, a = resonant_system()
    y_h = lfilter(b, a, u)
    y_l = y_h[..., ::F]
    return y_l + noise_std * rng.standard_normal(y_l.shape)
