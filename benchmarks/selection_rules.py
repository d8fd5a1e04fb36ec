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
(the same with the eiv variances), ``pmse kappa k`` for k = 1.5, 2, 3, 4, 6
(``k`` times the reference variance subtracted from the bias estimate),
``pmse hw`` for w = 1, 3, 6, 12 (the bias estimate averaged over ``2 w + 1``
= 3-25 neighbouring slow bins before clipping at 0), ``pmse ref blend`` and
``pmse ref median`` (PMSE against the ``b30 h5`` blend below, with the same
weighted mean of the Lemma-2 variances, or against the band-wise median of
the valid candidates, with the median of their variances), ``blend b30
h5`` (``per_band=True``: candidates weighted per slow bin by
``exp(-30 (score - best))``, score the mean log eiv std over the bin's bands
averaged over 11 slow bins), ``blend b10 h10`` (softer weights, 21 bins) and
``mix`` (the mean of the PMSE pick's and the ``b30 h5`` blend's band values).

``--mix`` also prints the mixes ``a`` times the PMSE pick's band values plus
``1 - a`` times a per-bin blend's (:func:`mix_ratios`; ``a`` = 0.3, 0.5, 0.7,
blends at sharpness / half width 30 / 5, 10 / 10, 100 / 5, 30 / 10).

``--diagnose`` also prints, for each record where PMSE is above 1.25x, why
(:func:`diagnose`): the share of the oracle's bins above 30 % relative error,
PMSE's predicted over actual error for the oracle's setting and its own pick,
the reference's error over its Lemma-2 variance, and the eiv over the
Lemma-2 variances.

``--speed`` times the scoring of the default grid on one record instead.

Run:  python benchmarks/selection_rules.py --seeds 1000-1019 --cache tune.pkl
      python benchmarks/selection_rules.py --seeds 2000-2019 --wafer \
          --cache held.pkl
      python benchmarks/selection_rules.py --cache tune.pkl --diagnose
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
    worst_stage_mean,
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


