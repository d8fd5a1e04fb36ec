"""Per-band selection of LRMBeyondNyquistCV (per_band=True, bands=...)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import frf_of, resonant_system, simulate_resonant

from lrmfrf import LRMBeyondNyquist, multisine
from lrmfrf.estimators._bands import region_bounds, region_weights
from lrmfrf.estimators.selection import LRMBeyondNyquistCV

N, F = 600, 3
M = N // F
TS = 0.5e-3
GRID = {"half_windows": (8, 12), "num_degrees": (2,), "den_degrees": (0, 4)}


@pytest.fixture(scope="module")
def record():
    rng = np.random.default_rng(11)
    u = multisine(N, rng=rng)
    y = simulate_resonant(u, F, 0.002, rng)
    return u, y


def test_one_band_is_the_global_choice(record):
    u, y = record
    glob = LRMBeyondNyquistCV(**GRID).fit(u, y, F, sample_time=TS)
    band = LRMBeyondNyquistCV(**GRID, per_band=True, bands=1).fit(
        u, y, F, sample_time=TS)
    assert band.band_params_ == [glob.best_params_]
    np.testing.assert_array_equal(band.frf_, glob.frf_)
    np.testing.assert_array_equal(band.frf_std_, glob.frf_std_)


def test_regions_take_their_own_setting_and_blend_at_the_edges(record):
    """The modes (120 Hz and 520 Hz, aliased to 147 Hz) lie in slow bins
    30-50 (3.3 Hz per bin): the region 100-200 Hz must keep a rational
    model (R_e = 4; a polynomial is bias-limited there, as in
    test_selection), and frf_ equals each region's own fit away from the
    edges and a convex combination of the two next to them."""
    u, y = record
    cv = LRMBeyondNyquistCV(**GRID, per_band=True, bands=(100.0, 200.0)).fit(
        u, y, F, sample_time=TS)
    assert len(cv.band_params_) == 3
    assert cv.band_params_[1]["den_degree"] == 4
    np.testing.assert_allclose(cv.band_frequencies_[[0, -1]], [0.0, 101 / (N * TS)])
    slow = np.arange(N // 2 + 1) % M
    slow = np.where(slow > M // 2, M - slow, slow)
    bounds = cv.band_bounds_
    ramp = min(GRID["half_windows"]) / 2
    for r, est in enumerate(cv.band_estimators_):
        inner = (slow >= bounds[r] + ramp) & (slow < bounds[r + 1] - ramp)
        np.testing.assert_array_equal(cv.frf_[inner], est.frf_[inner])
    for e in bounds[1:-1]:
        near = np.abs(slow + 0.5 - e) < ramp
        r = int(np.searchsorted(bounds, e)) - 1
        a, b = cv.band_estimators_[r].frf_, cv.band_estimators_[r + 1].frf_
        # on the segment between the two fits: |x-a| + |x-b| = |a-b|
        gap = np.abs(cv.frf_ - a) + np.abs(cv.frf_ - b) - np.abs(a - b)
        assert np.all(np.abs(gap[near]) <= 1e-12 * np.abs(a[near]).max())


def test_weights_are_a_partition_of_unity():
    bounds = region_bounds(4, 101, np.arange(101.0))
    for ramp in (1, 6, 13):
        w = region_weights(bounds, ramp)
        np.testing.assert_allclose(w.sum(axis=0), 1.0, atol=1e-12)
        assert np.all((w >= 0) & (w <= 1))
        # continuity: neighbouring bins differ by at most 1/ramp
        assert np.max(np.abs(np.diff(w, axis=1))) <= 1.0 / ramp + 1e-12


def test_window_wide_regions_are_no_worse_than_global_on_the_resonant_system(
        record):
    """On the two-mode test system at low noise, with regions about as wide as
    the largest window (4 here), the per-band estimate's median error is
    within 10 % of the global pick's (10 % for the blend at the edges).
    Narrower regions add selection noise: the automatic count (8 regions of
    13 bins here, tuned on the cluster stages of the benchmark) let smooth
    regions choose R_e = 0 and gave 1.13x on this record, which is why the
    docstring recommends per_band only for stages with distinct regions."""
    u, y = record
    G = frf_of(*resonant_system(), N)
    glob = LRMBeyondNyquistCV(**GRID).fit(u, y, F)
    band = LRMBeyondNyquistCV(**GRID, per_band=True, bands=4).fit(u, y, F)
    e_glob = np.median(np.abs(glob.frf_ - G)[1:] / np.abs(G[1:]))
    e_band = np.median(np.abs(band.frf_ - G)[1:] / np.abs(G[1:]))
    assert e_band <= 1.1 * e_glob


def test_bad_bands_are_rejected(record):
    u, y = record
    with pytest.raises(ValueError, match="per_band=True"):
        LRMBeyondNyquistCV(bands=3).fit(u, y, F)
    with pytest.raises(ValueError, match="between 1 and 101 regions"):
        LRMBeyondNyquistCV(**GRID, per_band=True, bands=500).fit(u, y, F)
    with pytest.raises(ValueError, match="strictly between 0 and the slow Nyquist"):
        LRMBeyondNyquistCV(**GRID, per_band=True, bands=(0.4,)).fit(u, y, F)
    with pytest.raises(ValueError, match="increasing"):
        LRMBeyondNyquistCV(**GRID, per_band=True, bands=(0.1, 0.05)).fit(u, y, F)
    with pytest.raises(TypeError, match="`bands` must be None"):
        LRMBeyondNyquistCV(**GRID, per_band=True, bands="low").fit(u, y, F)
    with pytest.raises(TypeError, match="`per_band` must be True or False"):
        LRMBeyondNyquistCV(per_band="yes").fit(u, y, F)


def test_predict_uses_the_blended_frf(record):
    u, y = record
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cv = LRMBeyondNyquistCV(**GRID, per_band=True, bands=3).fit(u, y, F)
    full = cv._fast_frf(N)
    np.testing.assert_array_equal(full[: N // 2 + 1], cv.frf_)
    assert not np.array_equal(cv.frf_, cv.best_estimator_.frf_) or len(
        {tuple(p.values()) for p in cv.band_params_}) == 1
    pred = cv.predict(u)
    assert pred.shape == y.shape
    assert LRMBeyondNyquist().get_params()  # base class untouched


def test_per_band_on_a_mimo_record_takes_one_setting_per_region():
    """Two inputs, two outputs: a region's setting is chosen on the windows
    of both output rows; one region is the global choice and the blended
    matrix keeps the (n_y, n_u, K) shape."""
    rng = np.random.default_rng(12)
    u = np.array([multisine(N, rng=rng) for _ in range(2)])
    y0 = simulate_resonant(u, F, 0.0, rng)
    y = np.array([y0[0] + 0.5 * y0[1], 0.3 * y0[0] + y0[1]])
    y = y + 0.002 * rng.standard_normal(y.shape)
    glob = LRMBeyondNyquistCV(**GRID).fit(u, y, F)
    one = LRMBeyondNyquistCV(**GRID, per_band=True, bands=1).fit(u, y, F)
    assert one.band_params_ == [glob.best_params_]
    np.testing.assert_array_equal(one.frf_, glob.frf_)
    four = LRMBeyondNyquistCV(**GRID, per_band=True, bands=4).fit(u, y, F)
    assert four.frf_.shape == (2, 2, N // 2 + 1)
    assert len(four.band_params_) == 4
    # inside a region (away from the ramps) frf_ is that region's own fit
    lo, hi = four.band_bounds_[1], four.band_bounds_[2]
    centre = (lo + hi) // 2
    fit = four.band_estimators_[1]
    np.testing.assert_allclose(four.frf_[..., centre], fit.frf_[..., centre],
                               rtol=1e-12)
    # the blended covariance keeps frf_std_ == sqrt(diag(frf_cov_)), ramps too
    diag = np.sqrt(np.real(np.diagonal(four.frf_cov_, axis1=1, axis2=2)))
    diag = np.moveaxis(diag, -1, 1)  # (n_y, n_u, K)
    ok = four.valid_
    np.testing.assert_allclose(diag[ok], four.frf_std_[ok], rtol=1e-12)


# --- per slow bin, by the predicted std (bands=None) ------------------------------


def test_smoothed_scores_read_the_mirrored_bins_at_both_ends():
    """Slow bins 0..M//2: bin -k is bin k and bin k > M//2 is M - k, for even
    and odd M (known answers by hand); an inf spreads over its neighbours."""
    from lrmfrf.estimators._bands import smooth_scores

    row = np.arange(6.0)[None]  # M = 10: bins 0..5
    out = smooth_scores(row, 1, 10)
    # bin 0: (1 + 0 + 1) / 3; bin 5: (4 + 5 + 4) / 3 (bin 6 is bin 4)
    np.testing.assert_allclose(out[0], [2 / 3, 1, 2, 3, 4, 13 / 3], rtol=1e-15)
    odd = smooth_scores(np.arange(5.0)[None], 1, 9)  # M = 9: bins 0..4, 5 is 4
    np.testing.assert_allclose(odd[0, -1], (3 + 4 + 4) / 3, rtol=1e-15)
    bad = row.copy()
    bad[0, 2] = np.inf
    assert np.array_equal(np.isinf(smooth_scores(bad, 1, 10)[0]),
                          [False, True, True, True, False, False])


def test_score_weights_favour_the_smallest_std_and_sum_to_one():
    from lrmfrf.estimators._bands import score_weights

    scores = np.array([[0.0, 0.0, np.inf, np.inf],
                       [0.1, -0.1, 0.0, np.inf],
                       [1.0, 0.0, 0.5, np.inf]])
    w = score_weights(scores, 30.0)
    np.testing.assert_allclose(w[:, :3].sum(axis=0), 1.0, rtol=1e-14)
    # known answer: exp(-30 * 0.1) relative weight, and below the floor -> 0
    np.testing.assert_allclose(w[1, 0] / w[0, 0], np.exp(-3.0), rtol=1e-14)
    assert w[2, 0] == 0.0 and w[0, 2] == 0.0  # exp(-30) < 1e-6; inf
    assert w[1, 2] == 1.0 - w[2, 2] and w[1, 2] > w[2, 2]
    assert np.isnan(w[:, 3]).all()  # no candidate valid: no weights


def test_std_scores_average_log_std_over_the_aliased_bins():
    from types import SimpleNamespace

    from lrmfrf.estimators._bands import std_scores

    N, Fs = 60, 3  # M = 20
    std = np.exp(np.arange(N // 2 + 1) / 10.0)
    valid = np.ones(N // 2 + 1, dtype=bool)
    valid[7] = False
    est = SimpleNamespace(frf_std_=std, valid_=valid)
    score = std_scores([est], N, Fs)[0]
    # by hand: of the fast bins 0..30 (M = 20), slow bin 3 fixes 3 and 23
    # (j mod 20 = 3) and 17 (j mod 20 = 17 = 20 - 3, its mirror); the stds
    # over 2**5, the binary exponent of the largest valid one (e**3 = 20.1)
    np.testing.assert_allclose(score[3], np.log(std[[3, 17, 23]] / 32).mean(),
                               rtol=1e-14)
    # slow bin 7 holds the invalid fast bin 7: inf (the candidate is out there)
    assert np.isinf(score[7]) and np.isfinite(score[6])


def test_per_bin_choice_with_one_candidate_is_that_fit(record):
    u, y = record
    grid = {"half_windows": (12,), "num_degrees": (2,), "den_degrees": (4,)}
    glob = LRMBeyondNyquistCV(**grid).fit(u, y, F)
    band = LRMBeyondNyquistCV(**grid, per_band=True).fit(u, y, F)
    assert band.band_params_ == [glob.best_params_]
    np.testing.assert_array_equal(band.band_weights_[:, glob.valid_[:M // 2 + 1]],
                                  1.0)
    np.testing.assert_array_equal(band.frf_, glob.frf_)
    np.testing.assert_array_equal(band.frf_std_, glob.frf_std_)
    assert not hasattr(band, "band_bounds_")


def test_per_bin_choice_blends_with_weights_summing_to_one(record):
    u, y = record
    cv = LRMBeyondNyquistCV(**GRID, per_band=True).fit(u, y, F)
    w = cv.band_weights_
    assert w.shape == (len(cv.band_params_), M // 2 + 1)
    np.testing.assert_allclose(w.sum(axis=0), 1.0, rtol=1e-12)
    # frf_ is the weighted sum of the fits on the fast grid
    from lrmfrf.estimators._bands import to_fast_grid

    fast = np.stack([to_fast_grid(wi, N, F) for wi in w])
    expect = sum(fw * est.frf_ for fw, est in zip(fast, cv.band_estimators_,
                                                  strict=True))
    ok = cv.valid_
    np.testing.assert_allclose(cv.frf_[ok], expect[ok], rtol=1e-12)
    # refitting changes nothing (no state carried over from the first fit)
    again = LRMBeyondNyquistCV(**GRID, per_band=True).fit(u, y, F)
    np.testing.assert_array_equal(again.frf_, cv.frf_)


def test_per_bin_choice_on_a_mimo_record():
    rng = np.random.default_rng(12)
    u = np.array([multisine(N, rng=rng) for _ in range(2)])
    y0 = simulate_resonant(u, F, 0.0, rng)
    y = np.array([y0[0] + 0.5 * y0[1], 0.3 * y0[0] + y0[1]])
    y = y + 0.002 * rng.standard_normal(y.shape)
    cv = LRMBeyondNyquistCV(**GRID, per_band=True).fit(u, y, F)
    assert cv.frf_.shape == cv.frf_std_.shape == (2, 2, N // 2 + 1)
    np.testing.assert_allclose(cv.band_weights_.sum(axis=0), 1.0, rtol=1e-12)
    diag = np.sqrt(np.real(np.diagonal(cv.frf_cov_, axis1=1, axis2=2)))
    diag = np.moveaxis(diag, -1, 1)
    ok = cv.valid_
    np.testing.assert_allclose(diag[ok], cv.frf_std_[ok], rtol=1e-12)


def _cluster_records(seeds):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from generalisation_selection import per_band_table

    rows = per_band_table(seeds)
    ratio = np.array([r["rms_per_band"] / r["rms_best_global"] for r in rows])
    rigid = np.array([r["rigid_per_band"] / r["rigid_best_global"] for r in rows])
    cluster = np.array([r["cluster_per_band"] / r["cluster_best_global"]
                        for r in rows])
    return ratio, rigid, cluster


def test_per_bin_choice_beats_the_best_single_setting_on_cluster_stages():
    """Issue 15 item 4, fast version: on the cluster stages of the benchmark
    (rigid body below 100 Hz, three modes aliasing onto one slow frequency;
    seeds 1 and 2, both outputs, 40 dB) the per-slow-bin choice's RMS
    relative error is on average <= 0.9x that of the best single setting of
    the grid for each record (measured 0.78x), and its median error in the
    rigid-body region and around the cluster is, in the median over the
    records, no worse than that setting's (measured 0.90 and 0.95)."""
    ratio, rigid, cluster = _cluster_records([1, 2])
    assert ratio.mean() <= 0.9, ratio
    assert np.median(rigid) <= 1.0 and np.median(cluster) <= 1.0, (rigid, cluster)


