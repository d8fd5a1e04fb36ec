"""Slow-rate feedback (issue 13): the indirect route (fit r -> y_l, then
plant_from_closed_loop) against the direct fit from the measured plant input
u_h to y_l, with the controller running at the slow rate (vision in the loop).

Stages:

- ``siso``: the SISO wafer stage with a 20 Hz lead-PID on y4;
- ``mimo``: the MIMO stage (:func:`lrmfrf.plants.mimo_wafer_stage`, 4 actuators,
  4 encoders and the point of interest), its decoupled lead-PIDs redesigned for
  20 Hz at the slow rate (``stage.controller_at(F Ts, bandwidth_hz=20)``) on the
  four encoders, P = 4 orthogonal multisine experiments; the whole 5 x 4 plant.

For each SNR: median relative error of the plant FRF against the truth, the
median relative bias (|mean estimate - truth| / |truth|, R runs) and the median
ratio Monte Carlo std / reported std, per frequency band (below 100 Hz,
100 Hz to the slow Nyquist frequency, above it); for MIMO the medians run over
all 20 entries and the bins of the band.

Run: python benchmarks/slow_feedback.py [--runs 30] [--snr 60 40 20]
     [--stage siso mimo]
Prints a markdown table and writes benchmarks/results/slow_feedback.csv.
"""

from __future__ import annotations

import argparse
import csv
import warnings
from pathlib import Path

import numpy as np

from lrmfrf import LRMBeyondNyquist, multisine, plant_from_closed_loop
from lrmfrf.plants import lead_pid_controller, mimo_wafer_stage, wafer_stage
from lrmfrf.signals import orthogonal_multisines
from lrmfrf.simulate import frequency_grid, simulate_slow_feedback, true_frf

RESULTS = Path(__file__).parent / "results"
F = 3
N = 12_000


def _siso_setup():
    stage = wafer_stage()
    ts = stage.sample_time
    plant = stage.plant[0, 0]
    controller = lead_pid_controller(20.0, stage.mass, sample_time=F * ts)
    return plant, controller, multisine(N, rng=0), ts, None


def _mimo_setup():
    stage = mimo_wafer_stage(downsampling_factor=F)
    ts = stage.sample_time
    controller = stage.controller_at(F * ts, bandwidth_hz=20.0)
    r = orthogonal_multisines(stage.plant.ninputs, N, rng=0)  # (P, n_u, N)
    return stage.plant, controller, r, ts, stage.feedback_outputs


def _simulate(plant, controller, r, feedback, snr_db, rng):
    """u_h and y_l of every experiment (the first axis of a 3-D ``r``)."""
    experiments = r if r.ndim == 3 else [r]
    sims = [
        simulate_slow_feedback(plant, controller, rp, F, feedback_outputs=feedback,
                               snr_db=snr_db, rng=rng)
        for rp in experiments
    ]
    if r.ndim < 3:
        return sims[0].u_h, sims[0].y_l
    return np.stack([s.u_h for s in sims]), np.stack([s.y_l for s in sims])


def run(snr_db: float, runs: int, stage: str = "siso"):
    plant, controller, r, ts, feedback = (
        _mimo_setup() if stage == "mimo" else _siso_setup()
    )
    truth = true_frf(plant, N)
    routes = {"indirect": ([], []), "direct": ([], [])}
    for seed in range(runs):
        u_h, y_l = _simulate(plant, controller, r, feedback, snr_db,
                             np.random.default_rng(seed))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            closed = LRMBeyondNyquist().fit(r, y_l, F, sample_time=ts)
            direct = LRMBeyondNyquist().fit(u_h, y_l, F, sample_time=ts)
        indirect = plant_from_closed_loop(closed, controller, feedback)
        for name, est in (("indirect", indirect), ("direct", direct)):
            routes[name][0].append(np.where(est.valid_, est.frf_, np.nan))
            routes[name][1].append(np.where(est.valid_, est.frf_std_, np.nan))
    frequencies = frequency_grid(N, ts)
    nyquist = 1 / (2 * F * ts)
    bands = {"< 100 Hz": frequencies < 100,
             f"100-{nyquist:.0f} Hz": (frequencies >= 100) & (frequencies <= nyquist),
             f"> {nyquist:.0f} Hz": frequencies > nyquist}
    rows = []
    for name, (frfs, stds) in routes.items():
        frfs, stds = np.array(frfs), np.array(stds)
        ok = np.isfinite(frfs).all(axis=0) & np.isfinite(truth) & (frequencies > 0)
        ok &= np.abs(truth) > 0
        error = np.abs(frfs - truth) / np.abs(truth)
        bias = np.abs(frfs.mean(axis=0) - truth) / np.abs(truth)
        spread = np.sqrt(np.sum(np.abs(frfs - frfs.mean(axis=0)) ** 2, axis=0)
                         / (runs - 1))
        ratio = spread / stds.mean(axis=0)
        for band, where in bands.items():
            keep = ok & where
            rows.append({"stage": stage, "snr_db": snr_db, "route": name,
                         "band": band,
                         "median_rel_error": float(np.median(error[:, keep])),
                         "median_rel_bias": float(np.median(bias[keep])),
                         "std_ratio_mc": float(np.median(ratio[keep]))})
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--snr", type=float, nargs="+", default=[60.0, 40.0, 20.0])
    parser.add_argument("--stage", nargs="+", choices=["siso", "mimo"],
                        default=["siso", "mimo"])
    args = parser.parse_args()
    rows = [row for stage in args.stage for snr in args.snr
            for row in run(snr, args.runs, stage)]
    print("| stage | SNR dB | route | band | median rel. error | median rel. bias | "
          "MC std / std |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['stage']} | {row['snr_db']:g} | {row['route']} | "
              f"{row['band']} | "
              f"{row['median_rel_error']:.3g} | {row['median_rel_bias']:.3g} | "
              f"{row['std_ratio_mc']:.2f} |")
    RESULTS.mkdir(exist_ok=True)
    with open(RESULTS / "slow_feedback.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
