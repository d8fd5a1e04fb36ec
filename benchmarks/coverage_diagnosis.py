"""Which ingredient of ``std_method="eiv_robust"`` moves its median ratio?

A diagnosis for one (F, SNR) cell of ``benchmarks/coverage_bias_study.py``
(issue 15, item 2): the same systems (``stage_systems(..., alternate=True)``
of ``benchmarks/generalisation_std.py`` plus both ``wafer_stage()`` outputs),
the same multisine and noise seeds, ``M = 400``, the half windows of
``HALF_WINDOW``. Per run the default fit gives the ``"eiv"`` shape ``F^2
diag(S^H diag|e|^2 S)`` (per unit noise level) and the window's own level
``s_k = ||r||^2 / sum |e|^2 (1 - h)``; the variants are that shape times

``own``     ``s_k`` (the default ``"eiv"``),
``true``    the true noise level ``M sigma^2`` (shape only),
``pmed``    the neighbours' median level over median(chi^2_2q / 2q),
``switch2`` ``pmed``, or ``s_k`` where ``s_k > 2 pmed`` (``"eiv_robust"``'s
            noise part),

each with and without the neighbour term ``+nbr`` (``"eiv_robust"`` is
``switch2+nbr``). Printed per variant: the median over systems of the
median-over-bins ratio to the Monte-Carlo std and the mean 2-std coverage;
then the levels over the true one (median over windows and runs), the
fraction of windows that switch and of bins that get the neighbour term, and
the median ratio of ``switch2+nbr`` on the bins where the neighbour term is
added in at least half of the runs and on the others. Run::

    nice -n 5 python benchmarks/coverage_diagnosis.py --F 5 --snr 70 \\
        --seeds 1000-1009 --runs 30
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import numpy as np

from lrmfrf import LRMBeyondNyquist
from lrmfrf.local_models import dft, one_sided_fast_grid
from lrmfrf.signals import multisine
from lrmfrf.simulate import simulate, true_frf
from lrmfrf.uncertainty import (
    eiv_terms,
    neighbour_bias_term,
    neighbour_disagreement,
    robust_noise_variance,
)

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from generalisation_std import HALF_WINDOW, N_SLOW, stage_systems  # noqa: E402

LEVELS = ("own", "true", "pmed", "switch2")


def collect(system, F, snr_db, n_runs, seed):
    """Per run: estimates, per-variant variances (fast grid), and the
    ingredients (levels over the true one, switched windows, nbr bins)."""
    rng = np.random.default_rng(seed)
    N = N_SLOW * F
    u = multisine(N, rms=1.44, rng=rng)
    clean = simulate(system, u, F, snr_db=snr_db, rng=rng)
    sigma = float(clean.noise_std)
    truth = true_frf(system, N)
    n = HALF_WINDOW[F]
    U = dft(u)[None]
    true_level = N_SLOW * sigma**2
    out = {"G": [], "added": [], "switched": []}
    out.update({f"{lv}_level": [] for lv in LEVELS if lv != "true"})
    out.update({lv: [] for lv in LEVELS})
    out.update({f"{lv}+nbr": [] for lv in LEVELS})

    def fast(values):
        return one_sided_fast_grid(values, N, F, conj=False)

    for _ in range(n_runs):
        y = clean.y_l_clean + sigma * rng.standard_normal(N_SLOW)
        est = LRMBeyondNyquist(half_window=n).fit(u, y, F)
        lf, lay = est.local_fit_, est.layout_
        lead, trace = eiv_terms(U, dft(y)[None], lay, lf.theta, lf.slow_bins)
        shape = F**2 * np.real(np.diagonal(lead, axis1=1, axis2=2))
        with np.errstate(invalid="ignore", divide="ignore"):
            own = lf.rss / trace
        levels = {
            "own": own,
            "true": np.full_like(own, true_level),
            "pmed": robust_noise_variance(lf.rss, trace, lf.slow_bins, N_SLOW,
                                          n, lay.dof, switch=np.inf),
            "switch2": robust_noise_variance(lf.rss, trace, lf.slow_bins,
                                             N_SLOW, n, lay.dof),
        }
        v_eiv = shape * own[:, None]
        ok = lf.well_posed[:, None] & np.isfinite(v_eiv)
        add = neighbour_bias_term(neighbour_disagreement(lf), v_eiv, mask=ok)
        for lv, level in levels.items():
            v = shape * level[:, None]
            out[lv].append(fast(v))
            out[f"{lv}+nbr"].append(fast(v + add))
            if lv != "true":
                out[f"{lv}_level"].append(level / true_level)
        out["G"].append(est.frf_)
        out["added"].append(fast((add > 0).astype(float)))
        out["switched"].append(levels["switch2"] == own)
    data = {k: np.array(v) for k, v in out.items()}
    data["truth"] = truth
    return data


def evaluate(data):
    """Ratio and coverage per variant, and the ingredients, of one system."""
    G, truth = data["G"], data["truth"]
    n_runs = G.shape[0]
    mc = np.sqrt(np.sum(np.abs(G - G.mean(0)) ** 2, axis=0) / (n_runs - 1))
    bins = np.all(np.isfinite(G), axis=0) & np.isfinite(truth) & (mc > 0)
    bins[0] = False
    error = np.abs(G[:, bins] - truth[bins])
    out = {"MC": (1.0, float(np.mean(error <= 2 * mc[bins])))}
    per_bin = {}
    for lv in LEVELS:
        for name in (lv, f"{lv}+nbr"):
            var = data[name][:, bins]
            per_bin[name] = np.sqrt(np.nanmean(var, axis=0)) / mc[bins]
            out[name] = (float(np.median(per_bin[name])),
                         float(np.mean(error <= 2 * np.sqrt(var))))
    often = data["added"][:, bins].mean(axis=0) >= 0.5
    robust = per_bin["switch2+nbr"]
    out["info"] = {
        **{f"{lv}/true": float(np.nanmedian(data[f"{lv}_level"]))
           for lv in LEVELS if lv != "true"},
        "switched": float(np.mean(data["switched"])),
        "nbr bins": float(np.mean(data["added"][:, bins])),
        "nbr>=half": float(np.mean(often)),
        "ratio nbr": float(np.median(robust[often])) if often.any() else np.nan,
        "ratio rest": float(np.median(robust[~often])),
        "rest switch2": float(np.median(per_bin["switch2"][~often])),
    }
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1000-1009")
    parser.add_argument("--F", type=int, default=5)
    parser.add_argument("--snr", type=float, nargs="+", default=[70])
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args(argv)
    lo, hi = (int(s) for s in args.seeds.split("-"))
    systems = stage_systems(range(lo, hi + 1), args.F, alternate=True)
    start = time.perf_counter()
    for snr in args.snr:
        results = []
        for i, (name, system) in enumerate(systems):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = evaluate(collect(system, args.F, snr, args.runs,
                                       1000 * i + args.F))
            results.append(res)
            if args.verbose:
                info = " ".join(f"{k}={v:.3f}" for k, v in res["info"].items())
                print(f"{name}: own {res['own'][0]:.3f} true {res['true'][0]:.3f} "
                      f"pmed {res['pmed'][0]:.3f} switch2 {res['switch2'][0]:.3f} "
                      f"robust {res['switch2+nbr'][0]:.3f} | {info}", flush=True)
        print(f"F={args.F} {snr:g} dB ({len(results)} systems, {args.runs} runs, "
              f"{time.perf_counter() - start:.0f} s)")
        names = ["MC"] + [x for lv in LEVELS for x in (lv, f"{lv}+nbr")]
        for name in names:
            ratio = np.array([r[name][0] for r in results])
            cover = np.array([r[name][1] for r in results]) * 100
            print(f"  {name:<13} ratio {np.median(ratio):.3f} "
                  f"[{ratio.min():.3f}, {ratio.max():.3f}]  cover "
                  f"{cover.mean():5.1f} % (min {cover.min():5.1f})")
        for key in results[0]["info"]:
            vals = np.array([r["info"][key] for r in results])
            print(f"  {key:<13} median over systems {np.nanmedian(vals):.3f} "
                  f"[{np.nanmin(vals):.3f}, {np.nanmax(vals):.3f}]")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
