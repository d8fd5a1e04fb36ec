"""Iterative refinement (issue 4): SK and guarded LM on the wafer stage.

Accuracy: paper Table I settings (N = 1200, F = 3, R_g = R_t = 4, R_e = 7,
n = 18), random-phase multisine of RMS 1.44, G_y4 and G_z of the wafer stage,
45 dB output SNR, a fresh input and noise per realisation. For each
realisation: closed form, SK 30, SK 30 + LM 300 with the guard (and, with
--unguarded, without it). Reports the mean-cost drops (eq. meanCosts), median
relative FRF errors, guard activations and the per-bin worst case of
``|G_refined - G| / (10 |G_closed - G| + 10 std_closed)`` (must stay <= 1),
with the fast bin where it occurs, and the calibration of ``frf_std_``: the
median over bins of (median predicted std over realisations) / (Monte-Carlo
std of the estimate over realisations), for the closed form and each method.

Timing: SK 30 and LM 300 (each from the closed form) and SK 30 + LM 300 (the
chain) for N = 1200, 12000, 120000 (one record each; best of ``--repeats``
for N <= 12000). The last table fits ``time ~ N^a`` between consecutive sizes
(``a = 1``: linear growth). Wall and CPU (process) time: on a shared machine
the CPU time is the fairer measure of the code's own cost.

Run:  python benchmarks/refinement.py [--runs 100] [--unguarded]
      python benchmarks/refinement.py --runs 0 --sizes 1200 12000   # timing only
Writes benchmarks/results/refinement_accuracy.csv and refinement_timing.csv.
"""

from __future__ import annotations

import argparse
import csv
import time
import warnings
from pathlib import Path

import numpy as np

from lrmfrf import multisine
from lrmfrf.local_models import fit_local_models, one_sided_fast_grid
from lrmfrf.plants import wafer_stage
from lrmfrf.progress import progress
from lrmfrf.refinement import refine_local_models
from lrmfrf.simulate import simulate, true_frf
from lrmfrf.windows import LocalModelLayout

RESULTS = Path(__file__).parent / "results"
F = 3
PAPER = {"half_window": 18, "num_degree": 4, "transient_degree": 4, "den_degree": 7}
METHODS = {
    "SK30": {"sk_iterations": 30},
    "SK30+LM300": {"sk_iterations": 30, "lm_iterations": 300},
}
TIMED = {
    "SK30": {"sk_iterations": 30},
    "LM300": {"lm_iterations": 300},
    "SK30+LM300": {"sk_iterations": 30, "lm_iterations": 300},
}
UNGUARDED = {"SK30+LM300 unguarded": {"sk_iterations": 30, "lm_iterations": 300,
                                      "guard": None, "jump": None}}


def dft_data(system, n_samples, rng, snr_db):
    u = multisine(n_samples, rms=1.44, rng=rng)
    y = simulate(system, u, F, snr_db=snr_db, rng=rng).y_l
    return np.fft.fft(u)[None], np.fft.fft(y)[None]


def one_realisation(system, G, keep, rng, snr_db, methods):
    U, Y = dft_data(system, G.size * 2 - 2, rng, snr_db)
    layout = LocalModelLayout(F=F, **PAPER)
    closed = fit_local_models(U, Y, layout)
    n = 2 * (G.size - 1)
    G_closed = one_sided_fast_grid(closed.system, n, F, conj=True)
    std_closed = np.sqrt(one_sided_fast_grid(closed.system_var, n, F, conj=False))
    err_closed = np.abs(G_closed - G)[keep]
    rel = {"closed": float(np.median(err_closed / np.abs(G[keep])))}
    out = {"closed": {"frf": G_closed, "std": std_closed}}
    for name, kwargs in methods.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = refine_local_models(U, Y, layout, closed, **kwargs)
        G_hat = one_sided_fast_grid(result.local_fit.system, n, F, conj=True)
        std = np.sqrt(one_sided_fast_grid(result.local_fit.system_var, n, F,
                                          conj=False))
        err = np.abs(G_hat - G)[keep]
        bound = 10 * err_closed + 10 * std_closed[keep]
        history = result.cost_history
        out[name] = {
            "frf": G_hat,
            "std": std,
            "worst_bin": int(np.flatnonzero(keep)[np.argmax(err / bound)]),
            "median_rel_error": float(np.median(err / np.abs(G[keep]))),
            "worst_ratio": float(np.max(err / bound)),
            "worst_err_over_closed": float(np.max(err / err_closed)),
            "cost_after_sk": history[result.sk_iterations] / history[0],
            "cost_final": history[-1] / history[0],
            "n_guarded": result.n_guarded,
            "sk_iter": result.sk_iterations,
            "lm_iter": result.lm_iterations,
        }
    return rel["closed"], out


def mean_of(results, key):
    return float(np.mean([r[key] for r in results]))


def std_calibration(results, keep):
    """Median over bins of median predicted std / Monte-Carlo std."""
    frf = np.array([r["frf"] for r in results])[:, keep]
    predicted = np.median(np.array([r["std"] for r in results])[:, keep], axis=0)
    mc = np.sqrt(np.mean(np.abs(frf - frf.mean(axis=0)) ** 2, axis=0))
    return float(np.median(predicted / mc))


