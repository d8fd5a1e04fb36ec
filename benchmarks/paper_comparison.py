"""The paper's comparison (LRM vs LPM vs SA) on the OAT-like stage, Monte Carlo.

Table I settings (N = 1200, F = 3, LRM (4, 4, 7, n = 18), LPM (2, 2, n = 18),
SA with 11 Hann segments of 200 samples), a random-phase multisine of RMS
1.44, both equivalent systems G_y4 and G_z. The input is fixed per system and
the noise is redrawn in every run, so the Monte-Carlo std is the std the
Lemma 2 formula predicts (conditional on the input).

Run:  python benchmarks/paper_comparison.py [--runs 100] [--sweep-runs 40]
      [--n-sweep 1200,12000,120000] [--no-figures]
Prints markdown tables and the issue's targets (holds / does not hold), and
writes CSV (and PNG figures) to benchmarks/results/. Progress bars are shown
only when standard error is a terminal (not in a log file).
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from lrmfrf.metrics import relative_error
from lrmfrf.metrics import std_ratio as metrics_std_ratio
from lrmfrf.paper import (
    TABLE_I,
    compare_methods,
    paper_experiment,
    table1_estimators,
)
from lrmfrf.plants import wafer_stage
from lrmfrf.progress import progress

RESULTS = Path(__file__).parent / "results"
METRICS = [
    ("median_relative_below", "median rel. < Nyq"),
    ("median_relative_above", "median rel. > Nyq"),
    ("rms_relative_below", "RMS rel. < Nyq"),
    ("rms_relative_above", "RMS rel. > Nyq"),
    ("median_relative_resonance", "median rel. near res."),
    ("cumulative_error", "cumulative (own grid)"),
    ("cumulative_error_common", "cumulative (SA grid)"),
]


def monte_carlo(system, resonances, runs: int, snr_db: float, seed: int,
                n_samples: int = TABLE_I["n_samples"], verbose: bool = True):
    """Per run: error summaries of every method, plus the LRM/LPM FRFs and stds."""
    rng = np.random.default_rng(seed)
    base = paper_experiment(system, rng=rng, snr_db=None, n_samples=n_samples)
    clean = base.y_l
    noise_std = np.sqrt(np.var(clean) / 10 ** (snr_db / 10))
    summaries, frfs, stds = [], {"LRM": [], "LPM": []}, {"LRM": [], "LPM": []}
    for _ in progress(range(runs), enabled=None if verbose else False,
                      desc=f"{snr_db:g} dB"):
        base.y_l = clean + noise_std * rng.standard_normal(clean.size)
        estimators = table1_estimators()
        summaries.append(compare_methods(base, estimators, resonances=resonances))
        for name in frfs:
            frfs[name].append(estimators[name].frf_)
            stds[name].append(estimators[name].frf_std_)
    return base, summaries, {k: np.array(v) for k, v in frfs.items()}, {
        k: np.array(v) for k, v in stds.items()}


def std_ratio(estimates: np.ndarray, stds: np.ndarray) -> float:
    """Median over bins k >= 1 of predicted std / Monte-Carlo std.

    The Monte-Carlo std is the spread about the sample mean (ddof = 1), the
    prediction ``sqrt(mean_r std_r^2)``; the DC bin (G = 0 under integral
    action) is left out, as in every other metric.
    """
    return metrics_std_ratio(stds[:, 1:], estimates[:, 1:], None)


def comparison_table(stage, runs: int, seed: int, verbose: bool):
    rows = []
    for k, name in enumerate(("G_y4", "G_z")):
        system = getattr(stage, name)
        _, summaries, frfs, stds = monte_carlo(
            system, stage.resonance_frequencies_hz, runs, TABLE_I["snr_db"],
            seed + k, verbose=verbose)
        for method in ("LRM", "LPM", "SA"):
            row = {"system": name, "method": method}
            for key, _ in METRICS:
                row[key] = float(np.median([s[method][key] for s in summaries]))
            row["std_ratio"] = (std_ratio(frfs[method], stds[method])
                                if method in frfs else float("nan"))
            rows.append(row)
    return rows


def snr_sweep(stage, snrs, runs: int, seed: int, verbose: bool):
    """Median relative errors of LRM and LPM vs SNR, on G_y4 and G_z.

    Medians over runs of the per-run median over bins (all bins k >= 1, and
    the bins above the slow Nyquist frequency). The input and the noise
    sequence are the same at every SNR (only the noise level changes), so the
    curves are smooth.
    """
    rows = []
    for k, name in enumerate(("G_y4", "G_z")):
        system = getattr(stage, name)
        for snr in snrs:
            base, _, frfs, _ = monte_carlo(system, stage.resonance_frequencies_hz,
                                           runs, snr, seed + k, verbose=verbose)
            above = base.frequencies > base.slow_nyquist
            for method, estimates in frfs.items():
                rel = np.array([relative_error(base.frf_true, e)
                                for e in estimates])
                rows.append({
                    "system": name, "snr_db": snr, "method": method,
                    "median_relative": float(np.median(np.median(rel[:, 1:], 1))),
                    "median_relative_above": float(
                        np.median(np.median(rel[:, above], 1))),
                    "rms_relative": float(np.sqrt(np.mean(rel[:, 1:] ** 2))),
                })
    return rows


def sweep_slopes(rows) -> list[dict]:
    """Per system and method: the error's fall per 20 dB of SNR.

    ``fall_per_20db`` is ``10 ** (-20 * slope)`` with ``slope`` the
    least-squares slope of ``log10(median error)`` against SNR in dB, over
    the whole sweep and over its upper half (>= the median SNR). A method
    whose error falls as 1/SNR shows 10; a bias-limited one shows ~1.
    """
    out = []
    for name in dict.fromkeys(r["system"] for r in rows):
        for method in dict.fromkeys(r["method"] for r in rows):
            sel = [r for r in rows if r["system"] == name and r["method"] == method]
            snr = np.array([r["snr_db"] for r in sel])
            row = {"system": name, "method": method}
            for key in ("median_relative", "median_relative_above"):
                err = np.log10([r[key] for r in sel])
                upper = snr >= np.median(snr)
                for label, keep in (("all", snr == snr), ("upper", upper)):
                    if np.unique(snr[keep]).size < 2:
                        row[f"{key}_fall_per_20db_{label}"] = float("nan")
                        continue
                    slope = np.polyfit(snr[keep], err[keep], 1)[0]
                    row[f"{key}_fall_per_20db_{label}"] = float(10 ** (-20 * slope))
            out.append(row)
    return out


def n_sweep(stage, lengths, runs: int, seed: int, verbose: bool, snr_db=45.0):
    """Median relative error vs record length (window fixed), G_y4.

    With noise, the per-bin SNR and the window (in bins) do not change with N,
    so neither does the noise-limited error; without noise the model-structure
    error falls quickly as the window narrows in Hz.
    """
    rows = []
    rng = np.random.default_rng(seed)
    for N in lengths:
        for _ in progress(range(runs), enabled=None if verbose else False,
                          desc=f"N={N}"):
            experiment = paper_experiment(stage.G_y4, rng=rng, n_samples=N,
                                          snr_db=snr_db)
            estimators = table1_estimators()
            del estimators["SA"]
            result = compare_methods(experiment, estimators)
            for method, s in result.items():
                rows.append({"n_samples": N, "method": method,
                             "median_relative": s["median_relative_all"]})
    out = []
    for N in lengths:
        for method in ("LRM", "LPM"):
            values = [r["median_relative"] for r in rows
                      if r["n_samples"] == N and r["method"] == method]
            out.append({"snr_db": "none" if snr_db is None else snr_db,
                        "n_samples": N, "method": method,
                        "median_relative": float(np.median(values))})
    return out


def check_targets(rows, slopes) -> list[str]:
    """The issue's targets, each as one line "holds"/"DOES NOT HOLD"."""
    lines = []

    def verdict(ok):
        return "holds" if ok else "DOES NOT HOLD"

    c = "cumulative_error_common"
    for name in ("G_y4", "G_z"):
        r = {row["method"]: row for row in rows if row["system"] == name}
        lrm, lpm, sa = r["LRM"][c], r["LPM"][c], r["SA"][c]
        lines.append(f"- {name}: cumulative error on the SA grid LRM/LPM = "
                     f"{lrm / lpm:.3f} (target <= 0.2): {verdict(lrm <= 0.2 * lpm)}")
        lines.append(f"- {name}: cumulative error on the SA grid LRM/SA = "
                     f"{lrm / sa:.3f} (target <= 0.1): {verdict(lrm <= 0.1 * sa)}")
        a_lrm = r["LRM"]["median_relative_above"]
        a_lpm = r["LPM"]["median_relative_above"]
        lines.append(f"- {name}: median rel. error above the slow Nyquist frequency"
                     f" LRM {a_lrm:.3g} vs LPM {a_lpm:.3g}: "
                     f"{verdict(a_lrm < a_lpm)}")
        ratio = r["LRM"]["std_ratio"]
        lines.append(f"- {name}: LRM std ratio predicted/MC {ratio:.3f} (target "
                     f"0.75-1.25): {verdict(0.75 <= ratio <= 1.25)}")
    # 1/SNR is a slope over the whole sweep; saturation is the behaviour at
    # high SNR, so LPM is judged on the upper half of the sweep.
    for s in slopes:
        if s["method"] == "LRM":
            fall = s["median_relative_fall_per_20db_all"]
            ok = 7.0 <= fall <= 13.0
            text = "over the whole sweep; falls as 1/SNR (target 7-13x)"
        else:
            fall = s["median_relative_fall_per_20db_upper"]
            ok = fall <= 2.0
            text = "in the upper half of the sweep; saturates (target <= 2x)"
        lines.append(f"- {s['system']}: {s['method']} error falls {fall:.2f}x per "
                     f"20 dB {text}: {verdict(ok)}")
    return lines


