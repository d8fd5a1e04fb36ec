"""Known answers of the excitation signals."""

import numpy as np
import pytest

from lrmfrf import multisine


@pytest.mark.parametrize("N", [1200, 1201, 64])
def test_multisine_rms_flat_amplitude_and_bins(N):
    u = multisine(N, rms=1.44, rng=0)
    assert u.shape == (N,)
    np.testing.assert_allclose(np.sqrt(np.mean(u**2)), 1.44, rtol=1e-12)
    amplitude = np.abs(np.fft.rfft(u))
    assert amplitude[0] < 1e-9 * amplitude.max()  # no DC
    np.testing.assert_allclose(amplitude[1:], amplitude[1], rtol=1e-9)


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
