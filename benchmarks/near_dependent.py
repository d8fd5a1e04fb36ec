"""Nearly dependent experiments: error, std calibration and the check's flags.

System: ``G[0:3, 0:2]`` of ``lrmfrf.plants.random_stage(3, mimo=True)`` (3
outputs, 2 inputs), F = 3, M = 200, ``P = 2`` experiments: two random-phase
multisines, and the same plus ``eps`` times white noise (unit-rms inputs;
``ind``: two other multisines). Simulated from rest with
``lrmfrf.simulate.simulate`` at ``--snr`` dB per output; the default
``LRMBeyondNyquist()`` (37 equations per experiment for 42 parameters: the
windows need both experiments).

For each input draw (``--runs``) the noise-free outputs are fitted once
(``bias0``: median relative error with no noise, the local models' own
error) and ``--mc`` noise realisations are fitted with the default std
(``eiv``) and with ``std_method="lemma2"``. Columns, medians over the draws:

* ``err``: median over valid bins and noise runs of ``|G_hat - G| / |G|``;
* ``std/err``: median over bins of the RMS predicted std over the RMS error;
* ``spread``: Monte-Carlo std over the noise runs (relative to ``|G|``);
* ``mean-off``: ``|mean G_hat - G| / |G|``, the error the noise leaves in
  the mean (its noise-limited floor is ``spread / sqrt(mc)``);
* ``std/MC``: the predicted std over the Monte-Carlo std;
* ``flag``: fraction of bins the near-dependence check marks invalid
  (``--no-check``: the fits without it, the code before the check).

Run::

    python benchmarks/near_dependent.py --runs 4 --mc 20
    python benchmarks/near_dependent.py --runs 4 --mc 20 --no-check
    python benchmarks/near_dependent.py --runs 3 --mc 10 --snr 40 60 80 --table
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np

import lrmfrf.estimators.local as local_estimators
from lrmfrf import LRMBeyondNyquist
from lrmfrf.plants import random_stage
from lrmfrf.signals import multisine
from lrmfrf.simulate import simulate, true_frf

F, M = 3, 200
N = F * M


def _inputs(eps, rng):
    u1 = np.stack([multisine(N, rng=rng) for _ in range(2)])
    if eps is None:
        u2 = np.stack([multisine(N, rng=rng) for _ in range(2)])
    else:
        u2 = u1 + eps * rng.standard_normal(u1.shape)
    return np.stack([u1, u2])


def _fit(u, y, **params):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return LRMBeyondNyquist(**params).fit(u, y, F)


def run_case(G, truth, snr, eps, runs, mc, table_only):
    stats = {key: [] for key in ("err", "ratio", "ratio_l2", "bias0", "spread",
                                 "off", "mc", "mc_l2", "flag")}
    for run in range(runs):
        rng = np.random.default_rng(100 + run)
        u = _inputs(eps, rng)
        sims = [simulate(G, u[p], F, snr_db=snr, rng=1000 * run + p)
                for p in range(2)]
        clean = np.stack([s.y_l_clean for s in sims])
        sd = np.array([s.noise_std for s in sims])[:, :, None]
        if not table_only:
            fit0 = _fit(u, clean)
            stats["bias0"].append(np.nanmedian(np.abs(fit0.frf_ - truth)
                                               / np.abs(truth)))
        fits, stds, stds_l2, flags = [], [], [], []
        for r in range(mc):
            noise = np.random.default_rng(run * 7919 + r).standard_normal(clean.shape)
            y = clean + sd * noise
            est = _fit(u, y)
            fits.append(est.frf_)
            stds.append(est.frf_std_)
            flags.append(np.mean(~est.valid_))
            if not table_only:
                stds_l2.append(_fit(u, y, std_method="lemma2").frf_std_)
        fits, stds = np.array(fits), np.array(stds)
        stats["flag"].append(np.mean(flags))
        if np.isnan(fits).all():
            continue
        error = np.abs(fits - truth)
        rms_error = np.sqrt(np.mean(error**2, axis=0))
        stats["err"].append(np.nanmedian(error / np.abs(truth)))
        stats["ratio"].append(np.nanmedian(np.sqrt(np.mean(stds**2, 0)) / rms_error))
        if table_only:
            continue
        stds_l2 = np.array(stds_l2)
        spread = np.std(fits, axis=0, ddof=1)
        stats["ratio_l2"].append(np.nanmedian(np.sqrt(np.mean(stds_l2**2, 0))
                                              / rms_error))
        stats["spread"].append(np.nanmedian(spread / np.abs(truth)))
        stats["off"].append(np.nanmedian(np.abs(fits.mean(0) - truth)
                                         / np.abs(truth)))
        stats["mc"].append(np.nanmedian(np.sqrt(np.mean(stds**2, 0)) / spread))
        stats["mc_l2"].append(np.nanmedian(np.sqrt(np.mean(stds_l2**2, 0))
                                           / spread))
    return {key: float(np.median(v)) if v else float("nan")
            for key, v in stats.items()}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=4)
    parser.add_argument("--mc", type=int, default=20)
    parser.add_argument("--snr", type=float, nargs="+", default=[60.0])
    parser.add_argument("--eps", nargs="+",
                        default=["1e-6", "1e-5", "1e-4", "1e-3", "1e-2", "2e-2",
                                 "3e-2", "1e-1", "3e-1", "ind"])
    parser.add_argument("--no-check", action="store_true",
                        help="fit without the near-dependence check")
    parser.add_argument("--table", action="store_true",
                        help="err, std/err and flag only (faster)")
    args = parser.parse_args(argv)
    # (fully invalid fits: their medians are NaN)
    warnings.filterwarnings("ignore", "All-NaN slice", RuntimeWarning)
    if args.no_check:
        local_estimators.nearly_dependent_windows = lambda *a, **k: None
    G = random_stage(3, mimo=True)[0].G[0:3, 0:2]
    truth = true_frf(G, N)
    print(f"near-dependence check: {'off' if args.no_check else 'on'}; runs "
          f"{args.runs}, noise runs {args.mc}")
    for snr in args.snr:
        for text in args.eps:
            eps = None if text == "ind" else float(text)
            try:
                s = run_case(G, truth, snr, eps, args.runs, args.mc, args.table)
            except ValueError as exc:  # exactly dependent: refused
                print(f"snr {snr:3.0f} eps {text:>5}: refused "
                      f"({str(exc)[:60]}...)")
                continue
            line = (f"snr {snr:3.0f} eps {text:>5}: err {s['err']:7.3g} "
                    f"std/err {s['ratio']:5.2f}")
            if not args.table:
                line += (f" (lemma2 {s['ratio_l2']:5.2f}) bias0 {s['bias0']:8.2g} "
                         f"spread {s['spread']:7.3g} mean-off {s['off']:7.3g} "
                         f"std/MC {s['mc']:5.2f} (lemma2 {s['mc_l2']:5.2f})")
            print(line + f" flag {s['flag']:.2f}", flush=True)


if __name__ == "__main__":
    main()
