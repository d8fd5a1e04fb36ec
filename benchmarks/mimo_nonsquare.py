"""Non-square MIMO: accuracy and ``frf_std_`` calibration against a Monte Carlo.

Systems: sub-blocks ``G[0:n_y, 0:n_u]`` of the closed-loop equivalent system of
``lrmfrf.plants.random_stage(seed, mimo=True)`` (5 outputs, 4 inputs), shapes
``n_y x n_u`` in 1x2, 2x1, 3x2, 2x3 (and 3x3), F = 2 and 3, N = 400 F (M = 400
slow samples), simulated from rest with ``lrmfrf.simulate.simulate`` (so each
experiment has its own transient), ``snr_db`` per output. Two excitations:

* ``P = n_u``: ``lrmfrf.signals.orthogonal_multisines(n_u, N)``, the default
  ``LRMBeyondNyquist()`` (half window 18);
* ``P = 1``: ``n_u`` independent random-phase multisines in one record, with
  the half window widened until 20 residual degrees of freedom remain.

The input is fixed and only the noise changes between runs. Per entry ``(o,
i)`` the table gives the median over valid bins of the relative error
``|G_hat - G| / |G|`` (median over runs), and the median over bins of the
predicted std (RMS of ``frf_std_`` over the runs) divided by the Monte-Carlo
std ``sqrt(mean_r |G_hat_r - mean G_hat|^2)``; ``min``/``max`` of that ratio
over the entries; the largest (over entries) median over bins of ``|mean G_hat -
G| / MC std`` (noise-limited: about 0.9/sqrt(runs), 0.16 at 30 runs).

Run::

    python benchmarks/mimo_nonsquare.py --runs 30
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

SHAPES = [(1, 2), (2, 1), (3, 2), (2, 3), (3, 3)]  # (n_y, n_u)
DEFAULT = dict(num_degree=4, transient_degree=4, den_degree=7)


def one_experiment_half_window(n_u, F, dof=20):
    n_params = (DEFAULT["num_degree"] + 1) * F * n_u + DEFAULT["transient_degree"] \
        + 1 + DEFAULT["den_degree"]
    return max(18, int(np.ceil((n_params + dof - 1) / 2)))


def study(system, n_u, F, P, runs, snr_db, seed):
    M = 400
    N = M * F
    if P == n_u:
        u = orthogonal_multisines(n_u, N, rng=seed)
        est = LRMBeyondNyquist()
    else:
        rng = np.random.default_rng(seed)
        u = np.stack([multisine(N, rng=rng) for _ in range(n_u)])[None]
        est = LRMBeyondNyquist(half_window=one_experiment_half_window(n_u, F))
    truth = true_frf(system, N)
    if truth.ndim == 1:
        truth = truth[None, None]
    fits, stds, valids = [], [], []
    for run in range(runs):
        y = np.stack([simulate(system, u[p], F, snr_db=snr_db,
                               rng=1000 * run + p).y_l for p in range(P)])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est.fit(u, y, F)
        fits.append(np.asarray(est.frf_).reshape(truth.shape))
        stds.append(np.asarray(est.frf_std_).reshape(truth.shape))
        valids.append(np.asarray(est.valid_).reshape(truth.shape))
    fits, stds = np.array(fits), np.array(stds)
    valid = np.array(valids).all(axis=0) & np.isfinite(truth)
    mc = np.sqrt(np.mean(np.abs(fits - fits.mean(axis=0)) ** 2, axis=0))
    predicted = np.sqrt(np.mean(stds**2, axis=0))
    error = np.median(np.abs(fits - truth) / np.abs(truth), axis=0)
    bias = np.abs(fits.mean(axis=0) - truth) / mc
    rows = []
    for o in range(truth.shape[0]):
        for i in range(truth.shape[1]):
            keep = valid[o, i]
            keep[0] = keep[-1] = False  # DC / Nyquist: real-valued bins
            rows.append((o, i, np.median(error[o, i, keep]),
                         np.median(predicted[o, i, keep] / mc[o, i, keep]),
                         np.median(bias[o, i, keep])))
    return rows, est.half_window


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--snr", type=float, default=40.0)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--shapes", default=",".join(f"{a}x{b}" for a, b in SHAPES))
    args = parser.parse_args(argv)
    stage, draw = random_stage(args.seed, mimo=True)
    shapes = [tuple(int(v) for v in s.split("x")) for s in args.shapes.split(",")]
    print(f"random_stage({args.seed}, mimo=True), {args.runs} runs, "
          f"{args.snr} dB per output, N = 400 F; ratio = predicted std / MC std")
    print("| n_y x n_u | F | P | n | median rel. error (per entry) | "
          "std ratio median over entries (min-max) | bias / MC std, max |")
    print("|---|---|---|---|---|---|---|")
    for n_y, n_u in shapes:
        system = stage.G[0:n_y, 0:n_u]
        for F in (2, 3):
            for P in sorted({n_u, 1}, reverse=True):
                start = time.perf_counter()
                rows, n = study(system, n_u, F, P, args.runs, args.snr, args.seed)
                errors = " ".join(f"{r[2]:.3g}" for r in rows)
                ratios = np.array([r[3] for r in rows])
                bias = np.array([r[4] for r in rows])
                print(f"| {n_y}x{n_u} | {F} | {P} | {n} | {errors} | "
                      f"{np.median(ratios):.3f} ({ratios.min():.3f}-"
                      f"{ratios.max():.3f}) | {bias.max():.2f} |  [{time.perf_counter() - start:.0f} s]",
                      flush=True)


if __name__ == "__main__":
    main()