@pytest.mark.slow
def test_per_bin_choice_on_held_out_cluster_stages():
    """The same on the held-out seeds 11-18 (16 records): mean RMS ratio
    <= 0.9 (measured 0.857), region medians <= 1 (0.91 and 0.65)."""
    ratio, rigid, cluster = _cluster_records(range(11, 19))
    assert ratio.mean() <= 0.9, ratio
    assert np.median(rigid) <= 1.0 and np.median(cluster) <= 1.0, (rigid, cluster)


def test_cluster_mimo_stage_redraws_an_unstable_closed_loop(monkeypatch):
    """The 2x2 cluster stages of ``--per-band --mimo`` are redrawn until the
    closed loop is stable: :func:`mimo_wafer_stage` raises ``ValueError`` for
    a controller that does not stabilise it (its closed-loop poles are
    checked) and the draw is redrawn. Seed 18's first draw has a pole at
    1.00085: the stage returned is its second draw, stable. (A check of the
    returned stage's poles, added on the belief that ``mimo_wafer_stage``
    did not check them, could never fail and was removed.)"""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import generalisation_selection as bench

    real, made = bench.mimo_wafer_stage, []

    def recording(**kwargs):
        try:
            stage = real(**kwargs)
        except ValueError as error:
            made.append(error)
            raise
        made.append(stage)
        return stage

    monkeypatch.setattr(bench, "mimo_wafer_stage", recording)
    stage, _ = bench.cluster_mimo_stage(18)
    assert len(made) == 2, made
    assert isinstance(made[0], ValueError) and "not stabilise" in str(made[0])
    assert stage is made[1]
    assert np.max(np.abs(np.linalg.eigvals(stage.G.A))) < 1.0


