"""Closed-form choice of window and degrees on the wafer-stage benchmark.

For each realisation (new multisine phases and noise) and each candidate of a
fixed grid, the local problems are solved once; that gives the candidate's FRF
(compared with the true FRF) and its closed-form criteria (centre-bin PRESS,
AICc, GCV; see ``lrmfrf.estimators.selection``). The table compares
per system:

- oracle: the one fixed grid setting with the lowest median error over the
  realisations (needs the true FRF);
- selected: the setting chosen per realisation by each criterion (what
  ``LRMBeyondNyquistCV`` does), its error on that realisation;
- Table I of the paper: n = 18, R_g = R_t = 4, R_e = 7; and the R_g >= R_e
  setting of docs/method.md, (R_g, R_t, R_e) = (5, 5, 4) with n = 18.

Error of one realisation: the median over fast bins k = 1..N//2 of
``|G_hat - G| / |G|`` (DC left out: the closed loop has G(0) = 0). The table
reports the median of that over realisations.

A second table fits the Table I setting to P = 1, 2, 4, 8 experiments
(independent multisines and noise, each N = 1200) and shows the error falling
as about 1/sqrt(P).

A third study (``--heldout``) asks whether scikit-learn's ``GridSearchCV``
picks well when it holds out whole *experiments* whose multisines have other
phases. Per seed: P = 8 experiments (own random phases, own noise, 45 dB,
each starting at rest), a small grid (``HELDOUT_GRID``, R_t = R_g); for every
candidate the LRM fitted to all P experiments and its true error (median
relative error over all bins and over the bins above the slow Nyquist
frequency). Compared picks, each scored by the true error of the candidate
refitted on all P experiments:

- oracle: the candidate of the grid with the lowest true error on this seed;
- GridSearchCV R^2: ``KFold(4)`` over experiments (fit on 6, predict the slow
  output of the 2 held out), the estimators' own ``score`` (R^2);
- GridSearchCV spectral: the same folds, scored by minus the median over slow
  bins of ``|Y_l - Yhat_l| / |Y_l|`` (every bin counts equally, so the
  aliased bands above Nyquist weigh as much as the large low-frequency
  response that dominates R^2);
- LRMBeyondNyquistCV: AICc on the same P experiments (no refits).

The table also shows how little R^2 moves: the spread (max - min) of the
held-out R^2 over the candidates, against the spread of their true errors.

Run:  python3 benchmarks/selection.py [--realisations 50] [--n-jobs 2]
      python3 benchmarks/selection.py --heldout [--seeds 10] [--n-jobs 2]
      (the held-out study: about 1 min per seed and system on one core)
Writes benchmarks/results/selection.csv (one row per candidate and system),
benchmarks/results/selection_experiments.csv and, with ``--heldout``,
benchmarks/results/selection_heldout.csv (one row per seed and system).
"""

from __future__ import annotations

import argparse
import csv
import itertools
import pathlib
import time

import numpy as np
from joblib import Parallel, delayed
from sklearn.model_selection import GridSearchCV, KFold

from lrmfrf.estimators import LRMBeyondNyquist
from lrmfrf.estimators.selection import (
    CRITERIA,
    LRMBeyondNyquistCV,
    _combine,
    _local_criteria,
)
from lrmfrf.local_models import one_sided_fast_grid
from lrmfrf.plants import wafer_stage
from lrmfrf.progress import progress
from lrmfrf.signals import multisine
from lrmfrf.simulate import simulate, true_frf
from lrmfrf.windows import LocalModelLayout

N, F, RMS, SNR_DB = 1200, 3, 1.44, 45.0
# The default grid of LRMBeyondNyquistCV (transient degree tied: R_t = R_g).
HALF_WINDOWS = (12, 18, 24, 36)
NUM_DEGREES = (2, 4, 5, 6)
DEN_DEGREES = (2, 4, 7, 8)
TABLE_I = (18, 4, 4, 7)
METHOD_554 = (18, 5, 5, 4)


