"""Selection rules re-scored offline on the random-stage records (issue 15).

Each record of ``generalisation_selection.py`` (same stages, seeds, noise and
grid) is simulated once; per candidate of the grid the band values, the
Lemma-2 variances (``gvar`` times the window's noise estimate) and the
errors-in-variables variances (``frf_std_**2`` of ``LRMBeyondNyquist(**c)``,
the default ``std_method``) are kept, so rules are re-scored in seconds
(``--cache``). The ratio is the error of the rule's estimate (median relative
error over the valid fast bins) over that of the record's oracle (the best
setting of the grid).

Rules: ``pmse`` (the library's default, Lemma-2 variances), ``pmse eiv``
(the same with the eiv variances), ``pmse kappa 2`` (twice the reference
variance subtracted from the bias estimate), ``pmse h3`` (the bias estimate
averaged over 7 neighbouring slow bins before clipping at 0), ``blend b30
h5`` (``per_band=True``: candidates weighted per slow bin by
``exp(-30 (score - best))``, score the mean log eiv std over the bin's bands
averaged over 11 slow bins), ``blend b10 h10`` (softer weights, 21 bins) and
``mix`` (the mean of the PMSE pick's and the ``b30 h5`` blend's band values).

``--speed`` times the scoring of the default grid on one record instead.

Run:  python benchmarks/selection_rules.py --seeds 1000-1019 --cache tune.pkl
      python benchmarks/selection_rules.py --seeds 2000-2019 --wafer \
          --cache held.pkl
      python benchmarks/selection_rules.py --speed
(about 15 s of CPU per record the first time; the cache is re-used after)
"""

from __future__ import annotations

import argparse
import os
import pickle
import sys
import warnings

import numpy as np
from generalisation_selection import (
    _parse_seeds,
    default_grid,
    fixed_setting,
    pick,
    record_ingredients,
    regenerate_record,
    stage_systems,
)

from lrmfrf import LRMBeyondNyquist
from lrmfrf.estimators._bands import SCORE_HALF_WIDTH, SCORE_SHARPNESS, smooth_scores
from lrmfrf.local_models import one_sided_fast_grid
from lrmfrf.simulate import true_frf


