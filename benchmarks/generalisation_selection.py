"""Does the choice of window and degrees generalise to stages nobody tuned on?

For each random stage ``lrmfrf.plants.random_stage(seed)`` (its own ``F``) and
each of its four systems (``G_y4`` and ``G_z``, closed and open loop), one
record is simulated: a random-phase multisine of ``N = 400 F`` samples (the
slow record has ``M = 400`` samples, ``N = 1200`` at ``F = 3``), slow-output
noise at a signal-to-noise ratio drawn from 30-45 dB. Open-loop stages are
suspended (``random_stage(loop="open")``) and their records are the steady
state of a force shaped to the plant (:func:`record_ingredients`). ``wafer_stage()``
(``F = 3``) is added with ``seed="wafer"``. Every setting of
``LRMBeyondNyquistCV``'s default grid is fitted once (closed form, QR with
leverages); its error is the median over the valid fast bins ``k >= 1`` (true
FRF finite and non-zero) of ``|G_hat - G| / |G|`` against
``lrmfrf.simulate.true_frf``. The *oracle* of a record is the setting with
the lowest error. Per criterion, the table reports the pick's error divided by
the oracle's, its mean and worst over records; ``fixed`` is the one setting of
the grid with the lowest mean ratio over the records of the table (chosen with
the truth, so a bound no criterion can use).

Tuning stages: seeds 1000-1019; held-out stages: seeds 2000-2019. The
criteria are those of ``lrmfrf.estimators.selection.CRITERIA`` and the
variants explored for issue 15 (:func:`criterion_values`: ``loo`` full-window
leave-one-out, ``*_g`` geometric means over windows, ``aicg_k<c>`` the GAIC
family, ``dofg_k<c>``, ``bicg``, ``relstd`` the Lemma-2 relative std).
``pmse`` (the default since its second round) is scored by the library's own
function from the cached band values and Lemma-2 variances of every
candidate (``per_window["band"]``, ``["gvar"]``), so the criteria of a record
can be re-scored without refitting (:func:`criterion_values`).

``--mimo`` runs the same table on 2x2 systems instead: ``G[0:2, 0:2]`` of
``random_stage(seed, mimo=True)`` (the four-corner plate, its own ``F``;
``--wafer`` adds ``mimo_wafer_stage()`` at F = 3), two orthogonal multisine
experiments (:func:`lrmfrf.signals.orthogonal_multisines`) of ``N = 400 F``
samples, 30-45 dB on every output; each output row is scored as its own
local problem and the criterion pools the rows, as ``LRMBeyondNyquistCV``
does on MIMO data; the error is the median over all four entries and the
valid bins (library criteria but PRESS).

``--per-band`` runs the per-band study instead: cluster stages
(:func:`cluster_stage`: rigid body below 100 Hz and three modes aliasing onto
about the same slow frequency), one record each at 40 dB, the RMS relative
error of ``LRMBeyondNyquistCV(per_band=True)`` against the global pick and the
best single setting of the grid on that record, and the median relative errors
in the rigid-body region and around the cluster. With ``--mimo`` it runs on
2x2 cluster stages instead (:func:`cluster_mimo_stage`: the four-corner plate
with three such modes of random shapes, ``G[0:2, 0:2]``, two orthogonal
multisine experiments, the relative error of the 2x2 matrix per bin).
``--std-method eiv_robust`` passes ``std_method`` to the per-band
``LRMBeyondNyquistCV`` (the candidates' ``frf_std_``, and so the blend
weights); the single settings compared against are unchanged.

Run:  python benchmarks/generalisation_selection.py --seeds 1000-1019
      python benchmarks/generalisation_selection.py --seeds 2000-2019 --wafer
      python benchmarks/generalisation_selection.py --mimo --seeds 3000-3019 --wafer
      python benchmarks/generalisation_selection.py --per-band --seeds 1-8
      python benchmarks/generalisation_selection.py --per-band --mimo --seeds 1-8
      python benchmarks/generalisation_selection.py --per-band --mimo --seeds 1-8 --std-method eiv_robust
      [--n-jobs 2] [--criteria gaic aicc aicg_k3 ...] [--csv out.csv]
(about 5 s of CPU per record; 15-20 min per 20 stages on a loaded 2-core box)
"""

from __future__ import annotations

import argparse
import csv
import sys

import numpy as np
from joblib import Parallel, delayed

from lrmfrf.estimators.selection import (
    CRITERIA,
    LRMBeyondNyquistCV,
    _combine,
    _local_criteria,
    _pmse_criteria,
)
from lrmfrf.local_models import one_sided_fast_grid
from lrmfrf.plants import mimo_wafer_stage, random_stage, wafer_stage
from lrmfrf.signals import multisine, orthogonal_multisines
from lrmfrf.simulate import periodic_state, simulate, true_frf
from lrmfrf.windows import LocalModelLayout

