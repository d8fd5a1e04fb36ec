"""The paper's comparison on the OAT-like stage: the issue's targets, fast tier.

The full statistics (>= 100 realisations, SNR and N sweeps) are in
benchmarks/paper_comparison.py and in the slow tests below.
"""

from __future__ import annotations

import numpy as np
import pytest

from lrmfrf.paper import (
    TABLE_I,
    compare_methods,
    on_grid,
    paper_experiment,
    table1_estimators,
)
from lrmfrf.plants import wafer_stage


@pytest.fixture(scope="module")
def stage():
    return wafer_stage()


def _runs(stage, name, n_runs, snr_db, seed):
    system = getattr(stage, name)
    rng = np.random.default_rng(seed)
    base = paper_experiment(system, rng=rng, snr_db=None)
    clean = base.y_l
    noise_std = np.sqrt(np.var(clean) / 10 ** (snr_db / 10))
    out = []
    for _ in range(n_runs):
        base.y_l = clean + noise_std * rng.standard_normal(clean.size)
        estimators = table1_estimators()
        summary = compare_methods(base, estimators,
                                  resonances=stage.resonance_frequencies_hz)
        out.append((summary, estimators))
    return base, out


def _check_targets(stage, name, n_runs, seed):
    _, runs = _runs(stage, name, n_runs, TABLE_I["snr_db"], seed)
    c = "cumulative_error_common"
    med = {m: np.median([s[m][c] for s, _ in runs]) for m in ("LRM", "LPM", "SA")}
    assert med["LRM"] <= 0.2 * med["LPM"]
    assert med["LRM"] <= 0.1 * med["SA"]
    above = {m: np.median([s[m]["median_relative_above"] for s, _ in runs])
             for m in ("LRM", "LPM")}
    assert above["LRM"] < above["LPM"]


@pytest.mark.parametrize("name", ["G_y4", "G_z"])
def test_lrm_beats_lpm_and_sa_at_45_db(stage, name):
    """Targets of the issue, 5 realisations (medians): LRM's cumulative error
    <= 0.2x LPM's and <= 0.1x SA's on SA's grid, and a lower median error
    above the slow Nyquist frequency. Measured margins are ~5x on each
    (benchmark), so 5 runs do not make this flaky."""
    _check_targets(stage, name, 5, seed=10)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["G_y4", "G_z"])
def test_lrm_beats_lpm_and_sa_at_45_db_many_runs(stage, name):
    _check_targets(stage, name, 100, seed=11)


def _std_ratio(stage, name, n_runs, seed):
    base, runs = _runs(stage, name, n_runs, TABLE_I["snr_db"], seed)
    estimates = np.array([e["LRM"].frf_ for _, e in runs])
    stds = np.array([e["LRM"].frf_std_ for _, e in runs])
    # unbiased spread around the MC mean (n_runs - 1)
    mc = np.sqrt(np.sum(np.abs(estimates - estimates.mean(0)) ** 2, axis=0)
                 / (n_runs - 1))
    predicted = np.sqrt(np.mean(stds**2, axis=0))
    return np.median(predicted[1:] / mc[1:])


@pytest.mark.parametrize("name", ["G_y4", "G_z"])
def test_lrm_std_ratio_on_the_stage(stage, name):
    """30 runs: the MC std per bin has ~13 % spread, the median over 600
    (correlated) bins ~3 %, so 0.9-1.1 tests the calibrated default
    (errors-in-variables sandwich; Lemma 2 gave 0.85-0.9 here)."""
    assert 0.9 <= _std_ratio(stage, name, 30, seed=12) <= 1.1


@pytest.mark.slow
@pytest.mark.parametrize("name", ["G_y4", "G_z"])
def test_lrm_std_ratio_on_the_stage_many_runs(stage, name):
    """200 runs: the issue's 0.95-1.05."""
    assert 0.95 <= _std_ratio(stage, name, 200, seed=13) <= 1.05


def test_lrm_error_falls_as_one_over_snr_while_lpm_saturates(stage):
    """20 dB more SNR: a noise-limited method's error falls 10x, a
    bias-limited one's barely moves. Thresholds 5x and 2x leave room for the
    spread of 8 runs."""
    medians = {}
    for snr in (45.0, 65.0):
        base, runs = _runs(stage, "G_y4", 8, snr, seed=14)
        for method in ("LRM", "LPM"):
            rel = [np.median(np.abs(e[method].frf_[1:] - base.frf_true[1:])
                             / np.abs(base.frf_true[1:])) for _, e in runs]
            medians[method, snr] = np.median(rel)
    assert medians["LRM", 45.0] / medians["LRM", 65.0] >= 5
    assert medians["LPM", 45.0] / medians["LPM", 65.0] <= 2


def test_on_grid_picks_exact_bins_only():
    grid = np.arange(11) * 10.0
    values = np.arange(11) * 1j
    np.testing.assert_array_equal(on_grid(grid, values, [0.0, 50.0, 100.0]),
                                  [0, 5j, 10j])
    with pytest.raises(ValueError, match="not bins of the given grid"):
        on_grid(grid, values, [55.0])
