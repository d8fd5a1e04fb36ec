"""The streamed closed form (issue 14 item 3) gives the eager computation's results.

The estimators fit the closed form from one-sided DFTs, chunk by chunk, write
each chunk into the outputs and compute ``local_fit_`` on first access. The
reference here is the previous eager computation written out in the test:
``fit_local_models`` on the full DFTs of all windows at once, then the
one-sided fast grid of the band values. Tolerance: bit for bit where the same
floating-point operations are done (they are: the windows read the same
values and the kernels solve each window alone), checked as 1e-12 relative so
that a harmless change of summation order in a kernel does not fail it.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from conftest import CACHE_HINT, simulate_resonant

from lrmfrf import LPMBeyondNyquist, LRMBeyondNyquist, _compiled
from lrmfrf.local_models import (
    EXCITATION_TOL,
    OneSidedSpectra,
    _excitation_reference,
    _excited_windows,
    _fast_grid_runs,
    _one_sided_mean_energy,
    _periodic_values,
    _relative_excitation,
    dft,
    fast_grid_targets,
    fit_local_models,
    fit_one_sided,
    one_sided_fast_grid,
    rescale_local_fit,
    scale_by_power_of_two,
    stream_chunk_size,
)
from lrmfrf.refinement import refine_local_models
from lrmfrf.signals import multisine
from lrmfrf.uncertainty import calibrated_local_fit, calibrated_refined_fit
from lrmfrf.windows import LocalModelLayout, local_regressor

RTOL = 1e-12
FIT_FIELDS = ("theta", "system", "system_var", "transient", "noise_var", "rss",
              "system_cov")


def assert_close(actual, desired, name=""):
    """Equal to RTOL of the largest magnitude, NaN where the reference is."""
    actual, desired = np.asarray(actual), np.asarray(desired)
    assert actual.shape == desired.shape, name
    if desired.dtype == bool:
        np.testing.assert_array_equal(actual, desired, err_msg=name)
        return
    np.testing.assert_array_equal(np.isnan(actual), np.isnan(desired), err_msg=name)
    scale = np.nanmax(np.abs(desired)) if np.isfinite(desired).any() else 1.0
    np.testing.assert_allclose(actual, desired, rtol=0, atol=RTOL * scale,
                               equal_nan=True, err_msg=f"{name}: {CACHE_HINT}")


def assert_same_fit(fit, reference):
    for name in FIT_FIELDS + ("well_posed", "excited", "slow_bins"):
        assert_close(getattr(fit, name), getattr(reference, name), name)


def siso_data(n_samples=1200, P=1, seed=0):
    rng = np.random.default_rng(seed)
    u = np.stack([multisine(n_samples, rng=rng) for _ in range(P)])
    y = simulate_resonant(u, 3, 1e-3, rng)
    return (u[0], y[0]) if P == 1 else (u[:, None], y[:, None])


def mimo_data(n_samples=1500, seed=1):
    """Two experiments, two inputs, two outputs: u (2, 2, N), y (2, 2, N/3)."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((2, 2, n_samples))
    y = np.stack([
        simulate_resonant(u[:, 0], 3, 0.0, rng) + 0.5 * simulate_resonant(
            u[:, 1], 3, 1e-3, rng),
        -0.3 * simulate_resonant(u[:, 0], 3, 1e-3, rng) + simulate_resonant(
            u[:, 1], 3, 0.0, rng),
    ], axis=1)
    return u, y