def true_band(rec):
    """The true FRF at every band value: fast bin ``j = k + f M`` of slow bin
    ``k`` and band ``f``, conjugated from its mirror ``N - j`` above ``N/2``."""
    M, N, F = rec["M"], rec["N"], rec["F"]
    j = np.arange(M // 2 + 1)[:, None] + M * np.arange(F)[None]
    G = rec["G"]
    return np.where(j <= N // 2, G[np.minimum(j, N // 2)],
                    np.conj(G[np.clip(N - j, 0, N // 2)]))


def band_relative_errors(rec, band):
    """Relative error ``|G_hat - G| / |G|`` per fast bin of band values (NaN
    where the truth is zero or not finite, and at DC)."""
    G = rec["G"]
    usable = np.isfinite(G) & (np.abs(G) > 0)
    usable[0] = False
    frf = one_sided_fast_grid(band, rec["N"], rec["F"], conj=True)
    rel = np.abs(frf - G) / np.abs(np.where(usable, G, 1.0))
    return np.where(usable, rel, np.nan)


def band_error(rec, band) -> float:
    """Median relative error over the valid fast bins of band values."""
    return float(np.nanmedian(band_relative_errors(rec, band)))


def _reference(rec) -> int:
    n_invalid = (~rec["ok"]).sum(axis=1)
    todo = np.flatnonzero(n_invalid == n_invalid.min())
    return int(max(todo, key=lambda i: (rec["layouts"][i].window,
                                        rec["layouts"][i].n_params, -i)))


def pmse_terms(rec, var, *, kappa=1.0, weight=2.0, half_width=0,
               reference=None):
    """PMSE's predicted relative squared error per band value of every
    candidate: ``max(|G_c - G_r|^2 - kappa var_r, 0) + weight var_c`` over
    ``|G_r|^2``, the bias estimate averaged over ``2 half_width + 1`` slow
    bins before the clip.

    ``reference``: ``(band_r, var_r)`` of shape (M//2+1, F) instead of the
    widest richest candidate (NaN band values where it has none).

    Returns ``(rel, both, size)``: rel (C, M//2+1, F), NaN outside ``both``
    (the band values scored) and ``size = |G_r|^2``.
    """
    if reference is None:
        r = _reference(rec)
        band_r, var_r, ok_r = rec["band"][r], var[r], rec["ok"][r]
    else:
        band_r, var_r = reference
        ok_r = np.isfinite(band_r).all(axis=-1)
    size = np.abs(band_r) ** 2
    both = (rec["ok"] & ok_r)[..., None] & (size > 0)[None]
    both &= np.isfinite(var) & np.isfinite(var_r)[None]
    both[:, 0, 0] = False
    with np.errstate(invalid="ignore", divide="ignore"):
        excess = (np.abs(rec["band"] - band_r) ** 2 - kappa * var_r) / size
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
    return np.where(both, rel, np.nan), both, size


def pmse_values(rec, var, **options) -> np.ndarray:
    """PMSE per candidate: the median of :func:`pmse_terms` (inf if none)."""
    rel = pmse_terms(rec, var, **options)[0]
    return np.array([np.median(x[np.isfinite(x)]) if np.isfinite(x).any()
                     else np.inf for x in rel])


def pmse_pick(rec, var, **options) -> int:
    """The candidate with the lowest :func:`pmse_values` among those with the
    fewest invalid windows (as the estimator)."""
    values = pmse_values(rec, var, **options)
    return int(np.lexsort((values, (~rec["ok"]).sum(axis=1)))[0])


def blend_weights(rec, sharpness, half_width):
    """Per-slow-bin weights (C, M//2+1) of all candidates by the eiv std
    (``per_band=True`` with ``bands=None``, recomputed from the cached std),
    and where any candidate is scored."""
    with np.errstate(divide="ignore", invalid="ignore"):
        score = 0.5 * np.log(rec["var_eiv"]).mean(axis=-1)
    score = np.where(rec["ok"] & np.isfinite(score), score, np.inf)
    score = smooth_scores(score, half_width, rec["M"])
    best = score.min(axis=0)
    finite = np.isfinite(best)
    with np.errstate(invalid="ignore"):
        w = np.exp(-sharpness * (score - np.where(finite, best, 0.0)))
    w = np.where(np.isfinite(score) & (w >= 1e-6), w, 0.0)
    return w / np.where(finite, w.sum(axis=0), 1.0), finite


def _weighted(w, finite, values):
    out = np.sum(w[..., None] * np.where(w[..., None] > 0, values, 0), 0)
    out[~finite] = np.nan
    return out


def blend_band(rec, sharpness, half_width):
    """Per-slow-bin blend of all candidates by the eiv std (``per_band=True``
    with ``bands=None``, its weights recomputed from the cached std)."""
    return _weighted(*blend_weights(rec, sharpness, half_width), rec["band"])


def blend_reference(rec, var):
    """The default blend's band values and the same weighted mean of the
    candidates' variances ``var``, as a PMSE reference."""
    w, finite = blend_weights(rec, SCORE_SHARPNESS, SCORE_HALF_WIDTH)
    return _weighted(w, finite, rec["band"]), _weighted(w, finite, var)


def median_reference(rec, var):
    """Band-wise median of the valid candidates (real and imaginary parts
    apart) and the median of their variances ``var``, as a PMSE reference."""
    ok = rec["ok"][..., None] & np.isfinite(var)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN bins
        band = np.where(ok, rec["band"], np.nan)
        median = (np.nanmedian(band.real, axis=0)
                  + 1j * np.nanmedian(band.imag, axis=0))
        return median, np.nanmedian(np.where(ok, var, np.nan), axis=0)


KAPPAS = (1.5, 2.0, 3.0, 4.0, 6.0)
HALF_WIDTHS = (1, 3, 6, 12)


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
    for kappa in KAPPAS:
        ratio[f"pmse kappa {kappa:g}"] = rec["errors"][
            pmse_pick(rec, rec["var"], kappa=kappa)] / oracle
    for h in HALF_WIDTHS:
        ratio[f"pmse h{h}"] = rec["errors"][
            pmse_pick(rec, rec["var"], half_width=h)] / oracle
    for name, reference in (("blend", blend_reference),
                            ("median", median_reference)):
        ratio[f"pmse ref {name}"] = rec["errors"][pmse_pick(
            rec, rec["var"], reference=reference(rec, rec["var"]))] / oracle
    blend = blend_band(rec, SCORE_SHARPNESS, SCORE_HALF_WIDTH)
    ratio[f"blend b{SCORE_SHARPNESS:g} h{SCORE_HALF_WIDTH}"] = (
        band_error(rec, blend) / oracle)
    ratio["blend b10 h10"] = band_error(rec, blend_band(rec, 10.0, 10)) / oracle
    ratio["mix"] = band_error(rec, 0.5 * (blend + rec["band"][chosen])) / oracle
    return ratio


#: ``--mix``: (sharpness, half width) of the blend and the PMSE pick's share.
MIX_BLENDS = ((30.0, 5), (10.0, 10), (100.0, 5), (30.0, 10))
MIX_SHARES = (0.3, 0.5, 0.7)


def mix_ratios(rec) -> dict:
    """Error over the oracle's of ``a`` times the PMSE pick's band values plus
    ``1 - a`` times the per-bin blend's, per (sharpness, half width, a)."""
    oracle = rec["errors"].min()
    chosen = rec["band"][pick(rec, "pmse")]
    out = {}
    for sharpness, half_width in MIX_BLENDS:
        blend = blend_band(rec, sharpness, half_width)
        for a in MIX_SHARES:
            out[(sharpness, half_width, a)] = band_error(
                rec, a * chosen + (1 - a) * blend) / oracle
    return out


def _setting(rec, i) -> tuple:
    return tuple(rec["grid"][i].values())


def diagnose(rec) -> dict:
    """Why PMSE misses the oracle on one record.

    ``noisy``: fraction of the oracle's valid fast bins with more than 30 %
    relative error. ``pred_oracle`` / ``pred_pick``: PMSE's value (its
    predicted relative squared error) for the oracle's setting and for its
    own pick over the actual one, the median over the same band values of
    ``|G_c - G|^2 / |G_r|^2``. ``ref_calib``: the reference's median of
    ``|G_r - G|^2 / var_r`` (Lemma-2 ``var_r``) over ``ln 2``, which is 1 for
    complex Gaussian errors of that variance. ``eiv_num2`` / ``eiv_rich``:
    the median ratio of the eiv to the Lemma-2 variances over the valid band
    values of the candidates with numerator degree 2 / of the reference (the
    widest, richest candidate).
    """
    oracle = int(np.argmin(rec["errors"]))
    chosen = pmse_pick(rec, rec["var"])
    rel, both, size = pmse_terms(rec, rec["var"])
    values = pmse_values(rec, rec["var"])
    truth = true_band(rec)
    usable = np.isfinite(truth) & (np.abs(truth) > 0)
    usable[0] = False

    def predicted_over_actual(i):
        keep = both[i] & usable
        actual = np.abs(rec["band"][i] - truth) ** 2 / size
        return values[i] / np.median(actual[keep])

    r = _reference(rec)
    keep = rec["ok"][r][:, None] & usable & np.isfinite(rec["var"][r])
    calib = np.abs(rec["band"][r] - truth) ** 2 / rec["var"][r]
    with np.errstate(invalid="ignore", divide="ignore"):
        eiv = rec["var_eiv"] / rec["var"]
    eiv = np.where(rec["ok"][..., None] & np.isfinite(eiv), eiv, np.nan)
    num2 = np.array([c["num_degree"] == 2 for c in rec["grid"]])
    oracle_rel = band_relative_errors(rec, rec["band"][oracle])
    return {
        "label": rec["label"], "ratio": rec["errors"][chosen] / rec["errors"][oracle],
        "oracle": _setting(rec, oracle), "pick": _setting(rec, chosen),
        "oracle_error": rec["errors"][oracle],
        "noisy": np.mean(oracle_rel[np.isfinite(oracle_rel)] > 0.3),
        "pred_oracle": predicted_over_actual(oracle),
        "pred_pick": predicted_over_actual(chosen),
        "ref_calib": np.median(calib[keep]) / np.log(2),
        "eiv_num2": np.nanmedian(eiv[num2]),
        "eiv_rich": np.nanmedian(eiv[r]),
    }


def print_diagnoses(records, rows) -> None:
    """:func:`diagnose` for the records where PMSE is above 1.25x."""
    worst = [rec for rec, row in zip(records, rows, strict=True)
             if row["pmse (default)"] > 1.25]
    print(f"\n{len(worst)} records with pmse above 1.25x: ratio, oracle error, "
          "oracle / pmse setting, oracle bins > 30 %, PMSE predicted / actual "
          "(oracle, pick), reference error / Lemma-2 var, eiv / Lemma-2 var "
          "(num degree 2, reference)")
    for rec in worst:
        d = diagnose(rec)
        print(f"{d['label']:18s}{d['ratio']:6.2f}{d['oracle_error']:6.2f} "
              f"{d['oracle']} / {d['pick']}{100 * d['noisy']:5.0f} %"
              f"{d['pred_oracle']:6.2f}{d['pred_pick']:6.2f}{d['ref_calib']:6.2f}"
              f"{d['eiv_num2']:6.2f}{d['eiv_rich']:6.2f}")


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
    parser.add_argument("--diagnose", action="store_true",
                        help="also print why PMSE misses the records above 1.25x")
    parser.add_argument("--mix", action="store_true",
                        help="also print the PMSE pick / blend mixes "
                        "(mix_ratios)")
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
          "records above 1.25, mean closed / open loop, worst stage (the mean "
          "of its records) per seed and per seed and loop")
    names = [*rows[0], f"fixed {key}"]
    for name in names:
        a = np.array(fixed if name.startswith("fixed") else [r[name] for r in rows])
        labelled = [{"label": rec["label"], name: x}
                    for rec, x in zip(records, a, strict=True)]
        stage = [worst_stage_mean(labelled, name, parts) for parts in (1, 2)]
        print(f"{name:22s}{a.mean():7.3f}{a.max():7.3f}{np.sum(a > 1.25):4d}"
              f"{a[closed].mean():8.3f}{a[~closed].mean():7.3f}"
              f"{stage[0]:7.3f}{stage[1]:7.3f}")
    if args.diagnose:
        print_diagnoses(records, rows)
    if args.mix:
        mixes = [mix_ratios(rec) for rec in records]
        print("\nmix a * pmse pick + (1 - a) * blend (sharpness, half width, a): "
              "mean, worst, records above 1.25")
        for key in mixes[0]:
            a = np.array([m[key] for m in mixes])
            print(f"{str(key):22s}{a.mean():7.3f}{a.max():7.3f}"
                  f"{np.sum(a > 1.25):4d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