def accuracy(runs, snr_db, unguarded, seed):
    stage = wafer_stage()
    methods = dict(METHODS, **(UNGUARDED if unguarded else {}))
    rows = []
    for system_name in ("G_y4", "G_z"):
        system = getattr(stage, system_name)
        G = true_frf(system, 1200)
        keep = np.isfinite(G) & (np.abs(G) > 0)
        keep[0] = False  # DC: double integrator in the loop
        rng = np.random.default_rng(seed)
        closed_med, closed_fits = [], []
        per_method = {name: [] for name in methods}
        for _ in progress(range(runs), enabled=None, desc=system_name):
            med, out = one_realisation(system, G, keep, rng, snr_db, methods)
            closed_med.append(med)
            closed_fits.append(out["closed"])
            for name in methods:
                per_method[name].append(out[name])
        closed_med = np.array(closed_med)
        std_ratio_closed = std_calibration(closed_fits, keep)
        for name in methods:
            res = per_method[name]
            med = np.array([r["median_rel_error"] for r in res])
            worst_run = int(np.argmax([r["worst_ratio"] for r in res]))
            rows.append({
                "system": system_name,
                "method": name,
                "runs": runs,
                "median_rel_error_closed": float(np.median(closed_med)),
                "median_rel_error": float(np.median(med)),
                "error_change_%": 100 * float(np.median(med / closed_med) - 1),
                "runs_better_than_closed": int(np.sum(med < closed_med)),
                "cost_after_sk_%": 100 * mean_of(res, "cost_after_sk"),
                "cost_final_%": 100 * mean_of(res, "cost_final"),
                "guarded_per_fit_mean": float(np.mean([r["n_guarded"] for r in res])),
                "guarded_per_fit_max": int(np.max([r["n_guarded"] for r in res])),
                "lm_iter_mean": float(np.mean([r["lm_iter"] for r in res])),
                "worst_bin_ratio": float(np.max([r["worst_ratio"] for r in res])),
                "worst_bin_k": res[worst_run]["worst_bin"],
                "worst_bin_err_over_closed": float(
                    np.max([r["worst_err_over_closed"] for r in res])),
                "std_over_mc_closed": std_ratio_closed,
                "std_over_mc": std_calibration(res, keep),
            })
    return rows


def timing(sizes, seed, repeats):
    system = wafer_stage().G_y4
    layout = LocalModelLayout(F=F, **PAPER)
    rows = []
    for n_samples in sizes:
        rng = np.random.default_rng(seed)
        U, Y = dft_data(system, n_samples, rng, 45.0)
        start = time.perf_counter()
        closed = fit_local_models(U, Y, layout)
        t_closed = time.perf_counter() - start
        for name, kwargs in TIMED.items():
            best, best_cpu = np.inf, np.inf
            for _ in range(repeats if n_samples <= 12000 else 1):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    start, start_cpu = time.perf_counter(), time.process_time()
                    result = refine_local_models(U, Y, layout, closed, **kwargs)
                    best = min(best, time.perf_counter() - start)
                    best_cpu = min(best_cpu, time.process_time() - start_cpu)
            windows = closed.slow_bins.size
            iters = result.sk_iterations + result.lm_iterations
            rows.append({
                "N": n_samples,
                "windows": windows,
                "method": name,
                "iterations_run": iters,
                "closed_form_s": t_closed,
                "refine_wall_s": best,
                "refine_cpu_s": best_cpu,
                "us_per_window_iteration": 1e6 * best / windows / max(iters, 1),
            })
    return rows


def growth(rows):
    """Exponent ``a`` of ``time ~ N^a`` between consecutive sizes, per method."""
    out = []
    for name in TIMED:
        mine = [r for r in rows if r["method"] == name]
        for small, large in zip(mine, mine[1:], strict=False):
            ratio = np.log(large["N"] / small["N"])
            out.append({
                "method": name,
                "N": f"{small['N']} -> {large['N']}",
                "exponent_wall": float(np.log(large["refine_wall_s"]
                                              / small["refine_wall_s"]) / ratio),
                "exponent_cpu": float(np.log(large["refine_cpu_s"]
                                             / small["refine_cpu_s"]) / ratio),
            })
    return out


def print_table(rows):
    if not rows:
        return
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for row in rows:
        cells = [f"{v:.4g}" if isinstance(v, float) else str(v) for v in row.values()]
        print("| " + " | ".join(cells) + " |")
    print()


def write_csv(rows, name):
    if not rows:
        return
    RESULTS.mkdir(exist_ok=True)
    with open(RESULTS / name, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100, help="realisations (0: skip)")
    parser.add_argument("--snr", type=float, default=45.0, help="output SNR in dB")
    parser.add_argument("--unguarded", action="store_true",
                        help="also run LM without the guard")
    parser.add_argument("--sizes", type=int, nargs="*", default=[1200, 12000, 120000],
                        help="record lengths N for timing (none: skip)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="timing repeats (best of) for N <= 12000")
    parser.add_argument("--seed", type=int, default=2024)
    args = parser.parse_args(argv)
    if args.runs > 0:
        rows = accuracy(args.runs, args.snr, args.unguarded, args.seed)
        print(f"## Accuracy, {args.runs} realisations, {args.snr:g} dB\n")
        print_table(rows)
        write_csv(rows, "refinement_accuracy.csv")
    if args.sizes:
        rows = timing(args.sizes, args.seed, args.repeats)
        print("## Timing (best of repeats; LM and SK each from the closed form)\n")
        print_table(rows)
        write_csv(rows, "refinement_timing.csv")
        print("## Growth with N (time ~ N^a; a = 1 is linear)\n")
        print_table(growth(rows))


if __name__ == "__main__":
    main()
