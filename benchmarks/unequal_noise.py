"""MIMO experiments with unequal noise levels: ``frf_std_`` against a Monte Carlo.

Systems: ``G[0:2, 0:2]`` of ``lrmfrf.plants.random_stage(seed, mimo=True)``
(closed-loop equivalent), F = 2 and 3, M = 400 slow samples, ``P = 2``
experiments simulated from rest (``lrmfrf.simulate.simulate``, each experiment
its own transient), the default ``LRMBeyondNyquist()``. Two excitations:

* ``orth``: ``lrmfrf.signals.orthogonal_multisines(2, N)``;
* ``one``: one input at a time (experiment ``p`` drives input ``p`` with a
  random-phase multisine, the other input is zero).

Noise: white, per output ``o`` the std ``sigma_o`` (``--snr`` dB below the
noise-free output of experiment 0), times ``ratio`` for experiment 1 (ratio
1 is the equal-noise control), or (``snr``) each experiment simulated with its
own ``snr_db = --snr`` (its noise set from its own output power: unequal
levels when one input is excited at a time).

The input is fixed and only the noise changes between runs. Per entry the
median over bins (DC and Nyquist left out) of the predicted std (RMS of
``frf_std_`` over the runs) over the Monte-Carlo std ``sqrt(sum_r |G_hat_r -
mean G_hat|^2 / (runs - 1))``, and the 2-std coverage (fraction of ``|G_hat -
G| < 2 frf_std_`` over bins and runs). Table: per case the median over the stages'
diagonal entries and over their off-diagonal entries (min-max over the
entries), the mean coverage, and the median over entries and stages of the
Monte-Carlo std over ``|G|`` (the estimate's own accuracy).

Run (about 12 minutes)::

    python benchmarks/unequal_noise.py --runs 20 --out benchmarks/results/x.txt

``--noise-weights off`` fits with the experiments unweighted (the pooled fit
of earlier versions, for comparison).

``--siso``: SISO records with several experiments instead (records of
different days): ``G_y4`` of the closed-loop ``lrmfrf.plants.random_stage(seed,
downsampling_factor=F)``, ``P`` (``--P``, default 2 and 3) experiments, each an
independent random-phase multisine (``lrmfrf.signals.multisine``, same RMS),
white noise of std ``sigma ratio**(p / (P - 1))`` in experiment ``p`` (the
noisiest ``ratio`` times the quietest; ``sigma`` ``--snr`` dB below the
noise-free output of experiment 0). ``snrR`` (e.g. ``snr4``): the inputs' RMS
differ instead (experiment ``p`` scaled by ``R**(p / (P - 1))``) and each
experiment is simulated at its own ``snr_db = --snr``, so its noise std scales
with its input (the same SNR on days of different amplitudes). Table per
case: the median over the stages of the median over bins of predicted std /
Monte-Carlo std (min-max over the stages), the 2-std coverage, the Monte-Carlo
std over ``|G|`` and the fraction of fits weighted (``noise_weights_`` not all
1). About 3 minutes with ``--runs 20``::

    python benchmarks/unequal_noise.py --siso --runs 20 \\
        --out benchmarks/results/x.txt
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lrmfrf import LRMBeyondNyquist  # noqa: E402
from lrmfrf.plants import random_stage  # noqa: E402
from lrmfrf.signals import multisine, orthogonal_multisines  # noqa: E402
from lrmfrf.simulate import simulate, true_frf  # noqa: E402

M = 400


def inputs(kind, N, seed):
    if kind == "orth":
        return orthogonal_multisines(2, N, rng=seed)
    rng = np.random.default_rng(seed)
    u = np.zeros((2, 2, N))
    for p in range(2):
        u[p, p] = multisine(N, rng=rng)
    return u


def study(system, kind, F, ratio, runs, snr_db, seed):
    """Per-entry (ratio, coverage, mc/|G|) and the fit times."""
    N = M * F
    u = inputs(kind, N, seed)
    truth = true_frf(system, N)
    clean = simulate(system, u[0], F, noise_std=0.0).y_l
    sigma = np.std(clean, axis=-1) * 10 ** (-snr_db / 20)
    est = LRMBeyondNyquist()
    fits, stds, valids, seconds = [], [], [], []
    for run in range(runs):
        ys = []
        for p in range(2):
            rng = 1000 * run + p + 17 * seed
            if ratio == "snr":
                ys.append(simulate(system, u[p], F, snr_db=snr_db, rng=rng).y_l)
            else:
                scale = 1.0 if p == 0 else float(ratio)
                ys.append(simulate(system, u[p], F, noise_std=sigma * scale,
                                   rng=rng).y_l)
        y = np.stack(ys)
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est.fit(u, y, F)
        seconds.append(time.perf_counter() - start)
        fits.append(est.frf_)
        stds.append(est.frf_std_)
        valids.append(est.valid_)
    fits, stds = np.array(fits), np.array(stds)
    valid = np.array(valids).all(axis=0) & np.isfinite(truth)
    valid[..., 0] = valid[..., -1] = False  # DC / Nyquist: real-valued bins
    mc = np.sqrt(np.sum(np.abs(fits - fits.mean(axis=0)) ** 2, axis=0)
                 / (runs - 1))
    predicted = np.sqrt(np.mean(stds**2, axis=0))
    inside = np.abs(fits - truth) < 2 * stds
    out = {}
    for o in range(2):
        for i in range(2):
            keep = valid[o, i]
            out[o, i] = (np.median(predicted[o, i, keep] / mc[o, i, keep]),
                         np.mean(inside[:, o, i, keep]),
                         np.median(mc[o, i, keep] / np.abs(truth[o, i, keep])))
    return out, np.median(seconds)


def siso_study(system, F, P, ratio, runs, snr_db, seed):
    """(ratio, coverage, mc/|G|, weighted fraction) of one SISO system and
    the median fit time."""
    N = M * F
    rng = np.random.default_rng(seed)
    u = np.stack([multisine(N, rng=rng) for _ in range(P)])  # (P, N)
    if ratio.startswith("snr"):  # inputs of unequal RMS, each at its own SNR
        u *= float(ratio[3:]) ** (np.arange(P) / (P - 1))[:, None]
    truth = true_frf(system, N)
    clean = np.stack([simulate(system, u_p, F, noise_std=0.0).y_l for u_p in u])
    if ratio.startswith("snr"):
        sigma, scales = 1.0, np.std(clean, axis=-1) * 10 ** (-snr_db / 20)
    else:
        sigma = np.std(clean[0]) * 10 ** (-snr_db / 20)
        scales = float(ratio) ** (np.arange(P) / (P - 1))
    est = LRMBeyondNyquist()
    fits, stds, valids, weighted, seconds = [], [], [], [], []
    noise_rng = np.random.default_rng(1000 + seed)
    for _ in range(runs):
        y = clean + sigma * scales[:, None] * noise_rng.standard_normal(clean.shape)
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est.fit(list(u), list(y), F)
        seconds.append(time.perf_counter() - start)
        fits.append(est.frf_)
        stds.append(est.frf_std_)
        valids.append(est.valid_)
        weighted.append(bool(np.any(est.noise_weights_ != 1.0)))
    fits, stds = np.array(fits), np.array(stds)
    valid = np.array(valids).all(axis=0) & np.isfinite(truth)
    valid[0] = valid[-1] = False  # DC / Nyquist: real-valued bins
    mc = np.sqrt(np.sum(np.abs(fits - fits.mean(axis=0)) ** 2, axis=0)
                 / (runs - 1))
    predicted = np.sqrt(np.mean(stds**2, axis=0))
    inside = np.abs(fits - truth) < 2 * stds
    return ((np.median(predicted[valid] / mc[valid]), np.mean(inside[:, valid]),
             np.median(mc[valid] / np.abs(truth[valid])), np.mean(weighted)),
            np.median(seconds))


def siso_main(args, emit):
    emit(f"random_stage(seed, downsampling_factor=F)[0].G_y4 (closed loop), "
         f"seeds {args.seeds}, {args.runs} runs, {args.snr} dB, M = {M}, "
         "independent random-phase multisines, default LRMBeyondNyquist(); "
         "ratio = noise std of the noisiest / quietest experiment (experiment p: "
         "ratio**(p/(P-1)); 'snrR': input RMS R**(p/(P-1)), each at its own "
         f"SNR); noise weights {args.noise_weights}")
    emit("| P | F | ratio | std/MC median (min-max) | coverage | "
         "MC std / abs(G) | weighted | fit s |")
    emit("|---|---|---|---|---|---|---|---|")
    for P in args.P:
        for F in args.F:
            for ratio in args.ratios or ["1", "2", "4", "10", "snr4", "snr10"]:
                res, secs = [], []
                for seed in args.seeds:
                    system = random_stage(seed, downsampling_factor=F)[0].G_y4
                    r, sec = siso_study(system, F, P, ratio, args.runs, args.snr,
                                        seed)
                    res.append(r)
                    secs.append(sec)
                res = np.array(res)
                emit(f"| {P} | {F} | {ratio} | {np.median(res[:, 0]):.2f} "
                     f"({res[:, 0].min():.2f}-{res[:, 0].max():.2f}) | "
                     f"{100 * np.mean(res[:, 1]):.1f} % | "
                     f"{np.median(res[:, 2]):.3g} | {100 * np.mean(res[:, 3]):.0f} % | "
                     f"{np.median(secs):.3f} |")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--snr", type=float, default=40.0)
    parser.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 5])
    parser.add_argument("--F", type=int, nargs="+", default=[2, 3])
    parser.add_argument("--kinds", nargs="+", default=["orth", "one"])
    parser.add_argument("--ratios", nargs="+", default=None,
                        help="default 1 2 4 10 snr (MIMO), 1 2 4 10 snr4 snr10 "
                             "(--siso)")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--noise-weights", choices=["auto", "off"], default="auto")
    parser.add_argument("--siso", action="store_true",
                        help="SISO records with P experiments (see above)")
    parser.add_argument("--P", type=int, nargs="+", default=[2, 3])
    args = parser.parse_args(argv)
    if args.noise_weights == "off":  # the pooled fit of earlier versions
        import lrmfrf.estimators.local as local

        local.experiment_noise_weights = lambda spectra, layout, **_: None
    lines = []

    def emit(text):
        print(text, flush=True)
        lines.append(text)

    if args.siso:
        siso_main(args, emit)
        if args.out is not None:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text("\n".join(lines) + "\n")
        return
    emit(f"random_stage(seed, mimo=True)[0].G[0:2, 0:2], seeds {args.seeds}, "
         f"{args.runs} runs, {args.snr} dB, M = {M}, P = 2, default "
         "LRMBeyondNyquist(); ratio = noise std of experiment 1 / experiment 0 "
         f"('snr': each experiment its own snr_db); noise weights {args.noise_weights}")
    emit("| kind | F | ratio | std/MC diag median (min-max) | std/MC off-diag "
         "median (min-max) | coverage diag / off | MC std / abs(G) | fit s |")
    emit("|---|---|---|---|---|---|---|---|")
    for kind in args.kinds:
        for F in args.F:
            for ratio in args.ratios or ["1", "2", "4", "10", "snr"]:
                diag, off, cov_d, cov_o, rel, secs = [], [], [], [], [], []
                for seed in args.seeds:
                    system = random_stage(seed, mimo=True)[0].G[0:2, 0:2]
                    res, sec = study(system, kind, F, ratio, args.runs, args.snr,
                                     seed)
                    secs.append(sec)
                    for (o, i), (r, c, m) in res.items():
                        (diag if o == i else off).append(r)
                        (cov_d if o == i else cov_o).append(c)
                        rel.append(m)
                diag, off = np.array(diag), np.array(off)
                emit(f"| {kind} | {F} | {ratio} | {np.median(diag):.2f} "
                     f"({diag.min():.2f}-{diag.max():.2f}) | {np.median(off):.2f} "
                     f"({off.min():.2f}-{off.max():.2f}) | "
                     f"{100 * np.mean(cov_d):.1f} / {100 * np.mean(cov_o):.1f} % | "
                     f"{np.median(rel):.3g} | {np.median(secs):.3f} |")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