def _markdown(rows, columns) -> str:
    head = "| " + " | ".join(label for _, label in columns) + " |"
    rule = "|" + "---|" * len(columns)
    body = []
    for row in rows:
        cells = []
        for key, _ in columns:
            value = row[key]
            cells.append(f"{value:.3g}" if isinstance(value, float) else str(value))
        body.append("| " + " | ".join(cells) + " |")
    return "\n".join([head, rule, *body])


def _write_csv(name: str, rows) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    with open(RESULTS / name, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _figures(stage, seed: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lrmfrf.plotting import plot_error, plot_frf

    for k, name in enumerate(("G_y4", "G_z")):
        system = getattr(stage, name)
        experiment = paper_experiment(system, rng=seed + k)
        estimators = table1_estimators()
        for est in estimators.values():
            est.fit(experiment.u_h, experiment.y_l, 3, sample_time=0.5e-3)
        fig, _ = plot_frf(*estimators.values(), true=system, labels=list(estimators),
                          title=f"{name}: Table I settings, 45 dB", units="m/N")
        fig.savefig(RESULTS / f"paper_bode_{name}.png", dpi=110)
        plt.close(fig)
        # The system itself as the truth: SA is scored on its own coarse grid.
        fig, _ = plot_error(system, *estimators.values(), labels=list(estimators),
                            kind="cumulative", units="m/N")
        fig.savefig(RESULTS / f"paper_cumulative_{name}.png", dpi=110)
        plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--sweep-runs", type=int, default=40)
    parser.add_argument("--snrs", default="25,35,45,55,65,75,85")
    parser.add_argument("--n-sweep", default="1200,12000,120000")
    parser.add_argument("--n-sweep-runs", type=int, default=5)
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument("--no-figures", action="store_true")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    verbose = not args.quiet
    stage = wafer_stage()

    rows = comparison_table(stage, args.runs, args.seed, verbose)
    _write_csv("paper_comparison.csv", rows)
    print(f"\n### Table I settings, 45 dB, {args.runs} noise realisations "
          "(medians over runs)\n")
    print(_markdown(rows, [("system", "system"), ("method", "method"), *METRICS,
                           ("std_ratio", "std pred./MC")]))
    snrs = [float(s) for s in args.snrs.split(",")]
    sweep = snr_sweep(stage, snrs, args.sweep_runs, args.seed + 7, verbose)
    _write_csv("paper_snr_sweep.csv", sweep)
    print(f"\n### SNR sweep, {args.sweep_runs} runs each (medians over runs of "
          "the median over bins)\n")
    print(_markdown(sweep, [("system", "system"), ("snr_db", "SNR dB"),
                            ("method", "method"),
                            ("median_relative", "median rel. (all bins)"),
                            ("median_relative_above", "median rel. > Nyq"),
                            ("rms_relative", "RMS rel.")]))
    slopes = sweep_slopes(sweep)
    print("\nFall of the error per 20 dB of SNR (10 = 1/SNR, 1 = saturated), "
          "least-squares over the sweep and over its upper half:\n")
    print(_markdown(slopes, [
        ("system", "system"), ("method", "method"),
        ("median_relative_fall_per_20db_all", "all bins, whole sweep"),
        ("median_relative_fall_per_20db_upper", "all bins, upper half"),
        ("median_relative_above_fall_per_20db_all", "> Nyq, whole sweep"),
        ("median_relative_above_fall_per_20db_upper", "> Nyq, upper half"),
    ]))
    print("\n### Targets of issue 3\n")
    for line in check_targets(rows, slopes):
        print(line)

    lengths = [int(n) for n in args.n_sweep.split(",")]
    nrows = []
    for snr in (45.0, None):
        nrows += n_sweep(stage, lengths, args.n_sweep_runs, args.seed + 11,
                         verbose, snr_db=snr)
    _write_csv("paper_n_sweep.csv", nrows)
    print(f"\n### N sweep, G_y4, window n = 18 fixed, {args.n_sweep_runs} runs "
          "(45 dB and noise-free)\n")
    print(_markdown(nrows, [("snr_db", "SNR dB"), ("n_samples", "N"),
                            ("method", "method"), ("median_relative", "median rel.")]))
    if not args.no_figures:
        _figures(stage, args.seed)


if __name__ == "__main__":
    main()
