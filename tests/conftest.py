"""Shared test helpers: a lightly damped two-mode plant, its exact FRF, its output."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import cont2discrete, lfilter


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


def simulate_resonant(u, F, noise_std, rng, b=None, a=None):
    """Slow output of the resonant system (at rest before the record) plus noise."""
    if b is None:
        b, a = resonant_system()
    y_h = lfilter(b, a, u)
    y_l = y_h[..., ::F]
    return y_l + noise_std * rng.standard_normal(y_l.shape)


def random_stage_record(seed: int = 3000, F: int = 3, snr_db: float = 40.0):
    """``(u, y_l)`` of a random stage's ``G_z`` (seed 3000: neither tuning nor
    held-out), N = 1200, one random-phase multisine."""
    from lrmfrf.plants import random_stage
    from lrmfrf.signals import multisine
    from lrmfrf.simulate import simulate

    stage, _ = random_stage(seed, downsampling_factor=F)
    u = multisine(1200, rms=1.44, rng=1)
    return u, simulate(stage.G_z, u, F, snr_db=snr_db, rng=2).y_l


def band_variances(cov):
    """Real diagonals of per-window band covariances ``(B, n, n)``."""
    return np.real(np.diagonal(cov, axis1=1, axis2=2))


#: Appended to bit-for-bit comparisons of two compiled kernels.
CACHE_HINT = (
    "a kernel compiled in this process and one loaded from numba's cache can "
    "differ in the last bits: if this follows a change to a compiled module, "
    "clear the cache (find lrmfrf -name '*.nb[ci]' -delete) and run again "
    "(README, Layout)"
)


def blas_threads():
    """The thread counts of the loaded BLAS libraries (threadpoolctl)."""
    import threadpoolctl

    return [lib["num_threads"] for lib in threadpoolctl.threadpool_info()
            if lib["user_api"] == "blas"]


@pytest.fixture
def two_blas_threads():
    """BLAS on (at least) two threads for the test, so that a limit to one can
    be seen; the process's settings are put back afterwards. The test's thread
    holds OpenBLAS's controlling thread (threadpoolctl >= 3.8) neither before
    nor after the test: it would silently ignore the limits set from worker
    threads (a test that limits BLAS itself, as the per-thread one does through
    threadpoolctl, took it and kept it for the tests after it)."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    clear = getattr(threadpoolctl.OpenBLASController, "clear_controlling_thread",
                    lambda: None)
    clear()
    if not blas_threads():  # pragma: no cover
        pytest.skip("no BLAS library found by threadpoolctl")
    forced = None
    if 1 in blas_threads():
        forced = threadpoolctl.threadpool_limits(limits=2, user_api="blas")
        clear()
    before = blas_threads()
    try:
        if 1 in before:  # pragma: no cover
            pytest.skip("BLAS cannot run on two threads here: a limit cannot be seen")
        yield before
    finally:
        if forced is not None:
            forced.restore_original_limits()
        clear()