def eager_reference(est, u, y, F=3):
    """The previous eager computation: all windows at once on the full DFTs,
    then the fast grid, for records (P, n_u, N) and (P, n_y, M)."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    if u.ndim == 1:
        u, y = u[None, None], y[None, None]
    P, n_u, N = u.shape
    layout = est.layout_
    U = dft(u).reshape(P, n_u * N)
    # the closed form with the std route of the estimator (lrmfrf.uncertainty)
    fits = [calibrated_local_fit(
        U, dft(y[:, o]), layout,
        fit_local_models(U, dft(y[:, o]), layout, return_cov=True),
        getattr(est, "std_method", "lemma2"),
    ) for o in range(y.shape[1])]
    frf = np.array([[one_sided_fast_grid(fit.system[:, i * F:(i + 1) * F], N, F,
                                         conj=True) for i in range(n_u)]
                    for fit in fits])
    std = np.sqrt(np.array([[one_sided_fast_grid(
        fit.system_var[:, i * F:(i + 1) * F], N, F, conj=False) for i in range(n_u)]
        for fit in fits]))
    cov = np.array([[[one_sided_fast_grid(np.diagonal(
        fit.system_cov[:, i * F:(i + 1) * F, j * F:(j + 1) * F], axis1=1, axis2=2),
        N, F, conj=True) for j in range(n_u)] for i in range(n_u)] for fit in fits])
    valid = np.array([one_sided_fast_grid(
        np.repeat(fit.well_posed[:, None], F, axis=1), N, F, conj=False)
        for fit in fits])
    return fits, frf, std, cov, valid


def check_against_eager(est, u, y):
    fits, frf, std, cov, valid = eager_reference(est, u, y)
    siso = len(fits) == 1 and frf.shape[1] == 1
    assert_close(est.frf_, frf[0, 0] if siso else frf, "frf_")
    assert_close(est.frf_std_, std[0, 0] if siso else std, "frf_std_")
    assert_close(est.frf_cov_, cov, "frf_cov_")
    valid = np.broadcast_to(valid[:, None], frf.shape)
    assert_close(est.valid_, valid[0, 0] if siso else valid, "valid_")
    noise = np.array([fit.noise_var for fit in fits])
    assert_close(est.noise_variance_, noise[0] if siso else noise, "noise")
    transient = np.stack([fit.transient.T for fit in fits], axis=1)  # (P, n_y, B)
    if siso:
        transient = transient[0, 0] if transient.shape[0] == 1 else transient[:, 0]
    assert_close(est.transient_, transient, "transient_")
    local = [est.local_fit_] if siso else est.local_fit_
    assert len(local) == len(fits)
    for fit, reference in zip(local, fits, strict=True):
        assert_same_fit(fit, reference)


# --- the pieces ------------------------------------------------------------------


@pytest.mark.parametrize("N", [1200, 1203, 1206])
def test_one_sided_spectra_are_the_dft(N):
    """rfft halves are the full DFT bit for bit (its upper half is the exact
    conjugate), and a chunk's compact spectra pose the same window problems."""
    rng = np.random.default_rng(N)
    u, y = rng.standard_normal((2, 2, N)), rng.standard_normal((2, 3, N // 3))
    spectra = OneSidedSpectra.from_records(u, y, 3)
    U = dft(u).reshape(2, -1)
    np.testing.assert_array_equal(spectra.full_inputs(), U)
    np.testing.assert_array_equal(spectra.full_outputs(2), dft(y[:, 2]))
    layout = LocalModelLayout(F=3, half_window=5, num_degree=1, transient_degree=1,
                              den_degree=2, n_experiments=2, n_inputs=2)
    M = N // 3
    for start, stop in [(0, 7), (3, 40), (M // 2 - 4, M // 2 + 1)]:
        U_c, Y_c, bins = spectra.window_spectra(start, stop, 5, output=1)
        A, b = local_regressor(U, dft(y[:, 1]), np.arange(start, stop), layout)
        A_c, b_c = local_regressor(U_c, Y_c, bins, layout)
        np.testing.assert_array_equal(A_c, A)
        np.testing.assert_array_equal(b_c, b)


@pytest.mark.parametrize("N, F", [(60, 3), (63, 3), (66, 3), (64, 4), (61, 1),
                                  (70, 5), (75, 5), (12, 2)])
def test_fast_grid_targets_fill_the_grid_once(N, F):
    """Chunk by chunk, the targets give one_sided_fast_grid, each bin once."""
    M = N // F
    rng = np.random.default_rng(N + F)
    values = rng.standard_normal((M // 2 + 1, F)) + 1j * rng.standard_normal(
        (M // 2 + 1, F))
    expected = one_sided_fast_grid(values, N, F, conj=True)
    for chunk in (1, 3, M):
        out = np.full(N // 2 + 1, np.nan, dtype=complex)
        hits = np.zeros(N // 2 + 1, dtype=int)
        for start in range(0, M // 2 + 1, chunk):
            stop = min(M // 2 + 1, start + chunk)
            fast, slow, band, mirrored = fast_grid_targets(start, stop, N, F)
            v = values[start:stop][slow, band]
            out[fast] = np.where(mirrored, np.conj(v), v)
            np.add.at(hits, fast, 1)
        np.testing.assert_array_equal(out, expected)
        assert (hits == 1).all()


@pytest.mark.parametrize("F", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("M", [1, 2, 7, 8, 9, 40, 41])
def test_fast_grid_runs_are_the_targets(F, M):
    """The runs of slices the estimators write with are fast_grid_targets:
    the same fast bins, sources and conjugation, chunk by chunk."""
    N, B = F * M, M // 2 + 1
    for chunk in (1, 2, 3, 7, B):
        for start in range(0, B, chunk):
            stop = min(B, start + chunk)
            fast, slow, band, mirrored = fast_grid_targets(start, stop, N, F)
            expected = sorted(zip(fast.tolist(), slow.tolist(), band.tolist(),
                                  mirrored.tolist()))
            got = []
            for f, k0, k1, j0, conj in _fast_grid_runs(start, stop, N, F):
                ks = range(k1 - 1, k0 - 1, -1) if conj else range(k0, k1)
                got += [(j0 + t, k, f, conj) for t, k in enumerate(ks)]
            assert sorted(got) == expected, (start, stop)


def gathered_window_spectra(spectra, start, stop, n, output):
    """The compact spectra as they were gathered through index arrays."""
    N, M, F = spectra.n_samples, spectra.n_slow, spectra.F
    slow = np.arange(start - n, stop + n)
    fast = (slow[None, :] + M * np.arange(F)[:, None]) % N
    P = spectra.inputs.shape[0]
    U = _periodic_values(spectra.inputs, fast.ravel(), N).reshape(P, -1)
    Y = _periodic_values(spectra.outputs[:, output], slow % M, M)
    return U, Y


@pytest.mark.parametrize("F, M", [(1, 9), (2, 8), (3, 41), (3, 40), (5, 7)])
def test_window_spectra_are_the_gathered_values(F, M):
    """window_spectra copies runs with slices: bit for bit the values the index
    arrays gathered, for windows that wrap around bin 0, cross the middle of
    the one-sided spectra, or are wider than half the record."""
    rng = np.random.default_rng(F * M)
    u = rng.standard_normal((2, 2, F * M))
    y = rng.standard_normal((2, 3, M))
    spectra = OneSidedSpectra.from_records(u, y, F)
    for n in range(1, M // 2 + 1):
        for start, stop in [(0, 1), (0, M // 2 + 1), (M // 2, M // 2 + 1),
                            (1, max(2, M // 3))]:
            for output in (1, [2, 0]):
                U, Y, bins = spectra.window_spectra(start, stop, n, output)
                U_ref, Y_ref = gathered_window_spectra(spectra, start, stop, n,
                                                       output)
                assert U.shape == U_ref.shape and Y.shape == Y_ref.shape
                assert U.tobytes() == U_ref.tobytes(), (n, start, stop)
                assert Y.tobytes() == Y_ref.tobytes(), (n, start, stop, output)


@pytest.mark.parametrize("gap", [None, "band", "faint", "all", "one input"])
def test_excited_windows_as_the_relative_excitation(gap):
    """The excitation test's shortcut (bands whose least bin energy clears the
    tolerance skip the window sums) gives the booleans of the relative
    energies, with and without unexcited windows."""
    F, P, n_u, n, M = 3, 2, 2, 6, 301
    N = F * M
    layout = LocalModelLayout(F=F, half_window=n, num_degree=2,
                              transient_degree=2, den_degree=2,
                              n_experiments=P, n_inputs=n_u)
    rng = np.random.default_rng(7)
    U_full = np.fft.rfft(rng.standard_normal((P, n_u, N)), axis=-1)
    if gap == "band":
        U_full[..., 200:230] = 0
    elif gap == "faint":  # not excited, but far from zero: the bound decides
        U_full[..., 200:230] *= 1e-9
    elif gap == "all":
        U_full[...] = 0
    elif gap == "one input":
        U_full[:, 1, 100:103] = 0
    spectra = OneSidedSpectra.from_records(np.fft.irfft(U_full, N, axis=-1),
                                           rng.standard_normal((P, 1, M)), F)
    reference = _excitation_reference(
        _one_sided_mean_energy(spectra.inputs, N), layout)
    for start, stop in [(0, 40), (40, 151), (0, M // 2 + 1)]:
        U, Y, bins = spectra.window_spectra(start, stop, n, [0])
        expected = (_relative_excitation(U, Y.shape[-1], bins, layout, reference)
                    > EXCITATION_TOL).all(axis=1)
        got = _excited_windows(U, Y.shape[-1], bins, layout, reference)
        np.testing.assert_array_equal(got, expected)
        if gap is None:
            assert expected.all()
    if gap in ("band", "faint"):
        assert not expected.all()


@pytest.mark.parametrize("relative", [1 - 1e-6, 1 + 1e-6, 1 - 1e-12, 1 + 1e-12])
@pytest.mark.parametrize("scale", [1.0, 2.0**-600, 2.0**600])
@pytest.mark.parametrize("band", [0, 1])
def test_excited_windows_at_the_tolerance(relative, scale, band):
    """A band whose window energies sit at the tolerance (``L m`` a hair
    above or below ``EXCITATION_TOL * reference``; band 1 with one fainter
    bin), the other band far above it: the shortcut must not clear the band
    where the window sums do not (a bound looser than ``L m`` by a factor,
    e.g. ``L + 1`` or a negative margin, fails here; the gap tests above only
    have energies far from the tolerance)."""
    F, n, B = 2, 3, 20
    layout = LocalModelLayout(F=F, half_window=n, num_degree=1,
                              transient_degree=1, den_degree=1)
    L, width = layout.window, B + 2 * n
    m = 0.37 * scale
    energy = np.full((layout.n_bands, width), m)
    energy[1, 9] = 0.5 * m  # one faint bin: its windows sum less than L m
    U = np.sqrt(energy).reshape(1, -1).astype(complex)
    reference = np.full(layout.n_bands, L * m)  # relative energy ~1: excited
    reference[band] = L * m / (EXCITATION_TOL * relative)
    bins = np.arange(B) + n
    expected = (_relative_excitation(U, width, bins, layout, reference)
                > EXCITATION_TOL).all(axis=1)
    got = _excited_windows(U, width, bins, layout, reference)
    np.testing.assert_array_equal(got, expected)
    if relative < 1 - 1e-9:  # below the tolerance everywhere
        assert not expected.any()
    elif relative > 1 + 1e-9:  # above it (except the faint bin's windows)
        assert expected.sum() == (B if band == 0 else B - L)


BACKENDS = ["numpy", pytest.param("numba", marks=pytest.mark.skipif(
    not _compiled.AVAILABLE, reason="numba not installed"))]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mimo", [False, True], ids=["siso", "mimo"])
def test_streamed_chunks_equal_fit_local_models(backend, mimo):
    """fit_one_sided in small chunks = fit_local_models on the full DFTs."""
    if mimo:
        u, y = mimo_data(3 * 2 * 1400 if backend == "numba" else 1500)
        layout = LocalModelLayout(F=3, half_window=20, num_degree=4,
                                  transient_degree=4, den_degree=7,
                                  n_experiments=2, n_inputs=2)
    else:
        u, y = siso_data(3 * 2 * 9000 if backend == "numba" else 1200)
        u, y = u[None, None], y[None, None]
        layout = LocalModelLayout(F=3, half_window=18, num_degree=4,
                                  transient_degree=4, den_degree=7)
    spectra = OneSidedSpectra.from_records(u, y, 3)
    output = y.shape[1] - 1
    reference = fit_local_models(spectra.full_inputs(), spectra.full_outputs(output),
                                 layout, return_cov=True, backend=backend,
                                 chunk_size=None if backend == "numba" else 37)
    streamed = fit_one_sided(spectra, layout, output=output, return_cov=True,
                             backend=backend,
                             chunk_size=1000 if backend == "numba" else 37)
    assert_same_fit(streamed, reference)


@pytest.mark.skipif(not _compiled.AVAILABLE, reason="needs numba")
@pytest.mark.parametrize("threads", [1, 2, 3, 16, 64, 128])
def test_stream_chunk_does_not_grow_with_the_threads(monkeypatch, threads):
    """A chunk is a multiple of the lanes times the threads when the memory
    budget holds that many windows; otherwise it gives every thread a lane
    group up to 1024 windows (``MAX_STREAM_FLOOR``) and grows no further with
    the thread count: with 64 threads a 4x4 fit's chunk was 6144 windows where
    the budget gives fewer than 96 (5.9 GB traced instead of 0.4)."""
    import lrmfrf.local_models as local_models

    floor = local_models.MAX_STREAM_FLOOR
    lanes = _compiled.LANES
    cases = [
        (LocalModelLayout(F=3, half_window=40, num_degree=2, transient_degree=2,
                          den_degree=2), 1),
        (LocalModelLayout(F=3, n_experiments=2, n_inputs=2, half_window=40,
                          num_degree=2, transient_degree=2, den_degree=2), 2),
        (LocalModelLayout(F=5, n_experiments=4, n_inputs=4, half_window=40,
                          num_degree=2, transient_degree=2, den_degree=2), 5),
    ]
    config = _compiled.numba.config
    for layout, rows in cases:
        monkeypatch.setattr(config, "NUMBA_NUM_THREADS", 1)
        single = stream_chunk_size(layout, rows)
        monkeypatch.setattr(config, "NUMBA_NUM_THREADS", threads)
        size = stream_chunk_size(layout, rows)
        quantum = lanes * threads
        assert size % lanes == 0 and lanes <= size <= max(single, floor)
        if single >= quantum:  # the budget holds a quantum: a multiple of it
            assert size % quantum == 0 and size > single - quantum
        else:  # a lane group per thread, up to the floor
            assert size >= min(quantum, floor - floor % lanes)


@pytest.mark.skipif(not _compiled.AVAILABLE, reason="needs numba")
def test_stream_chunk_keeps_to_a_small_budget(monkeypatch):
    """With a 1 MiB budget and one thread a chunk of the default SISO layout
    (about 4.4 kB a window, 119 windows in half the budget) is one lane group,
    and a 4x4, P = 4, F = 5 layout with four rows (about 0.2 MB a window) too:
    no 1024-window floor (0.2 GB here). With more threads a chunk gives each
    one a lane group, up to 1024 windows."""
    import lrmfrf.local_models as local_models

    monkeypatch.setattr(local_models, "CHUNK_BYTES", 2**20)
    monkeypatch.setattr(_compiled.numba.config, "NUMBA_NUM_THREADS", 1)
    siso = LocalModelLayout(F=3, half_window=18, num_degree=4, transient_degree=4,
                            den_degree=7)
    big = LocalModelLayout(F=5, n_experiments=4, n_inputs=4, half_window=18,
                           num_degree=4, transient_degree=4, den_degree=7)
    assert stream_chunk_size(siso, 1) == _compiled.LANES
    assert stream_chunk_size(big, 4) == _compiled.LANES
    # two threads: one lane group each, not one group for both
    monkeypatch.setattr(_compiled.numba.config, "NUMBA_NUM_THREADS", 2)
    assert stream_chunk_size(big, 4) == 2 * _compiled.LANES
    # 64 threads: at most the floor of 1024 windows, in whole lane groups
    monkeypatch.setattr(_compiled.numba.config, "NUMBA_NUM_THREADS", 64)
    assert stream_chunk_size(big, 4) == 1024 - 1024 % _compiled.LANES
    monkeypatch.setattr(local_models, "CHUNK_BYTES", 2**26)
    assert stream_chunk_size(siso, 1) > 1024  # the default budget: many groups


# --- the estimators ----------------------------------------------------------------


@pytest.mark.parametrize("Est", [LRMBeyondNyquist, LPMBeyondNyquist])
@pytest.mark.parametrize("case", ["siso", "siso P=2", "mimo", "scaled", "long"])
def test_fitted_attributes_equal_the_eager_computation(Est, case):
    """SISO, two experiments, 2x2 MIMO, records scaled far from 1, and a record
    long enough for the compiled kernel in several chunks (``long``)."""
    if case == "mimo":
        u, y = mimo_data()
        est = Est(half_window=20).fit(u, y, 3)
    elif case == "long":
        if not _compiled.AVAILABLE:
            pytest.skip("numba not installed")
        u, y = siso_data(3 * 2 * 9000)
        est = Est().fit(u, y, 3)
        assert stream_chunk_size(est.layout_) < y.size // 2 + 1  # several chunks
    else:
        u, y = siso_data(P=2 if case == "siso P=2" else 1)
        if case == "scaled":  # normalised by powers of two inside fit
            u, y = u * 2.0**-90, y * 2.0**100
        est = Est().fit(u, y, 3)
    check_against_eager(est, u, y)


def test_several_chunks_write_the_same_outputs(monkeypatch):
    """Outputs written chunk by chunk (7 windows each) = the eager computation
    with the same chunks (the numpy kernel's round-off follows its batch)."""
    import lrmfrf.local_models as local_models

    u, y = siso_data()
    monkeypatch.setattr(local_models, "default_chunk_size", lambda *a, **k: 7)
    est = LRMBeyondNyquist().fit(u, y, 3)
    check_against_eager(est, u, y)


@pytest.mark.filterwarnings("ignore::lrmfrf.exceptions.IdentifiabilityWarning")
@pytest.mark.parametrize("backend", BACKENDS)
def test_chunks_write_the_fast_grid_bit_for_bit(monkeypatch, backend):
    """The fitted arrays, written chunk by chunk with slices, are bit for bit
    the fast grid of the chunks' band values (one_sided_fast_grid of
    local_fit_, computed with the same chunks): 2x2, two experiments,
    records scaled far from 1 and an input gap (NaN bins), small chunks."""
    import lrmfrf.local_models as local_models

    monkeypatch.setattr(local_models, "resolve_backend", lambda *a, **k: backend)
    chunk = _compiled.LANES if backend == "numba" else 23
    monkeypatch.setattr(local_models, "stream_chunk_size", lambda *a, **k: chunk)
    monkeypatch.setattr(local_models, "default_chunk_size", lambda *a, **k: chunk)
    F, N = 3, 3 * 2 * 401
    u, y = mimo_data(N)
    U = np.fft.rfft(u, axis=-1)
    U[:, 1, 300:400] = 0  # windows without input 1 in a band: not valid
    u = np.fft.irfft(U, N, axis=-1) * 2.0**-90
    est = LRMBeyondNyquist(half_window=20).fit(u, y * 2.0**100, F)
    assert not est.valid_.all() and est.valid_.any()
    for o, fit in enumerate(est.local_fit_):
        for i in range(2):
            band = slice(i * F, (i + 1) * F)
            cases = [
                (est.frf_[o, i], one_sided_fast_grid(fit.system[:, band], N, F,
                                                     conj=True)),
                (est.frf_std_[o, i], np.sqrt(one_sided_fast_grid(
                    fit.system_var[:, band], N, F, conj=False))),
                (est.valid_[o, i], one_sided_fast_grid(
                    np.repeat(fit.well_posed[:, None], F, axis=1), N, F,
                    conj=False)),
            ]
            for j in range(2):
                cases.append((est.frf_cov_[o, i, j], one_sided_fast_grid(
                    np.diagonal(fit.system_cov[:, band, j * F:(j + 1) * F],
                                axis1=1, axis2=2), N, F, conj=True)))
            for actual, desired in cases:
                assert actual.dtype == desired.dtype
                assert actual.tobytes() == desired.tobytes()


def test_local_fit_is_computed_on_first_access():
    """A closed-form fit keeps no per-window parameters: local_fit_ comes from
    the stored one-sided spectra on first access, then stays (and survives
    pickling and a refit)."""
    u, y = siso_data()
    est = LRMBeyondNyquist().fit(u, y, 3)
    B, p = est.slow_frequencies_.size, est.n_params_
    held = [v for v in vars(est).values() if isinstance(v, np.ndarray)]
    assert all(B * p > v.size for v in held)
    source = est._local_fit_source_
    assert est._local_fit_cache_ is None
    assert source.spectra.nbytes == 16 * (u.size // 2 + 1 + y.size // 2 + 1)
    copy = pickle.loads(pickle.dumps(est))
    fit = est.local_fit_
    assert fit.theta.shape == (B, p)
    assert est.local_fit_ is fit and est._local_fit_source_ is None
    assert_same_fit(copy.local_fit_, fit)
    est.fit(u[::-1].copy(), y[::-1].copy(), 3)
    assert est.local_fit_ is not fit
    assert not hasattr(LRMBeyondNyquist(), "local_fit_")


@pytest.mark.filterwarnings("ignore:Sanathanan-Koerner used all")
def test_refinement_runs_from_the_new_representation():
    """sk_iterations > 0: the closed form on the full DFTs, refined, gives the
    fitted attributes; local_fit_ is the refined fit, kept from the fit."""
    u, y = siso_data()
    est = LRMBeyondNyquist(sk_iterations=3).fit(u, y, 3)
    assert est.n_sk_iter_ >= 1 and est._local_fit_source_ is None
    U, Y = dft(u)[None], dft(y)[None]
    closed = fit_local_models(U, Y, est.layout_, return_cov=True)
    refined = refine_local_models(
        U, Y, est.layout_, closed, sk_iterations=3, lm_iterations=0, tol=1e-6,
        guard=0.5, jump=5.0, keep_best=True, chunk_size=None, verbose=False,
    ).local_fit
    # the default std route scales the refined variance to the eiv noise level
    refined = calibrated_refined_fit(U, Y, est.layout_, closed, refined,
                                     est.std_method)
    assert_same_fit(est.local_fit_, refined)
    assert_close(est.frf_, one_sided_fast_grid(refined.system, u.size, 3, conj=True))
    assert_close(est.noise_variance_, refined.noise_var)
    # and from records far from unit scale
    big = LRMBeyondNyquist(sk_iterations=3).fit(u, y * 2.0**120, 3)
    assert_close(big.frf_, scale_by_power_of_two(est.frf_, 120))
    assert_same_fit(big.local_fit_, rescale_local_fit(est.local_fit_, 0, 120))
