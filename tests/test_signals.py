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


@pytest.mark.parametrize("kwargs, match", [
    ({"bins": [0, 1]}, "bins"),
    ({"bins": [700]}, "bins"),
    ({"bins": []}, "bins"),
    ({"rms": -1.0}, "rms"),
])
def test_multisine_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        multisine(1000, **kwargs)


def test_multisine_bad_length():
    with pytest.raises(ValueError, match="n_samples"):
        multisine(1)
