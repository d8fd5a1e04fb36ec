"""Per-channel effects of ``diagnose`` on random 2x2 stages: rates.

For every seed, ``random_stage(seed, mimo=True)`` draws a four-corner plate
(its own ``F``), cut to the 2x2 stage of corners 1 and 2
(:func:`lrmfrf.discrepancy.hidden_mimo.two_by_two_stage`), closed loop
(diagonal lead-PID, flat multisines, from rest) and open loop (suspended,
input ``j`` shaped by ``1 / |P_jj|``, periodic steady state), as
``benchmarks/generalisation_diagnose.py --mimo`` builds them. ONE experiment
of two uncorrelated multisines, 40 dB output SNR. Cases:

- ``input_gain``: one input's gain (channel drawn), 0.8-0.95 or 1.05-1.25
  (the ranges of :func:`lrmfrf.discrepancy.hidden.draw_effect` for ``gain``);
- ``output_gain``: one output's (sensor) gain, same ranges;
- ``input_low_pass``: one input through a first-order low-pass, 300-3000 Hz
  log-uniform (``low_pass``'s range);
- ``input_delay``: one input delayed by 0.1-1.0 ms in steps of Ts / 20
  (``delay``'s range; fractional samples included);
- ``gain``: every input's gain alike
  (:func:`lrmfrf.discrepancy.hidden_mimo.mimo_hidden_effect_experiment`);
- ``none``: nothing hidden (same generator).

The per-channel true plants are built here with python-control
(``diag(outputs) P diag(inputs)``, a lag on one input; ZOH; a delayed input
by lifting the ZOH at Ts / 20), not with the catalogue's ``apply``; the simulation copies ``mimo_hidden_effect_experiment``
(which has no per-channel effects). A record is ``right`` when the findings
are exactly the hidden effect, on its channel, with the parameter within
the tolerance of :data:`lrmfrf.discrepancy.hidden.TOLERANCES` (gain 2 %,
cutoff 15 %, delay 5 %); ``named`` when the effect and channel are among the findings.

``--catalogue old`` runs the five all-channel effects only (the catalogue
before the per-channel effects), for comparison.

Usage::

    python benchmarks/diagnose_channels.py --seeds 1000-1007
    python benchmarks/diagnose_channels.py --seeds 1000-1003 --catalogue old
    python benchmarks/diagnose_channels.py --seeds 1000-1003 --sizing siso

Writes ``benchmarks/results/diagnose_channels_<catalogue>_seeds<a>-<b>.csv``
(one row per record) and the summary table as ``.txt`` beside it.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
import warnings
from pathlib import Path

import control
import numpy as np

CASES = ("input_gain", "output_gain", "input_low_pass", "gain", "none",
         "input_delay")
LOOPS = ("closed", "open")
TOLERANCE = {"gain": 0.02, "cutoff": 0.15, "delay": 0.05}


def _static(values) -> control.StateSpace:
    return control.ss(np.zeros((0, 0)), np.zeros((0, 2)), np.zeros((2, 0)),
                      np.diag(values))


def true_plant(stage, case: str, channel: int, value: float) -> control.StateSpace:
    """Continuous true plant with one channel's effect (python-control)."""
    plant = control.ss(stage.plant_continuous())
    scale = np.ones(2)
    if case == "input_gain":
        scale[channel] = value
        return plant * _static(scale)
    if case == "output_gain":
        scale[channel] = value
        return _static(scale) * plant
    if case == "input_low_pass":
        tau = 1.0 / (2 * math.pi * value)
        unit = control.ss(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)),
                          [[1.0]])
        lags = [control.ss(control.tf([1.0], [tau, 1.0])) if j == channel else unit
                for j in range(2)]
        return plant * control.append(*lags)
    raise ValueError(case)


def delayed_input(stage, channel: int, delay: float) -> control.StateSpace:
    """Discrete true plant with input ``channel`` delayed by ``delay`` (a
    multiple of Ts / 20), lifted from the ZOH at the fine step as the
    hidden-effect generator builds delays (not the catalogue's exact expm)."""
    from lrmfrf.discrepancy.hidden_mimo import _lifted_zoh

    delays = [delay if j == channel else 0.0 for j in range(2)]
    return _lifted_zoh(control.ss(stage.plant_continuous()), stage.sample_time,
                       delays)