def cached_record(label, system, F, seed) -> dict:
    """One record: band values, Lemma-2 and eiv variances per candidate."""
    open_loop = "/open/" in label
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = record_ingredients(system, F, seed, open_loop=open_loop)
        u, y = regenerate_record(system, F, seed, open_loop=open_loop)
        stds = [LRMBeyondNyquist(**c).fit(u, y, F).frf_std_ for c in rec["grid"]]
    M, N = rec["M"], rec["N"]
    j = np.arange(M // 2 + 1)[:, None] + M * np.arange(F)[None]
    mirror = np.where(j <= N // 2, j, N - j)  # fast bin of each band value
    band, var, var_eiv, ok = [], [], [], []
    for pw, layout, std in zip(rec["per_window"], rec["layouts"], stds,
                               strict=True):
        band.append(pw["band"])
        var.append(pw["gvar"] * (pw["residual"] * M * layout.n_equations
                                 / layout.dof)[:, None])
        var_eiv.append(np.nan_to_num(std[mirror] ** 2, nan=np.inf))
        ok.append(pw["ok"])
    return {"label": label, "F": F, "M": M, "N": N, "G": true_frf(system, N),
            "errors": rec["errors"], "grid": rec["grid"], "layouts": rec["layouts"],
            "per_window": [{"band": b, "gvar": pw["gvar"],
                            "residual": pw["residual"], "ok": o}
                           for b, pw, o in zip(band, rec["per_window"], ok,
                                               strict=True)],
            "band": np.array(band), "var": np.array(var),
            "var_eiv": np.array(var_eiv), "ok": np.array(ok)}


def band_error(rec, band) -> float:
    """Median relative error over the valid fast bins of band values."""
    G = rec["G"]
    usable = np.isfinite(G) & (np.abs(G) > 0)
    usable[0] = False
    frf = one_sided_fast_grid(band, rec["N"], rec["F"], conj=True)
    rel = np.abs(frf - G) / np.abs(np.where(usable, G, 1.0))
    return float(np.nanmedian(np.where(usable, rel, np.nan)))


def _reference(rec) -> int:
    n_invalid = (~rec["ok"]).sum(axis=1)
    todo = np.flatnonzero(n_invalid == n_invalid.min())
    return int(max(todo, key=lambda i: (rec["layouts"][i].window,
                                        rec["layouts"][i].n_params, -i)))


def pmse_pick(rec, var, *, kappa=1.0, weight=2.0, half_width=0) -> int:
    """PMSE with variances ``var``, ``kappa var_r`` subtracted from ``|G_c -
    G_r|^2`` (averaged over ``2 half_width + 1`` slow bins before the clip)."""
    r = _reference(rec)
    size = np.abs(rec["band"][r]) ** 2
    both = (rec["ok"] & rec["ok"][r])[..., None] & (size > 0)[None]
    both &= np.isfinite(var) & np.isfinite(var[r])[None]
    both[:, 0, 0] = False
    with np.errstate(invalid="ignore", divide="ignore"):
        excess = (np.abs(rec["band"] - rec["band"][r]) ** 2
                  - kappa * var[r]) / size
        excess = np.where(both, excess, np.nan)
        if half_width:
            kernel = np.ones(2 * half_width + 1)
            total = np.apply_along_axis(np.convolve, 1, np.nan_to_num(excess),
                                        kernel, "same")
            count = np.apply_along_axis(np.convolve, 1,
                                        np.isfinite(excess).astype(float),
                                        kernel, "same")
            excess = np.where(both, total / count, np.nan)
        rel = np.maximum(excess, 0.0) + weight * var / size
    values = np.array([np.median(x[np.isfinite(x)]) if np.isfinite(x).any()
                       else np.inf for x in np.where(both, rel, np.nan)])
    return int(np.lexsort((values, (~rec["ok"]).sum(axis=1)))[0])


def blend_band(rec, sharpness, half_width):
    """Per-slow-bin blend of all candidates by the eiv std (``per_band=True``
    with ``bands=None``, its weights recomputed from the cached std)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        score = 0.5 * np.log(rec["var_eiv"]).mean(axis=-1)
    score = np.where(rec["ok"] & np.isfinite(score), score, np.inf)
    score = smooth_scores(score, half_width, rec["M"])
    best = score.min(axis=0)
    finite = np.isfinite(best)
    with np.errstate(invalid="ignore"):
        w = np.exp(-sharpness * (score - np.where(finite, best, 0.0)))
    w = np.where(np.isfinite(score) & (w >= 1e-6), w, 0.0)
    w = w / np.where(finite, w.sum(axis=0), 1.0)
    band = np.sum(w[..., None] * np.where(w[..., None] > 0, rec["band"], 0), 0)
    band[~finite] = np.nan
    return band


def rule_ratios(rec) -> dict:
    """Error over the oracle's of each rule on one record."""
    oracle = rec["errors"].min()
    ratio = {}
    chosen = pick(rec, "pmse")  # the library's criterion
    if pmse_pick(rec, rec["var"]) != chosen:
        raise RuntimeError(f"{rec['label']}: the re-scored PMSE is not the "
                           "library's")
    ratio["pmse (default)"] = rec["errors"][chosen] / oracle
    ratio["pmse eiv"] = rec["errors"][pmse_pick(rec, rec["var_eiv"])] / oracle
    ratio["pmse kappa 2"] = rec["errors"][pmse_pick(rec, rec["var"],
                                                    kappa=2.0)] / oracle
    ratio["pmse h3"] = rec["errors"][pmse_pick(rec, rec["var"],
                                               half_width=3)] / oracle
    blend = blend_band(rec, SCORE_SHARPNESS, SCORE_HALF_WIDTH)
    ratio[f"blend b{SCORE_SHARPNESS:g} h{SCORE_HALF_WIDTH}"] = (
        band_error(rec, blend) / oracle)
    ratio["blend b10 h10"] = band_error(rec, blend_band(rec, 10.0, 10)) / oracle
    ratio["mix"] = band_error(rec, 0.5 * (blend + rec["band"][chosen])) / oracle
    return ratio


def pmse_speed(seed: int = 1000, repeats: int = 3) -> dict:
    """CPU seconds to score the default grid on the first record of stage
    ``seed``: PMSE's ingredients by the estimator's closed form (the
    library's), by the QR solve with leverages (before), and GAIC; the best
    of ``repeats`` runs, all in this one process."""
    import time

    from lrmfrf.estimators.selection import (
        _local_criteria,
        _pmse_ingredients,
        local_model_criterion,
    )
    from lrmfrf.windows import LocalModelLayout

    label, system, F = stage_systems(seed)[0]
    u, y = regenerate_record(system, F, 13)
    U, Y = np.fft.fft(u)[None], np.fft.fft(y)[None]
    layouts = [LocalModelLayout(F=F, **c) for c in default_grid(F)]
    runs = {
        "pmse (closed form)": lambda lay: _pmse_ingredients(U, Y, lay),
        "pmse (QR, before)": lambda lay: _local_criteria(U, Y, lay, variance=True),
        "gaic": lambda lay: local_model_criterion(U, Y, lay, criterion="gaic"),
    }
    for run in runs.values():  # compile and warm up
        run(layouts[0])
    out = {}
    for name, run in runs.items():
        best = np.inf
        for _ in range(repeats):
            start = time.process_time()
            for lay in layouts:
                run(lay)
            best = min(best, time.process_time() - start)
        out[name] = best
    return {"label": label, "n_candidates": len(layouts), **out}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1000-1019")
    parser.add_argument("--wafer", action="store_true")
    parser.add_argument("--cache", help="pickle of the records (read if present)")
    parser.add_argument("--speed", action="store_true",
                        help="time PMSE's scoring (closed form vs QR) and GAIC")
    args = parser.parse_args(argv)
    if args.speed:
        times = pmse_speed()
        base = times["pmse (closed form)"]
        print(f"{times['label']}: {times['n_candidates']} candidates, CPU s "
              "(best of 3) and ratio to PMSE by the closed form")
        for name in ("pmse (closed form)", "pmse (QR, before)", "gaic"):
            print(f"{name:20s}{times[name]:8.3f}{times[name] / base:7.2f}")
        return 0
    if args.cache and os.path.exists(args.cache):
        with open(args.cache, "rb") as fh:
            records = pickle.load(fh)
    else:
        seeds = _parse_seeds(args.seeds) + (["wafer"] if args.wafer else [])
        records = [cached_record(label, system, F, 7919 * k + 13)
                   for k, seed in enumerate(seeds)
                   for label, system, F in stage_systems(seed)]
        if args.cache:
            with open(args.cache, "wb") as fh:
                pickle.dump(records, fh)
    rows = [rule_ratios(rec) for rec in records]
    key, fixed = fixed_setting(records)
    closed = np.array(["/closed/" in rec["label"] for rec in records])
    print(f"{len(rows)} records; ratio = error / oracle error; mean, worst, "
          "records above 1.25, mean closed / open loop")
    names = [*rows[0], f"fixed {key}"]
    for name in names:
        a = np.array(fixed if name.startswith("fixed") else [r[name] for r in rows])
        print(f"{name:22s}{a.mean():7.3f}{a.max():7.3f}{np.sum(a > 1.25):4d}"
              f"{a[closed].mean():8.3f}{a[~closed].mean():7.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
