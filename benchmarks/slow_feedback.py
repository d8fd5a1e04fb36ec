"""Slow-rate feedback (issue 13): the indirect route (fit r -> y_l, then
plant_from_closed_loop) against the direct fit from the measured plant input
u_h to y_l, on the SISO wafer stage with a 20 Hz lead-PID running at the slow
rate on y4 (vision in the loop).

For each SNR: median relative error of the plant FRF against the truth, the
median relative bias (|mean estimate - truth| / |truth|, R runs) and the median
ratio Monte Carlo std / reported std, per frequency band (below 100 Hz,
100 Hz to the slow Nyquist frequency, above it).

Run: python benchmarks/slow_feedback.py [--runs 30] [--snr 60 40 20]
Prints a markdown table and writes benchmarks/results/slow_feedback.csv.
"""

from __future__ import annotations

import argparse
import csv
import warnings
from pathlib import Path

import numpy as np

from lrmfrf import LRMBeyondNyquist, multisine, plant_from_closed_loop
from lrmfrf.plants import lead_pid_controller, wafer_stage
from lrmfrf.simulate import frequency_grid, simulate_slow_feedback, true_frf

RESULTS = Path(__file__).parent / "results"
F = 3
N = 12_000


def run(snr_db: float, runs: int):
    stage = wafer_stage()
    ts = stage.sample_time
    plant = stage.plant[0, 0]
    controller = lead_pid_controller(20.0, stage.mass, sample_time=F * ts)
    r = multisine(N, rng=0)
    truth = true_frf(plant, N)
    routes = {"indirect": ([], []), "direct": ([], [])}
    for seed in range(runs):
        sim = simulate_slow_feedback(plant, controller, r, F, snr_db=snr_db, rng=seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            closed = LRMBeyondNyquist().fit(r, sim.y_l, F, sample_time=ts)
            direct = LRMBeyondNyquist().fit(sim.u_h, sim.y_l, F, sample_time=ts)
        indirect = plant_from_closed_loop(closed, controller)
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
        error = np.abs(frfs - truth) / np.abs(truth)
        bias = np.abs(frfs.mean(axis=0) - truth) / np.abs(truth)
        spread = np.sqrt(np.sum(np.abs(frfs - frfs.mean(axis=0)) ** 2, axis=0)
                         / (runs - 1))
        ratio = spread / stds.mean(axis=0)
        for band, where in bands.items():
            keep = ok & where
            rows.append({"snr_db": snr_db, "route": name, "band": band,
                         "median_rel_error": float(np.median(error[:, keep])),
                         "median_rel_bias": float(np.median(bias[keep])),
                         "std_ratio_mc": float(np.median(ratio[keep]))})
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--snr", type=float, nargs="+", default=[60.0, 40.0, 20.0])
    args = parser.parse_args()
    rows = [row for snr in args.snr for row in run(snr, args.runs)]
    print("| SNR dB | route | band | median rel. error | median rel. bias | "
          "MC std / std |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['snr_db']:g} | {row['route']} | {row['band']} | "
              f"{row['median_rel_error']:.3g} | {row['median_rel_bias']:.3g} | "
              f"{row['std_ratio_mc']:.2f} |")
    RESULTS.mkdir(exist_ok=True)
    with open(RESULTS / "slow_feedback.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