def simulate_record(stage, continuous, rng, *, n_samples=1200, rms=1.44,
                    snr_db=40.0):
    """ONE experiment as ``mimo_hidden_effect_experiment`` simulates it (a
    discrete ``continuous`` is used as it is)."""
    from lrmfrf.signals import multisine
    from lrmfrf.simulate import periodic_state, simulate

    true = (continuous if control.isdtime(continuous, strict=True)
            else control.sample_system(continuous, stage.sample_time, "zoh"))
    controller = stage.controller
    system = true if controller is None else control.feedback(true, controller,
                                                               sign=-1)
    if np.max(np.abs(np.linalg.eigvals(system.A))) >= 1.0:
        raise RuntimeError("the hidden effect made the closed loop unstable.")
    amplitudes = [None, None]
    if controller is None:  # shaped excitation, as the generator in open loop
        z = np.exp(2j * np.pi * np.arange(n_samples // 2 + 1) / n_samples)
        with np.errstate(divide="ignore", invalid="ignore"):
            nominal = stage.plant(z)
        for j in range(2):
            size = np.abs(nominal[j, j])
            top = np.max(size[np.isfinite(size)])
            size = np.where(np.isfinite(size), size, top)
            amplitudes[j] = 1.0 / np.maximum(size, 1e-6 * top)
    u = np.stack([multisine(n_samples, rms=rms, rng=rng, amplitude=amplitudes[j])
                  for j in range(2)])
    x0 = periodic_state(system, u) if controller is None else None
    sim = simulate(system, u, stage.downsampling_factor, snr_db=snr_db, rng=rng,
                   x0=x0)
    return u[None], np.asarray(sim.y_l)[None]


def run_record(seed: int, loop: str, case: str, catalogue: str,
               calibration_runs: int, sizing: str = "plate") -> dict:
    from lrmfrf.discrepancy import (
        Delay,
        Gain,
        LowPass,
        MissingMode,
        ModeShift,
        diagnose,
    )
    from lrmfrf.discrepancy.hidden_mimo import (
        mimo_hidden_effect_experiment,
        two_by_two_stage,
    )
    from lrmfrf.plants import random_stage

    start = time.perf_counter()
    record_seed = seed * 100 + CASES.index(case) + (50 if loop == "open" else 0)
    rng = np.random.default_rng(record_seed)
    plate, draw = random_stage(seed, mimo=True)
    stage = two_by_two_stage(plate, loop=loop,
                             downsampling_factor=draw.downsampling_factor,
                             sizing=sizing)
    channel, key, value = -1, "", math.nan
    if case in ("gain", "none"):
        experiment = mimo_hidden_effect_experiment(
            None if case == "none" else case, stage=stage, rng=rng)
        u, y = experiment.u_h, experiment.y_l
        if case == "gain":
            key, value = "gain", experiment.effects[0].parameters["gain"]
    else:
        channel = int(rng.integers(2))
        if case == "input_low_pass":
            key = "cutoff"
            value = math.exp(rng.uniform(math.log(300.0), math.log(3000.0)))
        elif case == "input_delay":
            key = "delay"
            step = stage.sample_time / 20
            value = step * int(rng.integers(round(0.1e-3 / step),
                                            round(1.0e-3 / step) + 1))
        else:
            key = "gain"
            value = (rng.uniform(0.8, 0.95) if rng.random() < 0.5
                     else rng.uniform(1.05, 1.25))
        true = (delayed_input(stage, channel, value) if case == "input_delay"
                else true_plant(stage, case, channel, value))
        u, y = simulate_record(stage, true, rng)
    effects = None if catalogue == "new" else [Gain(), Delay(), LowPass(),
                                               MissingMode(), ModeShift()]
    row = {"seed": seed, "loop": loop, "case": case, "F": stage.downsampling_factor,
           "channel": channel, "key": key, "value": value, "error": ""}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            report = diagnose(stage.plant, u, y, stage.downsampling_factor,
                              controller=stage.controller, effects=effects,
                              calibration_runs=calibration_runs, rng=record_seed,
                              steady_state=loop == "open")
        except (ValueError, RuntimeError) as exc:  # reported, not hidden
            row.update(error=f"{type(exc).__name__}: {exc}", named="", found="",
                       right=False, named_ok=False, any_finding=False,
                       ambiguous=False, param_error=math.nan,
                       gap_before=math.nan, gap_after=math.nan,
                       seconds=time.perf_counter() - start)
            return row
    side = {"input_gain": "input", "output_gain": "output",
            "input_low_pass": "input", "input_delay": "input"}.get(case)
    matches = [f for f in report.findings if f.effect == case
               and (side is None or f.parameters.get(side) == channel)]
    error = (abs(matches[0].parameters[key] / value - 1) if matches and key
             else math.nan)
    names = [f.effect for f in report.findings]
    row.update(
        named=" ".join(names),
        found=" ".join(
            f.effect + "(" + ",".join(f"{k}={v:.4g}" for k, v in f.parameters.items())
            + ")" for f in report.findings),
        right=(names == [] if case == "none" else
               names == [case] and bool(matches) and error <= TOLERANCE[key]),
        named_ok=(names == [] if case == "none" else bool(matches)),
        any_finding=bool(names),
        ambiguous="ambiguous" in names,
        param_error=error,
        gap_before=report.gap_before,
        gap_after=report.gap_after,
        seconds=time.perf_counter() - start,
    )
    return row


def summarise(rows):
    table = []
    for loop in LOOPS:
        for case in CASES:
            group = [r for r in rows if r["loop"] == loop and r["case"] == case]
            if not group:
                continue
            errors = [r["param_error"] for r in group
                      if np.isfinite(r["param_error"])]
            table.append({
                "loop": loop, "case": case, "n": len(group),
                "right": _rate(r["right"] for r in group),
                "named": _rate(r["named_ok"] for r in group),
                "ambiguous": _rate(r["ambiguous"] for r in group),
                "any": _rate(r["any_finding"] for r in group),
                "median_error": float(np.median(errors)) if errors else math.nan,
                "seconds": float(np.mean([r["seconds"] for r in group])),
                "errors": sum(bool(r["error"]) for r in group),
            })
    return table


def format_table(table) -> str:
    lines = ["loop    case            n  right%  named%  ambig%  any%  "
             "med.err  s/rec  exc",
             "-" * 78]
    for t in table:
        lines.append(
            f"{t['loop']:<7} {t['case']:<14} {t['n']:>2} {t['right']:>7.0f} "
            f"{t['named']:>7.0f} {t['ambiguous']:>7.0f} {t['any']:>5.0f} "
            f"{t['median_error']:>8.3g} {t['seconds']:>6.1f} {t['errors']:>4}")
    lines.append("right: exactly the hidden effect, its channel, parameter within "
                 "2 % (gain) / 15 % (cutoff) / 5 % (delay); none: no finding.")
    lines.append("named: the effect on its channel among the findings; any: some "
                 "finding (for none: a false alarm).")
    return "\n".join(lines)


def _rate(flags) -> float:
    flags = list(flags)
    return 100.0 * float(np.mean(flags)) if flags else math.nan


def parse_seeds(text: str) -> list[int]:
    if "-" in text:
        low, high = (int(v) for v in text.split("-"))
        return list(range(low, high + 1))
    return [int(v) for v in text.split(",")]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1000-1007")
    parser.add_argument("--loops", nargs="*", default=list(LOOPS), choices=LOOPS)
    parser.add_argument("--cases", nargs="*", default=list(CASES), choices=CASES)
    parser.add_argument("--catalogue", choices=("new", "old"), default="new")
    parser.add_argument("--calibration-runs", type=int, default=10)
    parser.add_argument("--sizing", choices=("plate", "siso"), default="plate",
                        help="2x2 stages' mode sizes (two_by_two_stage): the "
                        "plate's own (default, the records so far) or relative "
                        "to the corner as the SISO stages' (generalisation_"
                        "diagnose.py --mimo's default)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover
        pass
    seeds = parse_seeds(args.seeds)
    sized = "" if args.sizing == "plate" else f"_{args.sizing}_sized"
    out = Path(args.out or (f"benchmarks/results/diagnose_channels_{args.catalogue}"
                            f"{sized}_seeds{seeds[0]}-{seeds[-1]}.csv"))
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in seeds:
        for loop in args.loops:
            for case in args.cases:
                row = run_record(seed, loop, case, args.catalogue,
                                 args.calibration_runs, args.sizing)
                rows.append(row)
                print(f"{seed} {loop:<6} {case:<14} ch={row['channel']:>2} "
                      f"{row['key']}={row['value']:.4g} -> {row['found'] or '-'} "
                      f"{'OK' if row['right'] else 'MISS'} "
                      f"{row['seconds']:.1f}s {row['error']}", flush=True)
    with out.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    text = (f"{len(rows)} records, catalogue {args.catalogue}, seeds {args.seeds}, "
            f"calibration_runs {args.calibration_runs}, 40 dB, one experiment, "
            f"sizing {args.sizing}\n"
            + format_table(summarise(rows)))
    out.with_suffix(".txt").write_text(text + "\n")
    print(text)
    print(f"wrote {out} and {out.with_suffix('.txt')}", file=sys.stderr)
    return rows


if __name__ == "__main__":
    main()
