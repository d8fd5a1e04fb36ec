"""``diagnose``: where do model and measurement disagree, and why?

The public entry point only: the input checks and preparation are in
:mod:`._inputs`, the search (greedy, prune, refit, debias) in :mod:`._search`.
"""

from __future__ import annotations

import numpy as np

from .._blas_threads import single_threaded_blas
from .._validation import check_bool, check_records, check_rng, renamed_keyword
from ._inputs import MIN_BINS as MIN_BINS  # importable from here as before
from ._inputs import (
    check_band,
    check_calibration,
    check_catalogue,
    check_models,
    check_settings,
    comparison_problem,
    fit_estimator,
    resolve_sample_time,
)
from ._inputs import measured_system as measured_system
from ._search import Calibrator, run_search
from .detect import Calibration
from .effects import Effect
from .report import DiagnosisReport

__all__ = ["diagnose"]


def diagnose(
    plant,
    u_h,
    y_l,
    F: int,
    *,
    sample_time: float | None = None,
    controller=None,
    estimator=None,
    effects: list[Effect] | None = None,
    alpha: float = 0.01,
    effect_alpha: float = 1e-3,
    ic_margin: float = 6.0,
    max_effects: int = 3,
    calibration_runs: int = 10,
    calibration: Calibration | None = None,
    smoothing_bins: int = 9,
    band=None,
    debias_rounds: int = 2,
    rng: int | np.random.Generator | None = None,
    random_state=None,
    window=None,
    steady_state: bool = False,
) -> DiagnosisReport:
    """Find what is missing from a plant model, given a (slow-rate) measurement.

    The measured FRF (fast grid, beyond the slow Nyquist frequency, from
    ``estimator``) is compared with the model; if they differ by more than the
    calibrated noise, effects from the catalogue are fitted to the whitened
    discrepancy, the best is accepted when significant and unambiguous
    (greedy, up to ``max_effects``), all accepted effects are refitted jointly
    (then corrected for the estimator's bias, ``debias_rounds``), and an
    unnamed low-order model error is fitted when nothing in the catalogue
    explains the gap. ``gap_before`` and ``gap_after`` are measured with the
    same std, calibrated at the updated model.

    Parameters
    ----------
    plant : control.StateSpace or control.TransferFunction
        Model of the plant, ``n_y`` outputs and ``n_u`` inputs as the records
        (SISO or MIMO): discrete with ``dt == sample_time`` (taken as the ZOH
        discretisation of a continuous model) or continuous (discretised
        with ZOH).
    u_h : array-like of shape (N,), (n_u, N) or (P, n_u, N), or list of records
        Fast-rate input(s); several experiments (a list or a 3-D array; a 2-D
        array is one record, channels first) give better statistics. MIMO:
        one experiment with ``n_u`` uncorrelated inputs at once is enough.
    y_l : array-like of shape (M,), (n_y, M) or (P, n_y, M), or list of records
        Slow-rate output(s), ``M = N / F``.
    F : int
        Downsampling factor.
    sample_time : float, optional
        Fast sample time in s. Default: the ``dt`` of ``plant`` if it is
        discrete, else of ``controller``; one of the three must give it. A
        value that contradicts a discrete model's ``dt`` is an error.
    controller : control.StateSpace or control.TransferFunction, optional
        Discrete feedback controller (``dt == sample_time``; ``n_u`` outputs,
        ``n_y`` inputs, ``u = u_h - C y``). The measured system is then
        ``P (I + C P)^-1`` (eq. EquivalentSystems) and effects are named at
        the plant level. Without it the measured system is ``P``.
    estimator : estimator, optional
        FRF estimator with ``fit(u_h, y_l, F, *, sample_time)`` and ``frf_``,
        ``frf_std_``, ``valid_`` (default ``LRMBeyondNyquist()``, its half
        window raised where the default would leave its local fits fewer than
        10 residual degrees of freedom, e.g. at ``F >= 4`` with one
        experiment; see ``_inputs.default_estimator``). An already
        fitted estimator is used as is (it must match the data sizes); an
        unfitted one is cloned and fitted to the data.
    effects : list of Effect, optional
        Catalogue (default :func:`default_effects`). A per-channel effect
        with an explicit ``channel`` must name one of the data's channels
        (``ValueError`` otherwise, before any calibration).
    alpha : float, default=0.01
        False-alarm level of the global test (no findings when it passes).
    effect_alpha : float, default=1e-3
        Level of the likelihood-ratio test that accepts an effect.
    ic_margin : float, default=6.0
        BIC margin by which the best candidate must beat every other; else the
        step is reported as ``"ambiguous"`` and nothing is added. A
        per-channel effect of a MIMO plant (``input_gain``, ``output_gain``,
        ``input_low_pass``, ``input_delay``) must beat its all-channel version
        (``gain``, ``low_pass``, ``delay``) by it; within it the all-channel
        one is named.
    max_effects : int, default=3
        Most effects accepted in the greedy search; ``0`` only tests (the
        report then has no findings, whatever the p-values say).
    calibration_runs : int, default=10
        Simulated experiments used to calibrate the tests against the
        estimator (see :func:`lrmfrf.discrepancy.detect.calibrate`). ``0``
        trusts the estimator's std and uses a heuristic correlation inflation
        (documented fallback, with a warning).
    calibration : Calibration, optional
        Reuse the nominal-model calibration of an earlier report
        (``report.calibration``) with the same inputs, plant and bins.
    smoothing_bins : int, default=9
        Width in bins of the moving mean that makes the discrepancy spectrum
        (called ``window`` before issue 12).
    band : (float, float), optional
        Compare only the estimator's bins with ``low <= f <= high`` (Hz), e.g.
        ``(0, slow_nyquist)`` to mimic a slow-rate-only analysis.
    debias_rounds : int, default=2
        Rounds of the final, bias-corrected joint refit: the estimator bias
        calibrated at the updated model (large at sharp resonances, where it
        flattens the peak) is subtracted from the measurement, the accepted
        effects are refitted and the bias is recalibrated at the new model.
        Without it the damping of a 0.8 %-damped mode comes out ~30 % high.
        ``0`` skips it; it needs ``calibration_runs >= 2``.
    rng : int, numpy.random.Generator or None
        Seed or generator of the calibration noise (as ``rng`` in
        :func:`lrmfrf.signals.multisine` and :func:`lrmfrf.simulate.simulate`).
    random_state, window : optional
        Deprecated names of ``rng`` and ``smoothing_bins`` (they warn with a
        ``FutureWarning`` and are removed in the next release).
    steady_state : bool, default False
        The records are the periodic steady state of periodic inputs (the
        transient periods were discarded), not a start from rest: the
        calibration simulates them the same way (the estimator's bias at
        sharp resonances differs between the two; calibrating a steady-state
        record from rest gave false alarms on open-loop suspended stages).
        Needs a stable measured system.

    Returns
    -------
    DiagnosisReport

    Notes
    -----
    MIMO. The FRF entries ``(n_y, n_u, K)`` are compared together: the
    whitened residual is all entries' bins, each entry with its own
    calibrated bias and std scale; the tests use the bin power (mean over
    entries of ``|w|^2``) with the correlation inflation counted against
    the ``n_y n_u K`` terms (:mod:`lrmfrf.discrepancy.detect`). Gain, delay,
    low-pass and the unnamed model error act on all inputs alike; a missing
    mode has a rank-one residue ``c b^T``; a mode shift moves a mode of the
    whole plant (:mod:`lrmfrf.discrepancy.effects`).

    Raises
    ------
    TypeError, ValueError
        For a plant or controller of the wrong type, dimensions (the plant
        must have the records' ``n_y`` outputs and ``n_u`` inputs) or sample
        time, no sample
        time (neither given nor a discrete model's ``dt``), an unstable closed
        loop of the given plant and controller, data the estimator cannot fit,
        or too few usable bins. (Candidate models tried by the search that
        would make the loop unstable are skipped and listed in the report's
        ``skipped_candidates``, not an error.)

    Examples
    --------
    >>> import control, numpy as np
    >>> from lrmfrf.discrepancy import diagnose
    >>> from lrmfrf.signals import multisine
    >>> from lrmfrf.simulate import simulate
    >>> Ts = 1e-3
    >>> model = control.c2d(control.tf([1.0], [1e-3, 1.0]), Ts)
    >>> u = [multisine(600, rng=i) for i in range(2)]  # two experiments
    >>> y = [simulate(control.ss(model), ui, 3, snr_db=40, rng=i).y_l
    ...      for i, ui in enumerate(u)]
    >>> report = diagnose(model, u, y, 3, rng=0,
    ...                   calibration_runs=6)  # doctest: +SKIP
    """
    rng = renamed_keyword(rng, random_state, new="rng", old="random_state")
    smoothing_bins = renamed_keyword(smoothing_bins, window, new="smoothing_bins",
                                     old="window", default=9)
    records = check_records(u_h, y_l, F)
    # SISO: (P, N) and (P, M) stacks, responses (K,); MIMO: (P, n_u, N) and
    # (P, n_y, M), responses (n_y, n_u, K). The layers below follow the shape.
    shape = (records.n_outputs, records.n_inputs)
    entry_shape = () if records.is_siso else shape
    u, y = (records.u[:, 0], records.y[:, 0]) if records.is_siso else (
        records.u, records.y)
    F = records.F
    sample_time, source = resolve_sample_time(sample_time, plant, controller)
    settings = check_settings(
        alpha=alpha, effect_alpha=effect_alpha, ic_margin=ic_margin,
        max_effects=max_effects, calibration_runs=calibration_runs,
        smoothing_bins=smoothing_bins, debias_rounds=debias_rounds,
    )
    steady_state = check_bool(steady_state, "steady_state")
    catalogue = check_catalogue(effects, shape)
    rng = check_rng(rng)
    nominal, controller = check_models(plant, controller, sample_time, source,
                                       shape)
    band = check_band(band)
    fitted, template = fit_estimator(estimator, u, y, F, sample_time)
    problem, bins = comparison_problem(fitted, band, controller, sample_time,
                                       entry_shape)
    # the section the fits inside count themselves into (shared with other threads)
    with single_threaded_blas():
        calibrator = Calibrator(template, fitted, u, F, sample_time, bins, controller,
                                problem, settings.calibration_runs,
                                settings.smoothing_bins, rng,
                                steady_state=steady_state)
        cal0 = calibration if calibration is not None else calibrator(nominal)
        check_calibration(cal0, bins.size, entry_shape)
        return run_search(problem, nominal, catalogue, calibrator, cal0, settings,
                          controller=controller, F=F)