#: Slow samples per record (N = SLOW_SAMPLES * F).
SLOW_SAMPLES = 400
#: Signal-to-noise ratios are drawn uniformly from this range (dB).
SNR_RANGE = (30.0, 45.0)
SYSTEMS = (("closed", "G_y4"), ("closed", "G_z"), ("open", "G_y4"), ("open", "G_z"))


def default_grid(F: int, M: int = SLOW_SAMPLES) -> list[dict]:
    """The candidates of ``LRMBeyondNyquistCV()`` that are feasible for one
    record of ``M`` slow samples (at least 2 residual dof), in its order."""
    est = LRMBeyondNyquistCV()
    candidates = est._candidates(est._checked_params())
    out = []
    for c in candidates:
        layout = LocalModelLayout(F=F, **c)
        if layout.dof >= 2 and layout.window <= M:
            out.append(c)
    return out


def stage_systems(seed) -> list[tuple[str, object, int]]:
    """``(label, system, F)`` of the four systems of one stage (or the wafer
    stage's two closed-loop systems for ``seed="wafer"``)."""
    if seed == "wafer":
        stage = wafer_stage()
        return [(f"wafer/closed/{name}", getattr(stage, name), 3)
                for name in ("G_y4", "G_z")]
    out = []
    for loop, name in SYSTEMS:
        stage, draw = random_stage(int(seed), loop=loop)
        out.append((f"{seed}/{loop}/{name}", getattr(stage, name),
                    draw.downsampling_factor))
    return out


def mimo_stage_systems(seed) -> list[tuple[str, object, int]]:
    """``(label, 2x2 system, F)`` of one MIMO random stage (or of
    ``mimo_wafer_stage()`` at F = 3 for ``seed="wafer"``)."""
    if seed == "wafer":
        return [("mimo-wafer", mimo_wafer_stage(downsampling_factor=3).G[0:2, 0:2],
                 3)]
    stage, draw = random_stage(int(seed), mimo=True)
    return [(f"{seed}/mimo", stage.G[0:2, 0:2], draw.downsampling_factor)]