def test_per_bin_choice_leaves_out_candidates_with_one_residual_dof(record):
    """GRID's (8, 2, 2, 4) has 17 equations for 16 parameters: the default
    ``"pmse"`` criterion identifies it, ``"gaic"`` (2 dof) does not. Its
    Lemma-2 std (one residual dof) is too noisy to weigh by, so the per-bin
    blend leaves it out: the same candidates and the same FRF as with
    ``"gaic"``, whose identifiable set is the blend's."""
    u, y = record
    pmse = LRMBeyondNyquistCV(**GRID, per_band=True).fit(u, y, F)
    gaic = LRMBeyondNyquistCV(**GRID, per_band=True, criterion="gaic").fit(
        u, y, F)
    params = pmse.cv_results_["params"]
    thin = [i for i, p in enumerate(params) if p["half_window"] == 8
            and p["den_degree"] == 4]
    assert np.isfinite(np.asarray(pmse.cv_results_["criterion"])[thin]).all()
    assert not set(thin) & set(pmse.band_index_.tolist())
    np.testing.assert_array_equal(pmse.band_index_, gaic.band_index_)
    np.testing.assert_array_equal(pmse.frf_, gaic.frf_)


def test_worst_stage_mean_groups_by_seed_or_by_seed_and_loop():
    """``benchmarks/generalisation_selection.worst_stage_mean`` (the selection
    benchmarks' "worst stage"): ``parts=1`` averages a seed's four records
    (and the wafer's two), ``parts=2`` a seed's closed- or open-loop pair."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from generalisation_selection import worst_stage_mean

    ratios = {"1000/closed/G_y4": 1.6, "1000/closed/G_z": 1.0,
              "1000/open/G_y4": 1.0, "1000/open/G_z": 1.0,
              "1001/closed/G_y4": 1.2, "1001/closed/G_z": 1.2,
              "1001/open/G_y4": 1.2, "1001/open/G_z": 1.0,
              "wafer/closed/G_y4": 1.1, "wafer/closed/G_z": 1.3}
    rows = [{"label": label, "pmse": x} for label, x in ratios.items()]
    # seeds: 1000 -> 1.15, 1001 -> 1.15, wafer -> 1.2
    assert worst_stage_mean(rows, "pmse") == pytest.approx(1.2, abs=1e-12)
    # seed and loop: 1000/closed -> 1.3 (the largest), 1001/closed 1.2
    assert worst_stage_mean(rows, "pmse", parts=2) == pytest.approx(1.3, abs=1e-12)
