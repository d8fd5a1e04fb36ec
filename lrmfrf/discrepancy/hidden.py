"""Hidden-effect experiments on the wafer stage, for tests and benchmarks.

Separate from the workflow on purpose: the true plants are built here with
python-control and a fine-rate lifting of the delay, not with the catalogue's
model surgery, so a bug shared by generator and workflow cannot hide itself.

An experiment draws an effect class and its parameters, builds the true
plant ``P_true`` (nominal stage channel ``y4`` plus the effect), closes the
loop with the stage controller, simulates ``P`` experiments with the paper's
settings (``N = 1200``, ``F = 3``, random-phase multisine of RMS 1.44 N, output
SNR ``snr_db`` per experiment) and returns the data together with the nominal
plant and controller, which is all ``diagnose`` gets.

Detectability. An effect is *clearly detectable* when its oracle whitened
gap, ``sqrt(mean_k |G_true(k) - G_nominal(k)|^2 / std(k)^2)`` with the
estimator's std on the same data, is at least ``min_gap`` (default 5). Draws
below that are redrawn (the strength parameter of a missing mode is its
participation, drawn in [0.1, 0.4]).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import control
import numpy as np

__all__ = [
    "EFFECT_CLASSES",
    "HiddenEffect",
    "HiddenExperiment",
    "draw_effect",
    "hidden_effect_experiment",
    "score",
]

EFFECT_CLASSES = ("gain", "delay", "low_pass", "missing_mode", "mode_shift")

#: Parameter tolerances of issue 6 (relative; damping +/-30 %).
TOLERANCES = {
    "gain": {"gain": 0.02},
    "delay": {"delay": 0.05},
    "low_pass": {"cutoff": 0.15},
    "missing_mode": {"frequency": 0.01, "damping": 0.30},
    "mode_shift": {"frequency": 0.01, "damping": 0.30},
}

_LIFT = 20  # fine steps per fast sample for the delay (25 us at Ts = 0.5 ms)


@dataclass(frozen=True)
class HiddenEffect:
    """An effect hidden in the true plant.

    Attributes
    ----------
    name : str
        One of :data:`EFFECT_CLASSES`.
    parameters : dict
        True parameters with the keys of the workflow's catalogue.
    extra : dict
        Further truth (e.g. a missing mode's participation).
    """

    name: str
    parameters: dict
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class HiddenExperiment:
    """Data and models of one hidden-effect experiment.

    Attributes
    ----------
    u_h : ndarray of shape (P, 1, N)
        ``P`` SISO experiments in the record convention (3-D, channels
        second).
    y_l : ndarray of shape (P, 1, M)
    F : int
    sample_time : float
    plant : control.StateSpace
        Nominal discrete plant ``u -> y4`` (what the engineer has).
    controller : control.StateSpace or None
        The stage's controller; ``None`` for open-loop data.
    true_plant : control.StateSpace
        Discrete true plant.
    true_system : control.StateSpace
        True measured system: the closed loop ``P_true / (1 + C P_true)``, or
        ``P_true`` for open-loop data.
    effects : tuple of HiddenEffect
        Empty for a no-effect experiment.
    oracle_gap : float
        Whitened RMS distance between the true and nominal closed-loop FRFs
        (estimator std of this data), or NaN if not computed.
    noise_std : ndarray of shape (P,)
    """

    u_h: np.ndarray
    y_l: np.ndarray
    F: int
    sample_time: float
    plant: control.StateSpace
    controller: control.StateSpace
    true_plant: control.StateSpace
    true_system: control.StateSpace
    effects: tuple
    oracle_gap: float
    noise_std: np.ndarray


def draw_effect(name: str, rng: np.random.Generator, stage) -> HiddenEffect:
    """Draw the parameters of one effect class (ranges of issue 6).

    delay 0.1-1.0 ms (multiples of Ts/20, fractional samples included); gain
    0.8-0.95 or 1.05-1.25; low-pass cutoff 0.3-3 kHz (log-uniform); missing
    mode 150-950 Hz, damping 0.5-3 %, at least 4 % away from the model's modes;
    mode shift 3-10 % up or down of one model mode's frequency (damping kept).
    ``"missing_mode_high"`` draws a missing mode in 400-950 Hz (above the
    slow Nyquist frequency of 333 Hz).
    """
    if name == "gain":
        gain = rng.uniform(0.8, 0.95) if rng.random() < 0.5 else rng.uniform(1.05, 1.25)
        return HiddenEffect("gain", {"gain": float(gain)})
    if name == "delay":
        step = stage.sample_time / _LIFT
        delay = step * rng.integers(round(0.1e-3 / step), round(1.0e-3 / step) + 1)
        return HiddenEffect("delay", {"delay": float(delay)})
    if name == "low_pass":
        cutoff = math.exp(rng.uniform(math.log(300.0), math.log(3000.0)))
        return HiddenEffect("low_pass", {"cutoff": float(cutoff)})
    if name in ("missing_mode", "missing_mode_high"):
        existing = np.array(stage.resonance_frequencies_hz)
        low = 400.0 if name == "missing_mode_high" else 150.0
        while True:
            frequency = rng.uniform(low, 950.0)
            if np.all(np.abs(existing / frequency - 1) > 0.04):
                break
        damping = rng.uniform(0.005, 0.03)
        participation = rng.uniform(0.1, 0.4)
        return HiddenEffect(
            "missing_mode",
            {"frequency": float(frequency), "damping": float(damping)},
            {"participation": float(participation)},
        )
    if name == "mode_shift":
        index = int(rng.integers(len(stage.modes)))
        mode = stage.modes[index]
        shift = rng.uniform(0.03, 0.10) * (1 if rng.random() < 0.5 else -1)
        return HiddenEffect(
            "mode_shift",
            {"frequency": float(mode.frequency_hz * (1 + shift)),
             "damping": float(mode.damping)},
            {"mode_index": index, "model_frequency": mode.frequency_hz,
             "relative_shift": float(shift)},
        )
    raise ValueError(f"unknown effect class {name!r}; use one of {EFFECT_CLASSES}.")


def hidden_effect_experiment(
    effects=None,
    *,
    rng=None,
    n_samples: int = 1200,
    F: int = 3,
    n_experiments: int = 4,
    rms: float = 1.44,
    snr_db: float = 45.0,
    min_gap: float = 5.0,
    max_draws: int = 20,
    stage=None,
    loop: str = "closed",
    excitation: str = "flat",
    steady_state: bool = False,
) -> HiddenExperiment:
    """Simulate closed- or open-loop data of a stage with hidden effect(s).

    Parameters
    ----------
    effects : str, sequence of str, sequence of HiddenEffect or None
        Effect classes to draw (e.g. ``"delay"`` or ``("delay",
        "missing_mode")``), fixed effects, or ``None`` for no effect.
    rng : int or numpy.random.Generator
    n_samples, F, n_experiments : int
        ``N``, downsampling factor, number of experiments ``P``.
    rms : float
        Multisine RMS in N.
    snr_db : float
        Output SNR ``var(y_l) / var(v_l)`` of each experiment in dB.
    min_gap : float
        Redraw until the oracle gap reaches this (0: no check).
    max_draws : int
    stage : WaferStage, optional
        Default :func:`lrmfrf.plants.wafer_stage`; e.g. a
        :func:`lrmfrf.plants.random_stage`.
    loop : {"closed", "open"}, default "closed"
        ``"closed"``: the data are of the true plant in the loop with the
        stage's controller (``u_h`` a disturbance force), the experiment's
        ``controller`` is that controller. ``"open"``: the data are of the true
        plant itself and ``controller`` is ``None`` (what ``diagnose`` gets).
    excitation : {"flat", "shaped"}, default "flat"
        ``"flat"``: random-phase multisines with a flat amplitude spectrum.
        ``"shaped"``: amplitudes ``1 / |G_nom(k)|`` of the NOMINAL system (the
        nominal plant in open loop, its closed loop otherwise), so that the
        nominal output spectrum is flat: what an engineer does in open loop,
        where a flat force gives an output dominated by the low-frequency
        motion and no SNR above it.
    steady_state : bool, default False
        Record the periodic steady state of each multisine
        (:func:`lrmfrf.simulate.periodic_state`; the system must be stable)
        instead of starting at rest.

    Returns
    -------
    HiddenExperiment
    """
    from ..estimators import LRMBeyondNyquist
    from ..plants import wafer_stage
    from ..signals import multisine
    from ..simulate import periodic_state, simulate, true_frf

    if loop not in ("closed", "open"):
        raise ValueError(f"`loop` must be 'closed' or 'open'; got {loop!r}.")
    if excitation not in ("flat", "shaped"):
        raise ValueError(
            f"`excitation` must be 'flat' or 'shaped'; got {excitation!r}."
        )
    rng = np.random.default_rng(rng)
    stage = wafer_stage() if stage is None else stage
    Ts = stage.sample_time
    nominal = stage.plant[0, 0]
    controller = stage.controller
    if effects is None:
        effects = ()
    elif isinstance(effects, str):
        effects = (effects,)
    for _ in range(max_draws):
        drawn = tuple(
            e if isinstance(e, HiddenEffect) else draw_effect(e, rng, stage)
            for e in effects
        )
        true_plant = _true_plant(stage, drawn)
        if loop == "open":
            system = true_plant
        else:
            try:
                system = _closed_loop(true_plant, controller)
            except ValueError:
                continue
        amplitude = None
        if excitation == "shaped":
            nominal_system = (
                nominal if loop == "open" else _closed_loop(nominal, controller)
            )
            size = np.abs(true_frf(nominal_system, n_samples))
            amplitude = 1.0 / np.maximum(size, 1e-6 * size.max())
        u = np.stack([multisine(n_samples, rms=rms, rng=rng, amplitude=amplitude)
                      for _ in range(n_experiments)])
        sims = [
            simulate(system, u[p], F, snr_db=snr_db, rng=rng,
                     x0=periodic_state(system, u[p]) if steady_state else None)
            for p in range(n_experiments)
        ]
        # P SISO experiments: 3-D (P, 1, N) and (P, 1, M) records
        u = u[:, None, :]
        y = np.stack([s.y_l for s in sims])[:, None, :]
        gap = math.nan
        if drawn and min_gap > 0:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                est = LRMBeyondNyquist().fit(u, y, F, sample_time=Ts)
            g_true = true_frf(system, n_samples)[1:]
            nominal_system = (
                nominal if loop == "open" else _closed_loop(nominal, controller)
            )
            g_nom = true_frf(nominal_system, n_samples)[1:]
            std = est.frf_std_[1:]
            keep = np.isfinite(std) & (std > 0)
            gap = float(np.sqrt(np.mean(np.abs(g_true - g_nom)[keep] ** 2
                                        / std[keep] ** 2)))
            if gap < min_gap:
                continue
        return HiddenExperiment(
            u_h=u, y_l=y, F=F, sample_time=Ts, plant=nominal,
            controller=None if loop == "open" else controller,
            true_plant=true_plant, true_system=system,
            effects=drawn, oracle_gap=gap,
            noise_std=np.array([s.noise_std for s in sims]),
        )
    raise RuntimeError(
        f"no detectable, stable draw of {effects} in {max_draws} attempts; lower "
        "min_gap or raise the SNR."
    )


def score(experiment: HiddenExperiment, report) -> dict:
    """Compare a diagnosis with the hidden truth.

    Returns
    -------
    dict
        ``named``: names of the report's findings; ``any_finding``;
        ``all_named``: every hidden effect is among the findings;
        ``exact``: the findings are exactly the hidden effects (no extra,
        ambiguous or model-error finding); ``parameters_ok``: every matched
        effect's parameters are within :data:`TOLERANCES`; ``errors``:
        relative parameter errors; ``gap_before``, ``gap_after``,
        ``gap_ok`` (``gap_after <= 1.3`` and ``gap_before / gap_after >= 3``).
    """
    named = [f.effect for f in report.findings]
    truth = [e.name for e in experiment.effects]
    errors, params_ok = {}, True
    for effect in experiment.effects:
        matches = [f for f in report.findings if f.effect == effect.name]
        if not matches:
            params_ok = False
            continue
        best = min(matches, key=lambda f: _relative_error(effect, f))
        for key, tol in TOLERANCES[effect.name].items():
            error = abs(best.parameters[key] / effect.parameters[key] - 1)
            errors[f"{effect.name}.{key}"] = error
            params_ok &= bool(error <= tol)
    ratio = report.gap_before / max(report.gap_after, 1e-12)
    return {
        "truth": truth,
        "named": named,
        "any_finding": bool(named),
        "all_named": all(t in named for t in truth),
        "exact": sorted(named) == sorted(truth),
        "parameters_ok": bool(params_ok and truth),
        "errors": errors,
        "gap_before": report.gap_before,
        "gap_after": report.gap_after,
        "gap_ok": bool(report.gap_after <= 1.3 and ratio >= 3.0),
        "oracle_gap": experiment.oracle_gap,
    }


def _relative_error(effect, finding) -> float:
    return sum(
        abs(finding.parameters[key] / effect.parameters[key] - 1)
        for key in TOLERANCES[effect.name]
    )


# ---------------------------------------------------------------------------
# True plants (independent of the workflow's model surgery)
# ---------------------------------------------------------------------------


def _true_plant(stage, effects) -> control.StateSpace:
    from ..plants import Mode, modal_plant

    modes = list(stage.modes)
    series = control.tf([1.0], [1.0])
    gain = 1.0
    delay = 0.0
    for effect in effects:
        p = effect.parameters
        if effect.name == "gain":
            gain *= p["gain"]
        elif effect.name == "delay":
            delay += p["delay"]
        elif effect.name == "low_pass":
            tau = 1.0 / (2 * math.pi * p["cutoff"])
            series = series * control.tf([1.0], [tau, 1.0])
        elif effect.name in ("missing_mode", "missing_mode_high"):
            part = effect.extra["participation"]
            modes.append(Mode(p["frequency"], p["damping"], part, part))
        elif effect.name == "mode_shift":
            index = effect.extra["mode_index"]
            old = modes[index]
            modes[index] = Mode(p["frequency"], p["damping"], old.participation_y4,
                                old.participation_z)
        else:
            raise ValueError(f"unknown effect {effect.name!r}")
    continuous = modal_plant(stage.mass, modes, outputs=("y4",),
                             suspension=getattr(stage, "suspension", None))
    continuous = control.ss(control.series(control.ss(series), continuous)) * gain
    return _lifted_zoh(continuous, stage.sample_time, delay)


def _lifted_zoh(system, sample_time: float, delay: float) -> control.StateSpace:
    """ZOH discretisation with an input delay that is a multiple of Ts/_LIFT.

    The input is held over ``_LIFT`` fine steps (exact ZOH at the fine rate);
    the delay shifts it by whole fine steps; the fine-step matrices are
    summed into the fast-rate ``x[k+1] = Phi x + G0 u[k-d] + G1 u[k-d-1]``.
    """
    fine = control.sample_system(system, sample_time / _LIFT, method="zoh")
    A, B = np.asarray(fine.A), np.asarray(fine.B)
    C, D = np.asarray(fine.C), np.asarray(fine.D)
    steps = int(round(delay / (sample_time / _LIFT)))
    whole, frac = divmod(steps, _LIFT)
    n = A.shape[0]
    powers = [np.eye(n)]
    for _ in range(_LIFT):
        powers.append(A @ powers[-1])
    Phi = powers[_LIFT]
    # fine step i (0-based) of the interval sees u[k-d-1] for i < frac
    G1 = sum((powers[_LIFT - 1 - i] @ B for i in range(frac)), np.zeros((n, 1)))
    G0 = sum((powers[_LIFT - 1 - i] @ B for i in range(frac, _LIFT)), np.zeros((n, 1)))
    lags = whole + (1 if frac else 0)
    size = n + lags
    Ad = np.zeros((size, size))
    Bd = np.zeros((size, 1))
    Ad[:n, :n] = Phi
    if lags:
        Bd[n, 0] = 1.0
        for i in range(1, lags):
            Ad[n + i, n + i - 1] = 1.0
    for gain, lag in ((G0, whole), (G1, whole + 1)):
        if not np.any(gain):
            continue
        if lag == 0:
            Bd[:n] += gain
        else:
            Ad[:n, n + lag - 1] += gain[:, 0]
    Cd = np.zeros((1, size))
    Cd[0, :n] = C[0]
    if np.any(D):
        raise ValueError("the generator's plants are strictly proper.")
    return control.ss(Ad, Bd, Cd, np.zeros((1, 1)), sample_time)


def _closed_loop(plant, controller) -> control.StateSpace:
    loop = control.feedback(plant, control.ss(controller), sign=-1)
    if np.max(np.abs(np.linalg.eigvals(loop.A))) >= 1.0:
        raise ValueError("unstable closed loop")
    return loop
