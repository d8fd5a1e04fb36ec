"""MIMO accuracy and std calibration on two channels of the MIMO stage (issue 13).

System: ``lrmfrf.plants.mimo_wafer_stage().G[0:2, 0:2]`` (closed-loop equivalent
system, inputs 0-1 to outputs 0-1), F = 3, two orthogonal random-phase
multisine experiments (``lrmfrf.signals.orthogonal_multisines``) of N samples,
simulated to periodic steady state with ``scipy.signal.dlsim`` (3 periods, the
last kept), white output noise of ``--noise`` times each output's std.

Prints, per entry G[o, i]: the median relative error against the exact FRF
(all bins and above the slow Nyquist frequency) of LRM and LPM (defaults), and
the median over bins of LRM's ``frf_std_`` (RMS over the runs) divided by the
Monte-Carlo RMS error.

Run::

    python benchmarks/mimo_accuracy.py             # 40 runs, N = 3600
    python benchmarks/mimo_accuracy.py --runs 10   # quicker
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np
from scipy.signal import dlsim

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lrmfrf import LPMBeyondNyquist, LRMBeyondNyquist  # noqa: E402
from lrmfrf.plants import mimo_wafer_stage  # noqa: E402
from lrmfrf.signals import orthogonal_multisines  # noqa: E402


def true_frf(system, N):
    A, B, C, D = (np.asarray(m) for m in (system.A, system.B, system.C, system.D))
    z = np.exp(2j * np.pi * np.arange(N // 2 + 1) / N)
    X = np.linalg.solve(z[:, None, None] * np.eye(A.shape[0]) - A,
                        np.broadcast_to(B, (z.size,) + B.shape))
    return np.moveaxis(C @ X + D, 0, -1)


def steady_slow_output(system, u, F, periods=3):
    A, B, C, D = (np.asarray(m) for m in (system.A, system.B, system.C, system.D))
    N = u.shape[1]
    _, y, _ = dlsim((A, B, C, D, system.dt), np.tile(u, periods).T)
    return y[-N:].T[:, ::F]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=40)
    parser.add_argument("--N", type=int, default=3600)
    parser.add_argument("--noise", type=float, default=1e-3)
    args = parser.parse_args(argv)
    stage = mimo_wafer_stage()
    system, F = stage.G[0:2, 0:2], stage.downsampling_factor
    N = args.N
    G = true_frf(system, N)
    above = np.arange(N // 2 + 1) > N // (2 * F)
    rng = np.random.default_rng(0)
    u = orthogonal_multisines(2, N, rng=rng)
    clean = np.stack([steady_slow_output(system, u[p], F) for p in range(2)])
    sigma = args.noise * clean.std(axis=(0, 2), keepdims=True)
    sq = {"LRM": [], "LPM": []}
    var = []
    for _ in range(args.runs):
        y = clean + sigma * rng.standard_normal(clean.shape)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for name, est in (("LRM", LRMBeyondNyquist()), ("LPM", LPMBeyondNyquist())):
                est.fit(u, y, F)
                sq[name].append(np.abs(est.frf_ - G) ** 2)
                if name == "LRM":
                    var.append(est.frf_std_**2)
    print(f"2x2 MIMO stage channels, F={F}, P=2 orthogonal multisines, N={N}, "
          f"noise {args.noise:g} x output std, {args.runs} runs\n")
    print("| entry | LRM median rel. error (all / above Nyquist) | "
          "LPM (all / above) | LRM std / MC RMS error (median over bins) |")
    print("|---|---|---|---:|")
    mc = np.sqrt(np.mean(sq["LRM"], axis=0))
    std = np.sqrt(np.mean(var, axis=0))
    for o in range(2):
        for i in range(2):
            cells = []
            for name in ("LRM", "LPM"):
                rel = np.sqrt(np.mean(sq[name], axis=0))[o, i] / np.abs(G[o, i])
                cells.append(f"{np.nanmedian(rel[1:]):.2e} / "
                             f"{np.nanmedian(rel[above]):.2e}")
            ratio = np.nanmedian(std[o, i, 1:] / mc[o, i, 1:])
            print(f"| G[{o},{i}] | {cells[0]} | {cells[1]} | {ratio:.2f} |")


if __name__ == "__main__":
    main()
