"""Known answers of the excitation signals."""

import numpy as np
import pytest

from lrmfrf import multisine
from lrmfrf.signals import orthogonal_multisines


@pytest.mark.parametrize("N", [1200, 1201, 64])
def test_multisine_rms_flat_amplitude_and_bins(N):
    u = multisine(N, rms=1.44, rng=0)
    assert u.shape == (N,)
    np.testing.assert_allclose(np.sqrt(np.mean(u**2)), 1.44, rtol=1e-12)
    amplitude = np.abs(np.fft.rfft(u))
    assert amplitude[0] < 1e-9 * amplitude.max()  # no DC
    np.testing.assert_allclose(amplitude[1:], amplitude[1], rtol=1e-9)


def test_multisine_with_amplitude_spectrum():
    N = 1000
    shape = 1.0 + np.arange(N // 2 + 1) ** 2  # e.g. 1 / |G| of a double integrator
    u = multisine(N, rms=2.0, rng=3, amplitude=shape)
    spectrum = np.abs(np.fft.rfft(u))
    ratio = spectrum[1:] / shape[1:]
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.mean(u**2)), 2.0, rtol=1e-12)
    # the same phases as the flat multisine of the same seed
    flat = np.fft.rfft(multisine(N, rng=3))
    np.testing.assert_allclose(np.angle(np.fft.rfft(u)[1:] / flat[1:]), 0.0,
                               atol=1e-9)
    # with bins: only those are read
    v = multisine(N, bins=[4, 9], rng=0, amplitude=shape)
    V = np.abs(np.fft.rfft(v))
    np.testing.assert_allclose(V[9] / V[4], shape[9] / shape[4], rtol=1e-9)
    original = shape.copy()
    multisine(N, rng=0, amplitude=shape)
    np.testing.assert_array_equal(shape, original)  # input not modified


@pytest.mark.parametrize("amplitude, match", [
    (np.ones(10), r"shape \(501,\)"),
    (np.full(501, 1 + 0j), "real array"),
    (-np.ones(501), "finite and >= 0"),
    (np.full(501, np.inf), "finite and >= 0"),
    (np.zeros(501), "zero on every excited bin"),
])
def test_multisine_bad_amplitude(amplitude, match):
    with pytest.raises(ValueError, match=match):
        multisine(1000, rng=0, amplitude=amplitude)


def test_multisine_selected_bins_and_reproducibility():
    u = multisine(1000, bins=[3, 7, 500], rng=np.random.default_rng(1))
    spectrum = np.abs(np.fft.rfft(u))
    assert set(np.flatnonzero(spectrum > 1e-9 * spectrum.max())) == {3, 7, 500}
    np.testing.assert_array_equal(u, multisine(1000, bins=[3, 7, 500], rng=1))
    assert not np.array_equal(u, multisine(1000, bins=[3, 7, 500], rng=2))


@pytest.mark.parametrize("kwargs, exc, match", [
    ({"bins": [0, 1]}, ValueError, r"`bins` must be DFT bins in 1..N//2 = 1..500. "
     "Got bins from 0 to 1 instead"),
    ({"bins": [700]}, ValueError, "Got bins from 700 to 700 instead"),
    ({"bins": []}, ValueError, r"non-empty 1-D sequence.*Got shape \(0,\) instead"),
    ({"bins": [[3, 7]]}, ValueError, r"Got shape \(1, 2\) instead"),
    ({"bins": [2.5, 7]}, TypeError, "`bins` must hold whole numbers"),
    ({"bins": ["3"]}, TypeError, "`bins` must hold whole numbers"),
    ({"rms": -1.0}, ValueError, "`rms` must be a positive, finite number"),
    ({"rms": np.nan}, ValueError, "`rms` must be a positive, finite number"),
    ({"rms": "loud"}, TypeError, "`rms` must be a positive number. Got 'loud'"),
])
def test_multisine_bad_input(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        multisine(1000, **kwargs)


def test_multisine_whole_float_bins_accepted():
    """Whole floats are bins (not silently truncated fractions)."""
    np.testing.assert_array_equal(multisine(1000, bins=[3.0, 7.0], rng=1),
                                  multisine(1000, bins=[3, 7], rng=1))


def test_multisine_bad_length():
    with pytest.raises(ValueError, match="`n_samples` must be an integer >= 2"):
        multisine(1)
    with pytest.raises(TypeError, match="`n_samples` must be an integer"):
        multisine(100.5)


@pytest.mark.parametrize("n_u, N", [(1, 64), (2, 100), (3, 99), (4, 128), (5, 250)])
def test_orthogonal_multisines_are_orthogonal_at_every_bin(n_u, N):
    """U(k) U(k)^H = n_u A^2 I at every excited bin, Nyquist included."""
    u = orthogonal_multisines(n_u, N, rms=2.0, rng=3)
    assert u.shape == (n_u, n_u, N) and np.isrealobj(u)
    U = np.fft.rfft(u, axis=-1)[:, :, 1:]  # [p, i, k], DC not excited
    np.testing.assert_allclose(np.fft.rfft(u, axis=-1)[:, :, 0], 0.0, atol=1e-9)
    gram = np.einsum("pik,pjk->kij", U, U.conj())
    amplitude2 = np.abs(U[0, 0, 0]) ** 2
    expected = n_u * amplitude2 * np.eye(n_u)
    np.testing.assert_allclose(gram, np.broadcast_to(expected, gram.shape),
                               atol=1e-9 * n_u * amplitude2)
    assert np.sqrt(np.mean(u**2)) == pytest.approx(2.0, rel=1e-12)


def test_orthogonal_multisines_flat_spectrum_and_equal_rms_without_nyquist():
    u = orthogonal_multisines(3, 101, rms=1.5, rng=0)  # odd N: no Nyquist bin
    magnitude = np.abs(np.fft.rfft(u, axis=-1)[:, :, 1:])
    np.testing.assert_allclose(magnitude, magnitude[0, 0, 0], rtol=1e-10)
    np.testing.assert_allclose(np.sqrt(np.mean(u**2, axis=-1)), 1.5, rtol=1e-12)


def test_orthogonal_multisines_selected_bins_and_seeding():
    u = orthogonal_multisines(2, 200, bins=[3, 7, 50], rng=5)
    excited = np.flatnonzero(np.abs(np.fft.rfft(u[1, 0])) > 1e-9)
    np.testing.assert_array_equal(excited, [3, 7, 50])
    np.testing.assert_array_equal(u, orthogonal_multisines(2, 200, bins=[3, 7, 50],
                                                           rng=5))
    assert not np.array_equal(u, orthogonal_multisines(2, 200, bins=[3, 7, 50],
                                                       rng=6))


@pytest.mark.parametrize(
    "args, kwargs, exc, match",
    [
        ((0, 100), {}, ValueError, "n_inputs"),
        ((2.5, 100), {}, TypeError, "n_inputs"),
        ((2, 1), {}, ValueError, "n_samples"),
        ((2, 100), {"rms": -1.0}, ValueError, "rms"),
        ((2, 100), {"bins": [0, 1]}, ValueError, "bins"),
    ],
)
def test_orthogonal_multisines_bad_input(args, kwargs, exc, match):
    with pytest.raises(exc, match=match):
        orthogonal_multisines(*args, **kwargs)
