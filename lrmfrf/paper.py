"""The paper's experiment on the OAT-like stage: settings and method comparison.

One place for the settings of the paper's Table I (``Experimental settings``)
and the comparison of LRM, LPM and SA on the equivalent systems ``G_y4`` and
``G_z``; the demo, the benchmark and the notebook use it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .estimators import LPMBeyondNyquist, LRMBeyondNyquist, SpectralAnalysis
from .metrics import cumulative_error, error_summary
from .signals import multisine
from .simulate import simulate, true_frf

__all__ = [
    "TABLE_I",
    "PaperExperiment",
    "table1_estimators",
    "paper_experiment",
    "compare_methods",
    "on_grid",
]

#: Settings of the paper's Table I and its excitation (RMS 1.44 N, 45 dB).
TABLE_I = {
    "sample_time": 0.5e-3,
    "F": 3,
    "n_samples": 1200,
    "rms": 1.44,
    "snr_db": 45.0,
}


def table1_estimators() -> dict:
    """The three methods with the paper's settings.

    LRM: ``R_g = R_t = 4``, ``R_e = 7``, ``n = 18``; LPM: ``R_g = R_t = 2``,
    ``n = 18``; SA: 11 Hann segments of 200 samples with 100 overlap.
    """
    return {
        "LRM": LRMBeyondNyquist(
            half_window=18, num_degree=4, transient_degree=4, den_degree=7
        ),
        "LPM": LPMBeyondNyquist(half_window=18, num_degree=2),
        "SA": SpectralAnalysis(segment_length=200, overlap=100),
    }


@dataclass
class PaperExperiment:
    """One simulated experiment with the paper's settings.

    Attributes
    ----------
    u_h : ndarray of shape (N,)
    y_l : ndarray of shape (M,)
    frf_true : ndarray of shape (N//2+1,), complex
        True FRF on the fast DFT grid.
    frequencies : ndarray of shape (N//2+1,)
        Hz.
    F : int
    sample_time : float
    """

    u_h: np.ndarray
    y_l: np.ndarray
    frf_true: np.ndarray
    frequencies: np.ndarray
    F: int
    sample_time: float

    @property
    def slow_nyquist(self) -> float:
        """Nyquist frequency of the slow output in Hz."""
        return 1.0 / (2 * self.F * self.sample_time)


def paper_experiment(
    system,
    *,
    rng=None,
    snr_db: float | None = TABLE_I["snr_db"],
    n_samples: int = TABLE_I["n_samples"],
    F: int = TABLE_I["F"],
    rms: float = TABLE_I["rms"],
    u_h: np.ndarray | None = None,
) -> PaperExperiment:
    """Simulate one record: random-phase multisine, system at rest, white noise.

    Parameters
    ----------
    system : control.StateSpace
        Discrete SISO system at the fast sample time (e.g. ``stage.G_y4``).
    rng : int, numpy.random.Generator or None
        Draws the multisine phases (unless ``u_h`` is given) and the noise.
    snr_db : float or None, default=45
        Output SNR in dB; ``None`` for noise-free data.
    n_samples, F, rms
        Record length, downsampling factor and input RMS.
    u_h : ndarray of shape (n_samples,), optional
        A fixed input (for Monte-Carlo runs over noise only).

    Returns
    -------
    PaperExperiment
    """
    rng = np.random.default_rng(rng)
    if u_h is None:
        u_h = multisine(n_samples, rms=rms, rng=rng)
    sim = simulate(system, u_h, F, snr_db=snr_db, rng=rng)
    sample_time = float(system.dt)
    N = u_h.size
    return PaperExperiment(
        u_h=sim.u_h,
        y_l=sim.y_l,
        frf_true=true_frf(system, N),
        frequencies=np.arange(N // 2 + 1) / (N * sample_time),
        F=F,
        sample_time=sample_time,
    )


def on_grid(grid: np.ndarray, values: np.ndarray, frequencies: np.ndarray):
    """``values`` (given on ``grid``) at ``frequencies``: exact bins only.

    Parameters
    ----------
    grid : ndarray of shape (K,)
        Ascending frequencies (Hz) of ``values``.
    values : ndarray of shape (K,)
    frequencies : ndarray of shape (J,)
        Frequencies that must be bins of ``grid`` (no interpolation).

    Returns
    -------
    ndarray of shape (J,)
    """
    index = np.clip(np.searchsorted(grid, frequencies), 0, grid.size - 1)
    if not np.allclose(grid[index], frequencies, rtol=1e-12, atol=0):
        raise ValueError(
            "The requested frequencies are not bins of the given grid. Compare "
            "on a common grid (e.g. the coarser one)."
        )
    return values[index]


def compare_methods(
    experiment: PaperExperiment, estimators: dict, *, resonances=None
) -> dict:
    """Fit every estimator and summarise its errors against the true FRF.

    Each method is scored on its own grid (median and RMS relative error below
    and above the slow Nyquist frequency, near resonances, cumulative error
    eq. (CPSD)) and, for a fair comparison with spectral analysis, all methods
    also on the coarsest grid (``cumulative_error_common``, normalised by the
    coarse grid's record length).

    Parameters
    ----------
    experiment : PaperExperiment
    estimators : dict of str to estimator
        Unfitted estimators (they are fitted in place).
    resonances : array-like of float, optional
        Resonance frequencies in Hz for the "near resonance" error.

    Returns
    -------
    dict of str to dict
        Per method, the :func:`lrmfrf.metrics.error_summary` keys plus
        ``cumulative_error_common``.
    """
    fitted = {
        name: est.fit(
            experiment.u_h, experiment.y_l, experiment.F,
            sample_time=experiment.sample_time,
        )
        for name, est in estimators.items()
    }
    coarse = min(fitted.values(), key=lambda est: est.frequencies_.size)
    common = coarse.frequencies_
    grid, truth_fast = experiment.frequencies, experiment.frf_true
    true_common = on_grid(grid, truth_fast, common)
    results = {}
    for name, est in fitted.items():
        truth = on_grid(grid, truth_fast, est.frequencies_)
        summary = error_summary(
            truth, est.frf_, est.frequencies_,
            slow_nyquist=experiment.slow_nyquist, resonances=resonances,
            valid=est.valid_, n_samples=2 * (est.frequencies_.size - 1),
        )
        estimate_common = on_grid(est.frequencies_, est.frf_, common)
        valid_common = np.isfinite(estimate_common)
        summary["cumulative_error_common"] = float(cumulative_error(
            true_common, estimate_common, 2 * (common.size - 1), valid=valid_common
        )[-1])
        results[name] = summary
    return results