def grid() -> list[tuple[int, int, int, int]]:
    """Feasible (n, R_g, R_t, R_e) of the grid, in LRMBeyondNyquistCV's order."""
    out = []
    for n, rg, re in itertools.product(HALF_WINDOWS, NUM_DEGREES, DEN_DEGREES):
        n_params = (rg + 1) * F + (rg + 1) + re
        if n_params < 2 * n:  # at least 2 residual dof (AICc)
            out.append((n, rg, rg, re))
    return out


def one_realisation(system, G, seed: int, candidates) -> tuple[np.ndarray, dict]:
    """Errors and criteria of every candidate on one realisation."""
    rng = np.random.default_rng(seed)
    u = multisine(N, rms=RMS, rng=rng)
    sim = simulate(system, u, F, snr_db=SNR_DB, rng=rng)
    U = np.fft.fft(u)[None]
    Y = np.fft.fft(sim.y_l)[None]
    errors = np.empty(len(candidates))
    crits = {name: np.empty(len(candidates)) for name in CRITERIA}
    for i, (n, rg, rt, re) in enumerate(candidates):
        layout = LocalModelLayout(F=F, half_window=n, num_degree=rg,
                                  transient_degree=rt, den_degree=re)
        per_bin, ok, band = _local_criteria(U, Y, layout)
        frf = one_sided_fast_grid(band, N, F, conj=True)
        errors[i] = np.median(np.abs(frf[1:] - G[1:]) / np.abs(G[1:]))
        for name in CRITERIA:
            values = per_bin["press" if name == "press" else "residual"]
            crits[name][i] = _combine(values, ok, layout, name, N // F)
    return errors, crits


def run(realisations: int, n_jobs: int, seed: int = 2024):
    plant = wafer_stage()
    candidates = grid()
    rows, table = [], []
    for name, system in (("G_y4", plant.G_y4), ("G_z", plant.G_z)):
        G = true_frf(system, N)
        t0 = time.perf_counter()
        out = Parallel(n_jobs=n_jobs)(
            delayed(one_realisation)(system, G, seed + r, candidates)
            for r in progress(range(realisations), enabled=None, desc=name)
        )
        elapsed = time.perf_counter() - t0
        errors = np.array([o[0] for o in out])  # (R, C)
        crits = {c: np.array([o[1][c] for o in out]) for c in CRITERIA}
        median_err = np.median(errors, axis=0)
        oracle = int(np.argmin(median_err))
        i_table = candidates.index(TABLE_I)
        i_method = candidates.index(METHOD_554)
        picks = {c: np.argmin(crits[c], axis=1) for c in CRITERIA}
        sel = {c: float(np.median(errors[np.arange(realisations), picks[c]]))
               for c in CRITERIA}
        # Consistency with the estimator itself on the first realisation.
        rng = np.random.default_rng(seed)
        u = multisine(N, rms=RMS, rng=rng)
        sim = simulate(system, u, F, snr_db=SNR_DB, rng=rng)
        cv = LRMBeyondNyquistCV(half_windows=HALF_WINDOWS, num_degrees=NUM_DEGREES,
                                den_degrees=DEN_DEGREES,
                                criterion="aicc").fit(u, sim.y_l, F)
        assert tuple(cv.best_params_.values()) == candidates[picks["aicc"][0]]
        table.append({
            "system": name,
            "oracle": (candidates[oracle], median_err[oracle]),
            "table_I": median_err[i_table],
            "method_554": median_err[i_method],
            "selected": sel,
            "picks": picks,
            "seconds": elapsed,
        })
        for i, cand in enumerate(candidates):
            rows.append({
                "system": name, "half_window": cand[0], "num_degree": cand[1],
                "transient_degree": cand[2], "den_degree": cand[3],
                "median_rel_error": median_err[i],
                **{f"times_selected_{c}": int(np.sum(picks[c] == i))
                   for c in CRITERIA},
                **{f"median_{c}": float(np.median(crits[c][:, i])) for c in CRITERIA},
            })
    return candidates, table, rows


def experiments_error(system, G, seed: int, P: int) -> tuple[float, float, float]:
    """Table I LRM from P experiments: median relative error, RMS abs error,
    and the median predicted std (Lemma 2) relative to |G|."""
    rng = np.random.default_rng(seed)
    u = np.array([multisine(N, rms=RMS, rng=rng) for _ in range(P)])
    y = np.array([simulate(system, row, F, snr_db=SNR_DB, rng=rng).y_l for row in u])
    n, rg, rt, re = TABLE_I
    est = LRMBeyondNyquist(half_window=n, num_degree=rg, transient_degree=rt,
                           den_degree=re).fit(list(u), list(y), F)
    rel = np.abs(est.frf_[1:] - G[1:]) / np.abs(G[1:])
    return (float(np.median(rel)), float(np.sqrt(np.mean(rel**2))),
            float(np.median(est.frf_std_[1:] / np.abs(G[1:]))))


def run_experiments(realisations: int, n_jobs: int, seed: int = 7000):
    plant = wafer_stage()
    table = []
    for name, system in (("G_y4", plant.G_y4), ("G_z", plant.G_z)):
        G = true_frf(system, N)
        for P in (1, 2, 4, 8):
            out = np.array(Parallel(n_jobs=n_jobs)(
                delayed(experiments_error)(system, G, seed + 100 * P + r, P)
                for r in range(realisations)
            ))
            table.append({"system": name, "P": P,
                          "median_rel_error": float(np.median(out[:, 0])),
                          "rms_rel_error": float(np.median(out[:, 1])),
                          "predicted_rel_std": float(np.median(out[:, 2]))})
    return table


# --- held-out experiments with other phases: GridSearchCV -----------------------

HELDOUT_P, HELDOUT_FOLDS = 8, 4
HELDOUT_GRID = {"half_window": (12, 18, 24), "num_degree": (2, 4),
                "den_degree": (2, 4, 7)}
PICKS = ("oracle", "gridsearch_r2", "gridsearch_spectral", "aicc_cv")


def heldout_candidates() -> list[dict]:
    """The grid as LRMBeyondNyquistCV orders it (R_t tied to R_g)."""
    return [
        {"half_window": n, "num_degree": rg, "transient_degree": rg,
         "den_degree": re}
        for n, rg, re in itertools.product(*HELDOUT_GRID.values())
    ]


def spectral_score(estimator, u_h, y_l) -> float:
    """Minus the median over slow bins 1..M//2 (and held-out experiments) of
    the relative error of the predicted slow-output spectrum."""
    y = np.atleast_2d(np.asarray(y_l, dtype=float))
    Y = np.fft.rfft(y, axis=1)[:, 1:]
    Y_hat = np.fft.rfft(np.atleast_2d(estimator.predict(np.asarray(u_h))),
                        axis=1)[:, 1:]
    return -float(np.median(np.abs(Y - Y_hat) / np.abs(Y)))


def _errors(frf, G, above):
    rel = np.abs(frf[1:] - G[1:]) / np.abs(G[1:])
    return float(np.median(rel)), float(np.median(rel[above[1:]]))


def heldout_one_seed(system, G, above, seed: int) -> dict:
    """True errors of every candidate and the index each method picks."""
    rng = np.random.default_rng(seed)
    u = np.array([multisine(N, rms=RMS, rng=rng) for _ in range(HELDOUT_P)])
    y = np.array([simulate(system, row, F, snr_db=SNR_DB, rng=rng).y_l
                  for row in u])
    candidates = heldout_candidates()
    errors = np.array([
        _errors(LRMBeyondNyquist(**c).fit(list(u), list(y), F).frf_, G, above)
        for c in candidates
    ])  # (C, 2): all bins, above Nyquist
    search = GridSearchCV(
        LRMBeyondNyquist(), [{k: [v] for k, v in c.items()} for c in candidates],
        cv=KFold(HELDOUT_FOLDS), refit=False, n_jobs=1,
        scoring={"r2": lambda est, u_h, y_l: est.score(u_h, y_l),
                 "spectral": spectral_score},
    ).fit(list(u), list(y), F=F)
    results = search.cv_results_
    assert results["params"] == candidates
    cv = LRMBeyondNyquistCV(
        half_windows=HELDOUT_GRID["half_window"],
        num_degrees=HELDOUT_GRID["num_degree"],
        den_degrees=HELDOUT_GRID["den_degree"],
        criterion="aicc",
    ).fit(list(u), list(y), F)
    r2 = results["mean_test_r2"]
    return {
        "errors": errors,
        "r2": r2,
        "picks": {
            "oracle": int(np.argmin(errors[:, 0])),
            "gridsearch_r2": int(np.argmax(r2)),
            "gridsearch_spectral": int(np.argmax(results["mean_test_spectral"])),
            "aicc_cv": candidates.index(cv.best_params_),
        },
    }


def run_heldout(seeds: int, n_jobs: int, seed: int = 9000):
    plant = wafer_stage()
    slow_nyquist = plant.slow_nyquist_hz
    frequencies = np.arange(N // 2 + 1) / (N * plant.sample_time)
    above = frequencies > slow_nyquist
    table, rows = [], []
    candidates = heldout_candidates()
    for name, system in (("G_y4", plant.G_y4), ("G_z", plant.G_z)):
        G = true_frf(system, N)
        t0 = time.perf_counter()
        out = Parallel(n_jobs=n_jobs)(
            delayed(heldout_one_seed)(system, G, above, seed + r)
            for r in progress(range(seeds), enabled=None, desc=name)
        )
        elapsed = time.perf_counter() - t0
        summary = {"system": name, "seconds": elapsed}
        for pick in PICKS:
            index = np.array([o["picks"][pick] for o in out])
            err = np.array([o["errors"][i] for o, i in zip(out, index, strict=True)])
            oracle = np.array([o["errors"][o["picks"]["oracle"]] for o in out])
            summary[pick] = {
                "error": float(np.median(err[:, 0])),
                "error_above": float(np.median(err[:, 1])),
                "ratio": float(np.median(err[:, 0] / oracle[:, 0])),
                "hits": int(np.sum(index == [o["picks"]["oracle"] for o in out])),
                "most_often": candidates[np.bincount(index).argmax()],
            }
        summary["r2_spread"] = float(np.median([np.ptp(o["r2"]) for o in out]))
        summary["r2_median"] = float(np.median([np.median(o["r2"]) for o in out]))
        summary["error_spread"] = float(np.median(
            [np.ptp(o["errors"][:, 0]) for o in out]))
        summary["error_above_spread"] = float(np.median(
            [np.ptp(o["errors"][:, 1]) for o in out]))
        table.append(summary)
        for r, o in enumerate(out):
            row = {"system": name, "seed": seed + r}
            for pick in PICKS:
                i = o["picks"][pick]
                row[f"{pick}_index"] = i
                row[f"{pick}_error"] = o["errors"][i, 0]
                row[f"{pick}_error_above"] = o["errors"][i, 1]
            row["r2_min"], row["r2_max"] = float(o["r2"].min()), float(o["r2"].max())
            rows.append(row)
    return table, rows


def print_heldout(table, seeds: int) -> None:
    print(f"Held-out experiments: wafer stage, P={HELDOUT_P} experiments of N={N} "
          f"(own multisine phases), F={F}, {SNR_DB:g} dB, {seeds} seeds; grid "
          f"{HELDOUT_GRID} (R_t = R_g, {len(heldout_candidates())} candidates); "
          f"GridSearchCV with KFold({HELDOUT_FOLDS}) over experiments")
    print("error: median over seeds of the median relative error of the pick "
          "(refitted on all P experiments) over all bins / above the slow "
          "Nyquist frequency; x oracle: median over seeds of error / the "
          "seed's best of the grid; hits: seeds where the pick is the oracle's")
    head = (f"  {'method':24s}{'error':>8s}{'above Nyq':>11s}{'x oracle':>10s}"
            f"{'hits':>6s}  most often (n, R_g, R_t, R_e)")
    for t in table:
        print(f"\n{t['system']}  ({t['seconds']:.0f} s)")
        print(head)
        for pick in PICKS:
            p = t[pick]
            print(f"  {pick:24s}{p['error']:8.4f}{p['error_above']:11.4f}"
                  f"{p['ratio']:10.2f}{p['hits']:6d}  "
                  f"{tuple(p['most_often'].values())}")
        print(f"  held-out R^2: median {t['r2_median']:.4f}, spread over the grid "
              f"{t['r2_spread']:.4f}; true error spread over the grid "
              f"{t['error_spread']:.4f} (above Nyquist {t['error_above_spread']:.4f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realisations", type=int, default=50)
    parser.add_argument("--n-jobs", type=int, default=2)
    parser.add_argument("--heldout", action="store_true",
                        help="run only the held-out-experiments study")
    parser.add_argument("--seeds", type=int, default=10,
                        help="seeds of the held-out study")
    args = parser.parse_args()
    out = pathlib.Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    if args.heldout:
        table, rows = run_heldout(args.seeds, args.n_jobs)
        print_heldout(table, args.seeds)
        with open(out / "selection_heldout.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        return
    candidates, table, rows = run(args.realisations, args.n_jobs)
    print(f"Wafer stage, N={N}, F={F}, multisine RMS {RMS}, {SNR_DB:g} dB, "
          f"{args.realisations} realisations")
    print(f"grid: n in {HALF_WINDOWS}, R_g = R_t in {NUM_DEGREES}, R_e in "
          f"{DEN_DEGREES}: {len(candidates)} feasible candidates")
    print("error = median over realisations of the median relative error over bins")
    for t in table:
        print(f"\n{t['system']}  ({t['seconds']:.0f} s)")
        (cand, err) = t["oracle"]
        print(f"  {'oracle (fixed, true FRF) ' + str(cand):44s} {err:.4f}")
        print(f"  {'Table I (18, 4, 4, 7)':44s} {t['table_I']:.4f}"
              f"  ({t['table_I'] / err:.2f}x oracle)")
        print(f"  {'R_g >= R_e (18, 5, 5, 4)':44s} {t['method_554']:.4f}"
              f"  ({t['method_554'] / err:.2f}x oracle)")
        for c in CRITERIA:
            picks = t["picks"][c]
            values, counts = np.unique(picks, return_counts=True)
            top = candidates[values[np.argmax(counts)]]
            print(f"  {'selected by ' + c:44s} {t['selected'][c]:.4f}"
                  f"  ({t['selected'][c] / err:.2f}x oracle; most often {top})")
    with open(out / "selection.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)

    p_table = run_experiments(args.realisations, args.n_jobs)
    print(f"\nP experiments (Table I setting, each N={N}, {SNR_DB:g} dB): median "
          "over realisations; 'x P=1' is the error ratio to P=1, sqrt(P) the "
          "1/sqrt(P) law")
    print(f"{'system':7s}{'P':>3s}{'median rel':>12s}{'RMS rel':>10s}"
          f"{'pred. std':>11s}{'x P=1':>8s}{'sqrt(P)':>9s}")
    for row in p_table:
        first = next(r for r in p_table if r["system"] == row["system"])
        print(f"{row['system']:7s}{row['P']:3d}{row['median_rel_error']:12.4f}"
              f"{row['rms_rel_error']:10.4f}{row['predicted_rel_std']:11.4f}"
              f"{first['median_rel_error'] / row['median_rel_error']:8.2f}"
              f"{np.sqrt(row['P']):9.2f}")
    with open(out / "selection_experiments.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(p_table[0]))
        writer.writeheader()
        writer.writerows(p_table)


if __name__ == "__main__":
    main()
