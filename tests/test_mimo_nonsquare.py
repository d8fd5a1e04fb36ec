"""Non-square MIMO (n_y != n_u) on a random stage, against known truths: std
calibration with one and with n_u experiments, predict's band sum, experiments
whose inputs are linearly dependent, and the plant from a non-square closed
loop that feeds back non-adjacent outputs (benchmarks/mimo_nonsquare.py has
the larger Monte Carlo)."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import control
import numpy as np
import pytest

from lrmfrf import (LPMBeyondNyquist, LRMBeyondNyquist, LRMBeyondNyquistCV,
                    plant_from_closed_loop)
from lrmfrf.plants import random_stage
from lrmfrf.signals import multisine, orthogonal_multisines
from lrmfrf.simulate import frequency_grid, simulate, true_frf


@pytest.fixture(scope="module")
def stage():
    return random_stage(3, mimo=True)[0]


def _independent_inputs(n_u, N, rng):
    return np.stack([multisine(N, rng=rng) for _ in range(n_u)])


@pytest.mark.parametrize("P", [1, 3])
def test_two_by_three_std_matches_monte_carlo(stage, P):
    """G[0:2, 0:3] (2 outputs, 3 inputs), F = 2, M = 200, 40 dB per output,
    20 noise realisations with a fixed input: P = 3 orthogonal multisines
    (default window) or one record of three multisines (half window 31).
    Per entry, the median over bins of the predicted std (RMS over runs) over
    the Monte-Carlo std is within 0.85-1.2 (measured 1.01-1.16 with P = 1,
    1.08-1.12 with P = 3; the std of a 20-run std is 16 % per bin, much less
    for the median over ~190 bins). The std of the other output row (its own
    noise level; swapped rows: up to 1.22 with P = 1, 1.43 with P = 3) or the
    Lemma 2 std (0.81-1.00 and 0.79-0.85) fails it, with P = 1 by one entry
    only; the entries of one row have nearly the same std here (equal input
    powers), so the test does not see an input mix-up."""
    F, M, runs = 2, 200, 20
    N = F * M
    system = stage.G[0:2, 0:3]
    if P == 3:
        u, est = orthogonal_multisines(3, N, rng=0), LRMBeyondNyquist()
    else:
        u = _independent_inputs(3, N, np.random.default_rng(0))[None]
        est = LRMBeyondNyquist(half_window=31)
    fits, stds = [], []
    for run in range(runs):
        y = np.stack([simulate(system, u[p], F, snr_db=40, rng=10 * run + p).y_l
                      for p in range(P)])
        est.fit(u, y, F)
        assert est.frf_.shape == est.frf_std_.shape == (2, 3, N // 2 + 1)
        fits.append(est.frf_)
        stds.append(est.frf_std_)
    fits, stds = np.array(fits), np.array(stds)
    spread = np.sqrt(np.mean(np.abs(fits - fits.mean(axis=0)) ** 2, axis=0))
    predicted = np.sqrt(np.mean(stds**2, axis=0))
    ratio = np.median((predicted / spread)[..., 1:-1], axis=-1)
    assert np.all((ratio > 0.85) & (ratio < 1.2)), ratio
    # noise-limited: the mean over the runs is within a few MC std / sqrt(runs)
    truth = true_frf(system, N)
    bias = np.abs(fits.mean(axis=0) - truth) / spread
    assert np.all(np.median(bias[..., 1:-1], axis=-1) < 0.6)


@pytest.mark.parametrize("n_y, n_u", [(3, 2), (2, 3), (1, 2), (2, 1)])
def test_predict_is_the_band_sum_of_the_fitted_frf(stage, n_y, n_u):
    """predict = ifft of Y_l(k) = (1/F) sum_f G(k + fM) U(k + fM) with the
    fitted frf_, entry (o, i) applied to input i for output o."""
    F, M = 3, 200
    N = F * M
    u = orthogonal_multisines(n_u, N, rng=1) if n_u > 1 else \
        multisine(N, rng=1)[None, None]
    y = np.stack([simulate(stage.G[0:n_y, 0:n_u], u[p], F, snr_db=60, rng=p).y_l
                  for p in range(u.shape[0])])
    est = LRMBeyondNyquist(half_window=20).fit(u, y, F)
    full = np.concatenate([est.frf_, est.frf_[..., 1:(N + 1) // 2][..., ::-1].conj()],
                          axis=-1)  # (n_y, n_u, N), two-sided
    U = np.fft.fft(u, axis=-1)  # (P, n_u, N)
    Y = np.einsum("oik,pik->pok", full, U).reshape(u.shape[0], n_y, F, M).mean(axis=2)
    expected = np.fft.ifft(Y, axis=-1).real
    predicted = est.predict(u)
    assert predicted.shape == y.shape
    np.testing.assert_allclose(predicted, expected, rtol=0,
                               atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize("second", [lambda u: u, lambda u: -2.5 * u])
def test_dependent_experiments_are_refused_with_the_fix(stage, second):
    """Two experiments with the same (or a scaled) input and n_u = 2 give the
    equations of one experiment: 37 < 42 parameters per window at the default
    settings. It used to fit without a warning, valid everywhere (on these
    inputs, noise-free: median relative error 0.25 with frf_std_ 1e-13
    relative; 60 dB: 2.7 with a std of 1.3 relative, against 0.16 with
    independent inputs; measured in review). The error names the half window
    and independent experiments; the inputs are not modified."""
    F, M = 3, 200
    N = F * M
    u1 = _independent_inputs(2, N, np.random.default_rng(2))
    u = np.stack([u1, second(u1)])
    y = np.stack([simulate(stage.G[0:3, 0:2], u[p], F, snr_db=60, rng=p).y_l
                  for p in range(2)])
    before = u.copy(), y.copy()
    with pytest.raises(ValueError, match=r"only 1 of them is independent.*"
                       r"Increase half_window to at least 21.*different inputs"):
        LRMBeyondNyquist().fit(u, y, F)
    np.testing.assert_array_equal(u, before[0])
    np.testing.assert_array_equal(y, before[1])
    # the CV estimator skips the candidates it makes infeasible
    cv = LRMBeyondNyquistCV(half_windows=(18, 24), num_degrees=(4,),
                            den_degrees=(7,)).fit(u, y, F)
    assert cv.best_params_["half_window"] == 24
    # wide enough for one experiment: accepted (and LPM's smaller model too)
    assert LRMBeyondNyquist(half_window=21).fit(u, y, F).valid_.all()
    # LPM: the scaled copy's noise is 2.5x the first's (proportional to its
    # output) and the level estimate of two dependent experiments sits at its
    # bound: fitted pooled, and said so
    if np.array_equal(u[1], u1):
        assert LPMBeyondNyquist().fit(u, y, F).valid_.all()
    else:
        with pytest.warns(UserWarning, match="pooled noise level"):
            assert LPMBeyondNyquist().fit(u, y, F).valid_.all()


def test_repeated_siso_experiments_and_independent_ones_stay_accepted():
    """One input: a repeated experiment only needs the one-experiment window,
    which the default has; P = 3 with a third input that sums the other two
    counts as 2 experiments, enough for n_u = 3 at the default window."""
    rng = np.random.default_rng(3)
    F, N = 3, 600
    u = multisine(N, rng=rng)
    LRMBeyondNyquist().fit([u, u, 2 * u], list(rng.standard_normal((3, N // F))), F)
    u3 = _independent_inputs(3, N, rng)
    v3 = _independent_inputs(3, N, rng)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        LRMBeyondNyquist().fit(np.stack([u3, v3, u3 + v3]),
                               rng.standard_normal((3, 2, N // F)), F)


@pytest.mark.parametrize("rate", ["fast", "slow"])
def test_plant_from_non_square_closed_loop_feeding_back_outputs_0_and_2(stage,
                                                                        rate):
    """Plant G[0:3, 0:2] of the stage (3 outputs, 2 inputs) in a loop whose 2x2
    dynamic controller reads outputs 0 and 2, loop gain up to 6.6: the plant
    from the exact closed-loop FRF to 1e-10 of max |P| (measured 9e-12 fast,
    2e-14 slow). Fast: G_eq from control.feedback; slow: the forward map per
    slow bin (tests/test_closed_loop.py)."""
    from test_closed_loop import _slow_equivalent

    plant = stage.G[0:3, 0:2]
    ts, F, N = plant.dt, 3, 600
    truth = true_frf(plant, N)
    scale = np.abs(truth).max()
    mix = 3.0 / scale * np.array([[1.0, 0.3], [-0.2, 0.8]])
    dt = ts if rate == "fast" else F * ts
    controller = control.ss(np.diag([0.8, 0.8]), np.eye(2), 0.2 * mix, mix, dt)
    if rate == "fast":
        select = np.zeros((2, 3))
        select[0, 0] = select[1, 2] = 1
        loop = control.feedback(plant, controller * control.ss([], [], [], select, ts))
        closed = true_frf(loop, N)
    else:
        closed = _slow_equivalent(true_frf(plant, N, one_sided=False),
                                  true_frf(controller, N // F, one_sided=False),
                                  [0, 2])
    fit = SimpleNamespace(
        frequencies_=frequency_grid(N, ts), frf_=closed,
        frf_std_=np.zeros(closed.shape), valid_=np.ones(closed.shape, bool),
        sample_time_=ts, downsampling_factor_=F, n_inputs_=2, n_outputs_=3)
    result = plant_from_closed_loop(fit, controller, [0, 2])
    assert result.frf_.shape == (3, 2, N // 2 + 1) and result.loop_rate_ == rate
    assert result.valid_.all()
    assert np.abs(result.frf_ - truth).max() < 1e-10 * scale
    frd = result.to_frd()
    assert (frd.noutputs, frd.ninputs) == (3, 2)


@pytest.mark.parametrize("exponent", [-565, 530])
def test_independent_experiments_at_any_amplitude(stage, exponent):
    """The estimators fit records of any finite amplitude exactly (scaled by a
    power of two); the count of independent experiments must too. Records near
    1e-170 or 1e160 underflowed or overflowed in the Gram matrix of the
    records: 0 independent experiments, refused as all-zero inputs."""
    F, M = 3, 200
    N = F * M
    rng = np.random.default_rng(4)
    u = np.stack([_independent_inputs(2, N, rng) for _ in range(2)])
    y = np.stack([simulate(stage.G[0:3, 0:2], u[p], F, snr_db=60, rng=p).y_l
                  for p in range(2)])
    reference = LRMBeyondNyquist().fit(u, y, F)
    scaled = LRMBeyondNyquist().fit(np.ldexp(u, exponent), np.ldexp(y, exponent), F)
    np.testing.assert_allclose(scaled.frf_, reference.frf_, rtol=1e-12, atol=0)
    # a scaled copy is still dependent at that amplitude
    dependent = np.ldexp(np.stack([u[0], -2.5 * u[0]]), exponent)
    with pytest.raises(ValueError, match=r"only 1 of them is independent"):
        LRMBeyondNyquist().fit(dependent, np.ldexp(y, exponent), F)


def test_dependent_experiments_are_named_before_the_p_experiment_count():
    """LPM half_window=5, n_u = 2, the same input twice: too few equations
    for 2 experiments as well (22 < 24). The message must be the dependent
    one, whose half window (10) is enough; the 2-experiment count's advice
    (half_window 6, "at least 3 experiments") was refused again once
    followed."""
    F, M = 3, 200
    N = F * M
    u1 = _independent_inputs(2, N, np.random.default_rng(5))
    u = np.stack([u1, u1])
    y = np.random.default_rng(6).standard_normal((2, 3, M))
    with pytest.raises(ValueError, match=r"only 1 of them is independent.*"
                       r"Increase half_window to at least 10\b"):
        LPMBeyondNyquist(half_window=5).fit(u, y, F)
    assert LPMBeyondNyquist(half_window=10).fit(u, y, F).frf_.shape == (3, 2, N // 2 + 1)


def test_repeated_siso_experiments_need_the_one_experiment_window():
    """SISO is not exempt: at F = 6 the default LRM window (37 equations) is
    too small for one experiment (42 parameters), and the same multisine
    passed twice used to be fitted, valid everywhere (random_stage(3), 60 dB,
    10 runs: median relative error 3.2 with a std 0.37x the error, against
    0.035 with two different multisines; measured in review). The advice
    (half window 21) is accepted once followed."""
    F, M = 6, 300
    N = F * M
    u = multisine(N, rng=1)
    y = list(np.random.default_rng(7).standard_normal((2, M)))
    with pytest.raises(ValueError, match=r"only 1 of them is independent.*"
                       r"Increase half_window to at least 21\b"):
        LRMBeyondNyquist().fit([u, u], y, F)
    assert LRMBeyondNyquist(half_window=21).fit([u, u], y, F).valid_.all()
    LRMBeyondNyquist().fit([u, multisine(N, rng=2)], y, F)  # different inputs


def test_an_all_zero_experiment_is_named_in_the_dependence_message():
    """An experiment without input (e.g. a failed actuator record) counts
    for none: it was fitted silently before (n_u = 2, F = 3, 60 dB: median
    relative error 2.65 with frf_std_ 1.4 relative, valid everywhere;
    measured in review), and the
    refusal must not call it a repeated or scaled excitation only."""
    F, M = 3, 200
    N = F * M
    u1 = _independent_inputs(2, N, np.random.default_rng(8))
    y = np.random.default_rng(9).standard_normal((2, 2, M))
    with pytest.raises(ValueError, match=r"only 1 of them is independent.*"
                       r"or its input is zero"):
        LRMBeyondNyquist().fit(np.stack([u1, np.zeros_like(u1)]), y, F)


@pytest.mark.parametrize("shape, F, half_window", [((1, 1), 6, None),
                                                   ((3, 2), 3, None),
                                                   ((3, 2), 3, 21)])
def test_a_copy_shifted_by_whole_slow_samples_is_dependent(stage, shape, F,
                                                           half_window):
    """The same excitation shifted by whole slow samples (F fast samples; e.g.
    one period of a periodic multisine cut at another phase) has at every
    bin the aliased input vector of the original times a phase: no new
    equation on G. The Gram matrix of the records did not see it (the shifted
    record is nearly orthogonal to the original), and it was fitted, valid
    everywhere (60 dB: SISO F = 6, a shift of one slow sample, median
    relative error 0.34 against 0.035 with two different multisines and
    frf_std_ 0.67x the error; n_u = 2, F = 3: 0.77 against 0.24, 0.73x;
    measured in review). A shift that is not a whole number of slow samples
    is a different experiment (the bands see different phases); a window
    wide enough for one experiment accepts the shifted copy."""
    n_y, n_u = shape
    M = 200
    N = F * M
    rng = np.random.default_rng(10)
    u1 = _independent_inputs(n_u, N, rng)
    system = stage.G[0:n_y, 0:n_u]
    y1 = simulate(system, u1, F, snr_db=60, rng=0).y_l
    y = np.stack([y1, np.roll(y1, 2, axis=-1)])  # (outputs do not matter here)
    shifted = np.stack([u1, np.roll(u1, 2 * F, axis=-1)])
    est = LRMBeyondNyquist() if half_window is None else \
        LRMBeyondNyquist(half_window=half_window)
    if half_window is None:
        with pytest.raises(ValueError, match=r"only 1 of them is independent.*"
                           r"Increase half_window to at least 21\b"):
            est.fit(shifted, y, F)
    else:
        assert est.fit(shifted, y, F).valid_.all()
    # not a whole number of slow samples: two experiments
    est.fit(np.stack([u1, np.roll(u1, 2 * F + 1, axis=-1)]), y, F)
    # the count from the estimator's spectra equals the one without them
    from lrmfrf._validation import check_records
    from lrmfrf.local_models import OneSidedSpectra

    three = np.stack([u1, _independent_inputs(n_u, N, rng),
                      np.roll(u1, F, axis=-1)])
    records = check_records(three, np.concatenate([y, y[:1]]), F)
    spectra = OneSidedSpectra.from_records(records.u, records.y, F).inputs
    expected = 2 if 3 <= F * n_u else 3  # more than F n_u: not counted per bin
    assert records.independent_experiments() == expected
    assert records.independent_experiments(spectra) == expected


def test_different_inputs_that_miss_bands_are_not_called_dependent():
    """Two different records that excite only the slow band (F = 6) share a
    direction at every bin, as a shifted copy does, but because the input
    misses bands, not because the experiments repeat: the fit reports the
    bins it cannot identify (as before the per-bin count) instead of
    refusing the experiments as dependent."""
    from lrmfrf import IdentifiabilityWarning

    F, M = 6, 300
    N = F * M

    def slow_band_only(seed):
        spectrum = np.zeros(N // 2 + 1, complex)
        spectrum[1:M // 2] = np.exp(2j * np.pi * np.random.default_rng(seed)
                                    .random(M // 2 - 1))
        return np.fft.irfft(spectrum, N)

    y = list(np.random.default_rng(11).standard_normal((2, M)))
    with pytest.warns(IdentifiabilityWarning):
        est = LRMBeyondNyquist().fit([slow_band_only(1), slow_band_only(2)], y, F)
    assert not est.valid_.any()


def test_experiments_on_interleaved_bins_are_not_called_dependent(stage):
    """Zippered multisines, one input at a time (experiment p drives input p
    at the bins = p mod 2): at every slow bin only one experiment has input,
    so the per-bin rank is 1, but every window sees both experiments, and
    the fit is as accurate as with orthogonal multisines (2x2, F = 3, 60 dB,
    5 noise runs: median relative error 0.186 against 0.187; measured in
    review). The per-bin count refused it as dependent; only bins where
    every experiment has input tell dependence."""
    F, M = 3, 200
    N = F * M
    bins = np.arange(1, N // 2 + 1)
    rng = np.random.default_rng(12)
    u = np.zeros((2, 2, N))
    for p in range(2):
        u[p, p] = multisine(N, bins=bins[bins % 2 == p], rng=rng)
    system = stage.G[0:2, 0:2]
    y = np.stack([simulate(system, u[p], F, snr_db=60, rng=p).y_l
                  for p in range(2)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        est = LRMBeyondNyquist().fit(u, y, F)
    assert est.valid_.all()
    error = np.abs(est.frf_ - true_frf(system, N)) / np.abs(true_frf(system, N))
    assert np.median(error) < 0.3
    # the same records shifted by one slow sample in the second experiment
    # are still refused as dependent where both have input
    both = np.stack([u[0] + u[1], np.roll(u[0] + u[1], F, axis=-1)])
    with pytest.raises(ValueError, match="only 1 of them is independent"):
        LRMBeyondNyquist().fit(both, y, F)