def mimo_record_ingredients(system, F: int, seed: int, grid=None) -> dict:
    """As :func:`record_ingredients` for a 2x2 system and two orthogonal
    multisine experiments; per-window arrays are ``(n_y, M//2+1)``."""
    rng = np.random.default_rng(seed)
    N = SLOW_SAMPLES * F
    snr = float(rng.uniform(*SNR_RANGE))
    u = orthogonal_multisines(2, N, rng=rng)  # (P, n_u, N)
    y = np.stack([simulate(system, u[p], F, snr_db=snr, rng=rng).y_l
                  for p in range(2)])  # (P, n_y, M)
    G = true_frf(system, N)  # (n_y, n_u, K)
    U = np.fft.fft(u, axis=-1).reshape(2, 2 * N)
    Y = np.fft.fft(y, axis=-1)
    grid = mimo_grid(F) if grid is None else grid
    usable = np.isfinite(G) & (np.abs(G) > 0)
    usable[..., 0] = False
    errors = np.empty(len(grid))
    per_window, layouts = [], []
    for i, c in enumerate(grid):
        layout = LocalModelLayout(F=F, n_experiments=2, n_inputs=2, **c)
        residual, ok, bands, variances = [], [], [], []
        rel = np.full(G.shape, np.nan)
        for o in range(2):  # QR with the band variances (for "pmse")
            per_bin, ok_o, band, var = _local_criteria(U, Y[:, o], layout,
                                                       variance=True)
            residual.append(per_bin["residual"])
            ok.append(ok_o)
            bands.append(band)
            variances.append(var)
            for j in range(2):
                frf = one_sided_fast_grid(band[:, j * F:(j + 1) * F], N, F,
                                          conj=True)
                rel[o, j] = np.abs(frf - G[o, j]) / np.abs(
                    np.where(usable[o, j], G[o, j], 1.0))
        rel[~usable] = np.nan
        errors[i] = np.nanmedian(rel) if np.isfinite(rel).any() else np.inf
        per_window.append({"residual": np.stack(residual), "ok": np.stack(ok),
                           "band": np.stack(bands), "var": np.stack(variances)})
        layouts.append(layout)
    return {"errors": errors, "per_window": per_window, "layouts": layouts,
            "snr_db": snr, "N": N, "M": N // F, "F": F, "grid": grid}


def mimo_grid(F: int, M: int = SLOW_SAMPLES) -> list[dict]:
    """The default candidates feasible for two inputs and two experiments."""
    est = LRMBeyondNyquistCV()
    out = []
    for c in est._candidates(est._checked_params()):
        layout = LocalModelLayout(F=F, n_experiments=2, n_inputs=2, **c)
        if layout.dof >= 2 and layout.window <= M:
            out.append(c)
    return out


def record_ingredients(system, F: int, seed: int, grid=None, *,
                       open_loop: bool = False, per_band: bool = False) -> dict:
    """Simulate one record; per candidate its true error and criteria inputs.

    ``open_loop``: the record of an open-loop (suspended) stage is taken as an
    engineer would, and as ``generalisation_diagnose.py`` does: the force
    shaped to the plant (amplitudes ``1 / |G(k)|``) and the periodic steady
    state; a flat force from rest leaves the FRF above a few tens of Hz
    buried in the noise and the transient of the low-frequency motion.

    ``per_band``: also fit ``LRMBeyondNyquistCV(per_band=True)`` (every
    candidate fitted and weighted per slow bin by its predicted std) and store
    its median relative error as ``per_band_error``.

    Returns
    -------
    dict
        ``errors`` (C,), median relative error over valid bins; ``rel`` (C, K)
        the per-bin relative errors (NaN where not valid); ``per_window``: list
        of dicts of per-window arrays (``residual``, ``press``, ``ok``,
        ``relvar`` the Lemma-2 variance factor over |G_hat|^2 summed over
        bands); ``layouts``; ``snr_db``; ``N``.
    """
    N = SLOW_SAMPLES * F
    u, y_l, snr = regenerate_record(system, F, seed, open_loop=open_loop,
                                    return_snr=True)
    G = true_frf(system, N)
    U = np.fft.fft(u)[None]
    Y = np.fft.fft(y_l)[None]
    grid = default_grid(F) if grid is None else grid
    usable = np.isfinite(G) & (np.abs(G) > 0)
    usable[0] = False
    errors = np.empty(len(grid))
    rel = np.full((len(grid), G.size), np.nan)
    per_window, layouts = [], []
    for i, c in enumerate(grid):
        layout = LocalModelLayout(F=F, **c)
        per_bin, ok, band, extra = _ingredients(U, Y, layout)
        frf = one_sided_fast_grid(band, N, F, conj=True)
        r = np.abs(frf - G) / np.abs(np.where(usable, G, 1.0))
        r[~usable] = np.nan
        rel[i] = r
        errors[i] = np.nanmedian(r) if np.isfinite(r).any() else np.inf
        per_window.append({**per_bin, "ok": ok, **extra})
        layouts.append(layout)
    out = {"errors": errors, "rel": rel, "per_window": per_window,
           "layouts": layouts, "snr_db": snr, "N": N, "M": N // F, "F": F,
           "grid": grid}
    if per_band:
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cv = LRMBeyondNyquistCV(per_band=True).fit(u, y_l, F)
        r = np.abs(cv.frf_ - G) / np.abs(np.where(usable, G, 1.0))
        r[~(usable & cv.valid_)] = np.nan
        out["per_band_error"] = float(np.nanmedian(r))
    return out


def regenerate_record(system, F: int, seed: int, *, open_loop: bool = False,
                      return_snr: bool = False):
    """The fast input and slow output ``(u, y_l)`` of the record of
    :func:`record_ingredients` (the same random draws), and its SNR (dB)
    with ``return_snr``."""
    rng = np.random.default_rng(seed)
    N = SLOW_SAMPLES * F
    snr = float(rng.uniform(*SNR_RANGE))
    amplitude = None
    if open_loop:
        size = np.abs(true_frf(system, N))
        amplitude = 1.0 / np.maximum(size, 1e-6 * size.max())
    u = multisine(N, rng=rng, amplitude=amplitude)
    sim = simulate(system, u, F, snr_db=snr, rng=rng,
                   x0=periodic_state(system, u) if open_loop else None)
    return (u, sim.y_l, snr) if return_snr else (u, sim.y_l)


def _ingredients(U, Y, layout):
    """The library's per-window criteria plus extras explored here."""
    from lrmfrf.local_models import half_slow_bins
    from lrmfrf.solvers import solve_local_least_squares
    from lrmfrf.windows import local_regressor

    per_bin, ok, band = _local_criteria(U, Y, layout)
    bins = half_slow_bins(Y.shape[1])
    A, b = local_regressor(U, Y, bins, layout)
    sol = solve_local_least_squares(
        A, b, return_leverage=True,
        rank_columns=layout.n_system + layout.n_transient)
    theta = np.where(sol.well_posed[:, None], sol.theta, 0.0)
    res = b - np.einsum("bij,bj->bi", A, theta)
    M = Y.shape[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        loo = np.mean(np.abs(res / (1.0 - sol.leverage)) ** 2, axis=1) / M
        gvar = layout.F**2 * sol.gram_inv_diag[:, : layout.F]
        relvar = np.sum(gvar / np.abs(band) ** 2, axis=1)
        absvar = np.sum(gvar, axis=1)
    return per_bin, ok, band, {"loo": loo, "relvar": relvar, "absvar": absvar,
                               "band": band, "gvar": gvar}


# --- criteria -----------------------------------------------------------------


def _weights(size: int, M: int) -> np.ndarray:
    w = np.full(size, 2.0)
    w[0] = 1.0
    if M % 2 == 0:
        w[-1] = 1.0
    return w


def _wmean(values, ok, M):
    w = _weights(values.size, M)[ok]
    return float(np.sum(w * values[ok]) / w.sum()) if w.size else np.inf


def criterion_values(rec: dict, name: str) -> np.ndarray:
    """Value of criterion ``name`` for every candidate of a record."""
    M = rec["M"]
    if name == "pmse":  # the library's, from the cached band values
        ingredients = {}
        for i, (pw, layout) in enumerate(zip(rec["per_window"], rec["layouts"],
                                             strict=True)):
            if "var" in pw:  # 2x2 records: (n_y, M//2+1, n_u F) already
                ingredients[i] = (pw["band"], pw["var"], pw["ok"])
                continue
            var = pw["gvar"] * (pw["residual"] * M * layout.n_equations
                                / layout.dof)[:, None]
            ingredients[i] = (pw["band"][None], var[None], pw["ok"][None])
        scored = _pmse_criteria(ingredients, rec["layouts"])
        return np.array([scored[i].value for i in range(len(rec["layouts"]))])
    out = np.empty(len(rec["layouts"]))
    for i, (pw, layout) in enumerate(zip(rec["per_window"], rec["layouts"],
                                         strict=True)):
        ok = pw["ok"]
        if not ok.any():
            out[i] = np.inf
            continue
        L, p = layout.n_equations, layout.n_params
        if name in CRITERIA:
            values = pw["press" if name == "press" else "residual"]
            out[i] = _combine(values, ok, layout, name, M)
        elif name == "loo":
            out[i] = np.log(_wmean(pw["loo"], ok, M))
        elif name.startswith("aic_k"):  # log s2 + k p / (L - p - 1)
            k = float(name[5:])
            out[i] = np.log(_wmean(pw["residual"], ok, M)) + k * p / (L - p - 1)
        elif name.endswith("_g"):  # geometric mean over windows, then penalty
            base = name[:-2]
            key = {"press": "press", "loo": "loo"}.get(base, "residual")
            logs = _wmean(np.log(pw[key]), ok, M)
            penalty = {"aicc": (L + p) / (L - p - 1),
                       "gcv": -2 * np.log(1 - p / L),
                       "fpe": np.log((L + p) / (L - p))}.get(base, 0.0)
            out[i] = logs + penalty
        elif name.startswith("aicg_k"):  # geometric mean + k p / (L - p - 1)
            k = float(name[6:])
            out[i] = _wmean(np.log(pw["residual"]), ok, M) + k * p / (L - p - 1)
        elif name.startswith("dofg_k"):  # unbiased s2 = rss/(L-p), + k p/(L-p)
            k = float(name[6:])
            out[i] = (_wmean(np.log(pw["residual"] * L / (L - p)), ok, M)
                      + k * p / (L - p))
        elif name == "bicg":
            out[i] = (_wmean(np.log(pw["residual"]), ok, M)
                      + np.log(L) * p / (L - p - 1))
        elif name == "relstd":  # s2_dof * relvar, mean of logs over windows
            s2 = pw["residual"] * L / (L - p)
            out[i] = _wmean(np.log(s2 * pw["relvar"]), ok, M)
        elif name == "relstd_med":
            s2 = pw["residual"] * L / (L - p)
            out[i] = float(np.median(np.log(s2 * pw["relvar"])[ok]))
        else:
            raise ValueError(name)
    return out


def pick(rec: dict, name: str) -> int:
    """Index chosen by criterion ``name`` (fewest invalid bins first, as the
    estimator)."""
    values = criterion_values(rec, name)
    n_invalid = np.array([np.count_nonzero(~pw["ok"]) for pw in rec["per_window"]])
    return int(np.lexsort((values, n_invalid))[0])


def selection_table(seeds, *, criteria=CRITERIA, n_jobs: int = 1,
                    records=None, mimo: bool = False,
                    per_band: bool = False) -> dict:
    """Pick / oracle ratios of each criterion over the records of ``seeds``.

    Parameters
    ----------
    seeds : iterable of int or "wafer"
        Random-stage seeds (four records each) and/or ``"wafer"``.
    criteria : sequence of str
        Names known to :func:`criterion_values`.
    n_jobs : int
        Records simulated and fitted in parallel.
    records : list of dict, optional
        Precomputed :func:`record_ingredients` (with ``label``) to reuse.
    mimo : bool
        2x2 systems (:func:`mimo_stage_systems`, :func:`mimo_record_ingredients`).
    per_band : bool
        Also ``LRMBeyondNyquistCV(per_band=True)`` (SISO; its blended FRF
        against the same oracle): the row ``per_band``.

    Returns
    -------
    dict
        ``rows`` (one per record: label, F, snr, oracle setting and error, the
        ratio of each criterion), ``summary`` (per criterion and ``fixed``:
        mean and worst ratio, and the worst stage's mean ratio per seed and
        per seed and loop, :func:`worst_stage_mean`), ``fixed`` (the best
        single setting).
    """
    if records is None:
        systems = mimo_stage_systems if mimo else stage_systems
        ingredients = mimo_record_ingredients if mimo else record_ingredients
        jobs = [(label, system, F, 7919 * k + 13)
                for k, seed in enumerate(seeds)
                for label, system, F in systems(seed)]
        out = Parallel(n_jobs=n_jobs)(
            delayed(ingredients)(system, F, rec_seed,
                                 **({"open_loop": True} if "/open/" in label
                                    else {}),
                                 **({"per_band": True} if per_band else {}))
            for label, system, F, rec_seed in jobs
        )
        records = [{**r, "label": label} for (label, *_), r in zip(jobs, out,
                                                                   strict=True)]
    rows = []
    for rec in records:
        oracle = int(np.argmin(rec["errors"]))
        row = {"label": rec["label"], "F": rec["F"], "snr_db": rec["snr_db"],
               "oracle": tuple(rec["grid"][oracle].values()),
               "oracle_error": rec["errors"][oracle]}
        for name in criteria:
            i = pick(rec, name)
            row[name] = rec["errors"][i] / rec["errors"][oracle]
            row[f"{name}_pick"] = tuple(rec["grid"][i].values())
        if "per_band_error" in rec:
            row["per_band"] = rec["per_band_error"] / rec["errors"][oracle]
        rows.append(row)
    best_key, best_ratios = fixed_setting(records)
    for row, ratio in zip(rows, best_ratios, strict=True):
        row["fixed"] = ratio
    names = (*criteria, "fixed") + (("per_band",) if "per_band" in rows[0] else ())
    summary = {name: (float(np.mean([r[name] for r in rows])),
                      float(np.max([r[name] for r in rows])),
                      worst_stage_mean(rows, name),
                      worst_stage_mean(rows, name, parts=2))
               for name in names}
    return {"rows": rows, "summary": summary, "fixed": best_key,
            "records": records}


def worst_stage_mean(rows, name: str, parts: int = 1) -> float:
    """The largest mean ratio over one stage's records: the issue's "worst"
    read per stage rather than per record. The first ``parts`` fields of the
    label (``seed/loop/output``) name the stage: ``parts=1`` a seed's four
    records (closed- and open-loop ``G_y4`` and ``G_z``), ``parts=2`` a
    seed's closed- or open-loop stage (``random_stage(loop=...)``) with its
    two outputs."""
    stages = {}
    for row in rows:
        key = "/".join(row["label"].split("/")[:parts])
        stages.setdefault(key, []).append(row[name])
    return float(max(np.mean(v) for v in stages.values()))


def fixed_setting(records) -> tuple:
    """The one setting of the grid (in every record's grid) with the lowest
    mean error ratio to the oracle, and its ratio per record."""
    # keyed by the setting (grids differ with F)
    keys = {tuple(c.values()) for rec in records for c in rec["grid"]}
    best_key, best_ratios = None, None
    for key in sorted(keys):
        ratios = []
        for rec in records:
            settings = [tuple(c.values()) for c in rec["grid"]]
            if key not in settings:
                ratios = None
                break
            ratios.append(rec["errors"][settings.index(key)] / rec["errors"].min())
        if ratios is not None and (best_ratios is None
                                   or np.mean(ratios) < np.mean(best_ratios)):
            best_key, best_ratios = key, ratios
    return best_key, best_ratios


def _parse_seeds(text: str) -> list:
    out = []
    for part in text.split(","):
        if "-" in part:
            a, b = part.split("-")
            out.extend(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1000-1019",
                        help="random-stage seeds, e.g. 1000-1019 or 2000-2019")
    parser.add_argument("--wafer", action="store_true",
                        help="add wafer_stage() (its two closed-loop systems)")
    parser.add_argument("--criteria", nargs="+",
                        default=["pmse", "gaic", "aicc", "gcv", "press"])
    parser.add_argument("--n-jobs", type=int, default=1)
    parser.add_argument("--csv", help="write one row per record here")
    parser.add_argument("--per-band", action="store_true",
                        help="run the per-band study on cluster stages instead")
    parser.add_argument("--with-per-band", action="store_true",
                        help="also LRMBeyondNyquistCV(per_band=True) on these "
                        "records (SISO; every candidate fitted: slower)")
    parser.add_argument("--mimo", action="store_true",
                        help="2x2 systems of MIMO random stages (library criteria)")
    parser.add_argument("--bands", type=int, default=None,
                        help="regions of the per-band study (default: none, the "
                        "per-slow-bin choice by the predicted std)")
    parser.add_argument("--std-method", default=None,
                        help="per-band study: LRMBeyondNyquistCV(std_method=...) "
                        "for the blend's candidates (default: the library's); "
                        "the single settings compared against are the same")
    args = parser.parse_args(argv)
    if args.std_method is not None and not args.per_band:
        parser.error("--std-method is for the per-band study (--per-band)")
    if args.per_band:
        rows = per_band_table(_parse_seeds(args.seeds), bands=args.bands,
                              n_jobs=args.n_jobs, mimo=args.mimo,
                              std_method=args.std_method)
        if args.std_method is not None:
            print(f"candidates' std_method: {args.std_method}")
        print_per_band(rows)
        return 0
    seeds = _parse_seeds(args.seeds) + (["wafer"] if args.wafer else [])
    if args.mimo:
        if "--criteria" not in (argv if argv is not None else sys.argv):
            args.criteria = ["pmse", "gaic", "aicc", "gcv"]
        if set(args.criteria) - {"pmse", "gaic", "aicc", "gcv"}:
            parser.error("--mimo takes the criteria pmse, gaic, aicc and gcv")
    if args.with_per_band and args.mimo:
        parser.error("--with-per-band is for SISO records")
    table = selection_table(seeds, criteria=args.criteria, n_jobs=args.n_jobs,
                            mimo=args.mimo, per_band=args.with_per_band)
    rows = table["rows"]
    kind = "2x2 records" if args.mimo else "records"
    print(f"{len(rows)} {kind} ({args.seeds}{' + wafer' if args.wafer else ''}); "
          f"M = {SLOW_SAMPLES}, SNR {SNR_RANGE[0]:g}-{SNR_RANGE[1]:g} dB; "
          "ratio = pick error / oracle error (median rel. error, valid bins)")
    print(f"{'criterion':22s}{'mean':>8s}{'worst':>8s}  worst stage (mean of "
          "its records): per seed, per seed and loop")
    for name, (mean, worst, stage, loop) in table["summary"].items():
        label = f"fixed {table['fixed']}" if name == "fixed" else name
        print(f"{label:22s}{mean:8.3f}{worst:8.3f}{stage:8.3f}{loop:8.3f}")
    if args.csv:
        with open(args.csv, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return 0



# --- per-band selection ---------------------------------------------------------


def cluster_stage(seed: int, loop: str = "closed"):
    """A wafer stage (F = 3, Ts = 0.5 ms) with a smooth rigid-body region below
    100 Hz and a cluster of three modes that alias onto about the same slow
    frequency (270-290 Hz: a mode there, one near ``f_slow - f`` and one near
    ``f_slow + f``, ``f_slow = 666.7 Hz``), randomised per seed (frequency
    +-3 %, damping 0.5-2 %, participations)."""
    from dataclasses import replace

    from lrmfrf.plants import Mode
    from lrmfrf.plants.siso_stage import _named

    rng = np.random.default_rng(seed)
    slow_rate = 1.0 / (3 * 0.5e-3)
    for _ in range(100):  # redraw until the lead-PID loop is stable
        freqs = _cluster_frequencies(rng, slow_rate)
        modes = [Mode(float(f), float(rng.uniform(0.005, 0.02)),
                      float(rng.uniform(0.03, 0.15)),
                      float(rng.choice([-1, 1]) * rng.uniform(0.3, 1.2)))
                 for f in freqs]
        try:
            stage = wafer_stage(modes=modes, downsampling_factor=3)
        except ValueError:
            continue
        if stage.margins().phase_margin >= 30.0:
            break
    else:  # pragma: no cover
        raise RuntimeError(f"no stable cluster stage for seed {seed}")
    if loop == "open":
        stage = replace(stage, G_y4=_named(stage.plant[0, 0], "P_y4", "y4"),
                        G_z=_named(stage.plant[1, 0], "P_z", "z"))
    return stage, freqs


def per_band_record(seed: int, loop: str, output: str, bands=None,
                    snr_db: float = 40.0, std_method: str | None = None) -> dict:
    """Per-band pick vs the best single setting of the grid on one record.

    Errors are relative, ``|G_hat - G| / |G|`` over the fast bins valid for
    every estimate; RMS over all of them, medians over the rigid-body region
    (below 100 Hz) and over the cluster (within 15 Hz of its three modes).
    ``std_method`` (``None``: the library's default) is passed to
    ``LRMBeyondNyquistCV`` and so to the candidates whose ``frf_std_`` weighs
    the blend; the single settings compared against are fitted with the
    default (their FRF does not depend on the std route).
    """
    import warnings

    from lrmfrf import LRMBeyondNyquist

    stage, freqs = cluster_stage(seed, loop)
    system = getattr(stage, output)
    F, N = 3, 3 * SLOW_SAMPLES
    rng = np.random.default_rng(10_000 + seed)
    u = multisine(N, rng=rng)
    y = simulate(system, u, F, snr_db=snr_db, rng=rng).y_l
    G = true_frf(system, N)
    f = np.arange(N // 2 + 1) / (N * stage.sample_time)
    usable = np.isfinite(G) & (np.abs(G) > 0)
    usable[0] = False
    rigid = f < 100.0
    cluster = np.min(np.abs(f[:, None] - np.asarray(freqs)), axis=1) < 15.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cv = LRMBeyondNyquistCV(per_band=True, bands=bands,
                                **_std_kwargs(std_method)).fit(u, y, F)
        frfs = [LRMBeyondNyquist(**p).fit(u, y, F).frf_
                for p, ok in zip(cv.cv_results_["params"],
                                 cv.cv_results_["identifiable"], strict=True)
                if ok]
    rel = np.abs(np.array([cv.frf_, cv.best_estimator_.frf_, *frfs]) - G)
    rel = rel / np.abs(np.where(usable, G, 1.0))
    keep = usable & np.isfinite(rel).all(axis=0)
    rms = np.sqrt(np.mean(rel[:, keep] ** 2, axis=1))
    best = 2 + int(np.argmin(rms[2:]))
    med = {name: np.median(rel[:, keep & region], axis=1)
           for name, region in (("rigid", rigid), ("cluster", cluster))}
    return {"seed": seed, "loop": loop, "output": output,
            "rms_per_band": rms[0], "rms_global_pick": rms[1],
            "rms_best_global": rms[best],
            "rigid_per_band": med["rigid"][0], "rigid_best_global":
            med["rigid"][best], "cluster_per_band": med["cluster"][0],
            "cluster_best_global": med["cluster"][best],
            "band_params": [tuple(p.values()) for p in cv.band_params_],
            "best_params": tuple(cv.cv_results_["params"][
                [i for i, ok in enumerate(cv.cv_results_["identifiable"])
                 if ok][best - 2]].values())}


def _std_kwargs(std_method):
    """``{"std_method": std_method}``, or nothing for ``None`` (the default)."""
    return {} if std_method is None else {"std_method": std_method}


def per_band_table(seeds, *, loops=("closed",), outputs=("G_y4", "G_z"),
                   bands=None, n_jobs: int = 1, mimo: bool = False,
                   std_method: str | None = None) -> list[dict]:
    """:func:`per_band_record` over seeds, loops and outputs
    (:func:`per_band_mimo_record` per seed with ``mimo``)."""
    if mimo:
        return Parallel(n_jobs=n_jobs)(
            delayed(per_band_mimo_record)(seed, bands, std_method=std_method)
            for seed in seeds)
    return Parallel(n_jobs=n_jobs)(
        delayed(per_band_record)(seed, loop, output, bands,
                                 std_method=std_method)
        for seed in seeds for loop in loops for output in outputs
    )


def cluster_mimo_stage(seed: int):
    """The four-corner plate (:func:`lrmfrf.plants.mimo_wafer_stage`, F = 3,
    Ts = 0.5 ms, closed loop) with the rigid body and three flexible modes that
    alias onto about the same slow frequency, drawn as in
    :func:`cluster_stage` (265-290 Hz and near ``f_slow -+ f``; damping
    0.5-2 %); each mode's shape is random, at the four corners 0.2-0.8 and at
    the point of interest 0.5-2 in magnitude, with random signs. Redrawn
    until the closed loop is stable: :func:`mimo_wafer_stage` raises
    ``ValueError`` for a draw whose controller does not stabilise it (seeds
    18, 100, 112, 144 and 145 of 1-8, 11-18 and 100-159 on their first draw,
    poles at 1.0004-1.004)."""
    from lrmfrf.plants import PlateMode

    rng = np.random.default_rng(seed)
    slow_rate = 1.0 / (3 * 0.5e-3)
    for _ in range(100):  # redraw until the closed loop is stable
        freqs = _cluster_frequencies(rng, slow_rate)
        modes = [PlateMode(float(f), float(rng.uniform(0.005, 0.02)),
                           tuple(float(v) for v in rng.choice([-1, 1], 4)
                                 * rng.uniform(0.2, 0.8, 4)),
                           float(rng.choice([-1, 1]) * rng.uniform(0.5, 2.0)))
                 for f in freqs]
        try:
            return mimo_wafer_stage(modes=modes, downsampling_factor=3), freqs
        except ValueError:  # an unstable closed loop (or bad parameters)
            continue
    raise RuntimeError(  # pragma: no cover
        f"no stable 2x2 cluster stage for seed {seed}")


def _cluster_frequencies(rng, slow_rate: float) -> list:
    """Three mode frequencies that alias onto about one slow frequency at
    F = 3: ``f`` in 265-290 Hz and just above ``f_slow - f`` / just below
    ``f_slow + f`` (shared by the SISO and 2x2 cluster stages)."""
    base = rng.uniform(265.0, 290.0)
    return [base, (slow_rate - base) * rng.uniform(1.005, 1.03),
            (slow_rate + base) * rng.uniform(0.97, 0.995)]


def cluster_mimo_record(seed: int, snr_db: float = 40.0):
    """The 2x2 record of :func:`per_band_mimo_record`: ``G[0:2, 0:2]`` of
    :func:`cluster_mimo_stage`, two orthogonal multisine experiments of
    ``N = 1200`` (F = 3), ``snr_db`` on each output. Returns ``(stage, freqs,
    system, u, y)``."""
    stage, freqs = cluster_mimo_stage(seed)
    system = stage.G[0:2, 0:2]
    F, N = 3, 3 * SLOW_SAMPLES
    rng = np.random.default_rng(20_000 + seed)
    u = orthogonal_multisines(2, N, rng=rng)
    y = np.stack([simulate(system, u[p], F, snr_db=snr_db, rng=rng).y_l
                  for p in range(2)])
    return stage, freqs, system, u, y


def per_band_mimo_record(seed: int, bands=None, snr_db: float = 40.0,
                         std_method: str | None = None) -> dict:
    """:func:`per_band_record` on the 2x2 block ``G[0:2, 0:2]`` of
    :func:`cluster_mimo_stage`: two orthogonal multisine experiments of
    ``N = 1200``, ``snr_db`` on each output. The relative error of a bin is
    that of the matrix, ``||G_hat(k) - G(k)||_F / ||G(k)||_F`` (entry by
    entry, the small off-diagonal entries of the decoupled loop make the RMS
    of entry-wise relative errors about 10 and meaningless)."""
    import warnings

    from lrmfrf import LRMBeyondNyquist

    stage, freqs, system, u, y = cluster_mimo_record(seed, snr_db)
    F, N = 3, u.shape[-1]
    G = true_frf(system, N)  # (2, 2, N//2 + 1)
    f = np.arange(N // 2 + 1) / (N * stage.sample_time)
    size = np.sqrt(np.sum(np.abs(G) ** 2, axis=(0, 1)))  # ||G(k)||_F
    usable = np.isfinite(size) & (size > 0)
    usable[0] = False
    rigid = f < 100.0
    cluster = np.min(np.abs(f[:, None] - np.asarray(freqs)), axis=1) < 15.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cv = LRMBeyondNyquistCV(per_band=True, bands=bands,
                                **_std_kwargs(std_method)).fit(u, y, F)
        ok = [p for p, good in zip(cv.cv_results_["params"],
                                   cv.cv_results_["identifiable"], strict=True)
              if good]
        frfs = [LRMBeyondNyquist(**p).fit(u, y, F).frf_ for p in ok]
    diff = np.array([cv.frf_, cv.best_estimator_.frf_, *frfs]) - G
    rel = np.sqrt(np.sum(np.abs(diff) ** 2, axis=(1, 2)))
    rel = rel / np.where(usable, size, 1.0)
    keep = usable & np.isfinite(rel).all(axis=0)
    rms = np.sqrt(np.mean(rel[:, keep] ** 2, axis=1))
    best = 2 + int(np.argmin(rms[2:]))
    med = {name: np.median(rel[:, keep & region], axis=1)
           for name, region in (("rigid", rigid), ("cluster", cluster))}
    return {"seed": seed, "loop": "closed", "output": "G[0:2,0:2]",
            "rms_per_band": rms[0], "rms_global_pick": rms[1],
            "rms_best_global": rms[best],
            "rigid_per_band": med["rigid"][0], "rigid_best_global":
            med["rigid"][best], "cluster_per_band": med["cluster"][0],
            "cluster_best_global": med["cluster"][best],
            "band_params": [tuple(p.values()) for p in cv.band_params_],
            "best_params": tuple(ok[best - 2].values())}


def print_per_band(rows) -> None:
    print("per-band vs the global pick and the best single setting of the grid "
          "(lowest RMS relative error on that record); cluster stages (F = 3, "
          "M = 400, 40 dB); rigid/cluster: median relative error per-band/best")
    print(f"{'record':22s}{'RMS band':>9s}{'RMS pick':>9s}{'RMS best':>9s}"
          f"{'gain':>7s}"
          f"{'rigid b/g':>16s}{'cluster b/g':>16s}  band settings")
    for r in rows:
        gain = 1 - r["rms_per_band"] / r["rms_best_global"]
        settings = r["band_params"]
        shown = (f"{len(settings)} settings" if len(settings) > 4
                 else str(settings))
        print(f"{r['seed']:>4d}/{r['loop']}/{r['output']:9s}"
              f"{r['rms_per_band']:9.4f}{r['rms_global_pick']:9.4f}"
              f"{r['rms_best_global']:9.4f}{gain:7.1%}"
              f"{r['rigid_per_band']:8.4f}/{r['rigid_best_global']:.4f}"
              f"{r['cluster_per_band']:8.4f}/{r['cluster_best_global']:.4f}"
              f"  best {r['best_params']}; {shown}")
    ratio = np.array([r["rms_per_band"] / r["rms_best_global"] for r in rows])
    vs_pick = np.array([r["rms_per_band"] / r["rms_global_pick"] for r in rows])
    rigid = np.array([r["rigid_per_band"] / r["rigid_best_global"] for r in rows])
    cluster = np.array([r["cluster_per_band"] / r["cluster_best_global"]
                        for r in rows])
    print(f"RMS relative error, per-band / best single setting of the grid: mean "
          f"{ratio.mean():.3f} (gain {1 - ratio.mean():.1%}), median "
          f"{np.median(ratio):.3f}, worst {ratio.max():.3f}; per-band / global "
          f"pick: mean {vs_pick.mean():.3f}, median {np.median(vs_pick):.3f}")
    print(f"median error per region, per-band / best single setting (median over "
          f"records [min, max]): rigid body {np.median(rigid):.3f} "
          f"[{rigid.min():.3f}, {rigid.max():.3f}] ({np.mean(rigid <= 1):.0%} of "
          f"records <= 1), cluster {np.median(cluster):.3f} [{cluster.min():.3f}, "
          f"{cluster.max():.3f}] ({np.mean(cluster <= 1):.0%} <= 1)")


if __name__ == "__main__":
    sys.exit(main())
