"""frf_joint_cov_ of output rows fitted on weighted experiments, against
Monte Carlo (review31).

2x2 block of ``random_stage(3, mimo=True)``, F = 2, M = 400, one input excited
per experiment (P = 2), experiment 1's noise 5x experiment 0's (std), the
output noise correlated 0.8 between the two rows; default LRMBeyondNyquist,
whose rows are then weighted (``noise_weights_``). Printed per pair of
entries of the two rows: the median over the inner bins of |MC cross
covariance| / |predicted| (mean ``frf_joint_cov_`` over the runs) and the
median |correlation| measured and predicted; then per entry the MC variance
over the predicted one (``frf_cov_``).

Run (about 25 s)::

    python benchmarks/weighted_row_covariance.py --runs 40
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
from lrmfrf.signals import multisine  # noqa: E402
from lrmfrf.simulate import simulate  # noqa: E402

M, F = 400, 2


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=40)
    args = parser.parse_args(argv)
    system = random_stage(3, mimo=True)[0].G[0:2, 0:2]
    rng = np.random.default_rng(8)
    u = np.zeros((2, 2, M * F))
    for p in range(2):
        u[p, p] = multisine(M * F, rng=rng)
    clean = np.stack([simulate(system, u_p, F, noise_std=0.0).y_l for u_p in u])
    sigma = 0.01 * np.std(clean[0], axis=-1)
    rng = np.random.default_rng(0)
    G, J, weighted = [], [], []
    start = time.perf_counter()
    for _ in range(args.runs):
        a, b = rng.standard_normal((2, 2, M))
        v = np.stack([a, 0.8 * a + 0.6 * b], axis=1)  # (P, 2, M), corr 0.8
        v = v * sigma[None, :, None] * np.array([1.0, 5.0])[:, None, None]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est = LRMBeyondNyquist().fit(u, clean + v, F)
        G.append(est.frf_)
        J.append(est.frf_joint_cov_)
        weighted.append(bool(np.any(est.noise_weights_ != 1.0)))
    print(f"{args.runs} runs, {np.mean(weighted):.0%} of the fits weighted, "
          f"{time.perf_counter() - start:.0f} s")
    G, J = np.array(G), np.array(J)
    d = G - G.mean(axis=0)
    mc = np.einsum("roik,rpjk->oipjk", d, d.conj()) / (len(G) - 1)
    pred = J.mean(axis=0)
    k = np.arange(G.shape[-1])
    inner = (k % M != 0) & (k % M != M // 2)
    for i in range(2):
        for j in range(2):
            def corr(c, i=i, j=j):
                return np.abs(c[0, i, 1, j]) / np.sqrt(
                    c[0, i, 0, i].real * c[1, j, 1, j].real)

            ratio = np.abs(mc[0, i, 1, j]) / np.abs(pred[0, i, 1, j])
            print(f"rows 0, 1, entries ({i}, {j}): |MC| / |predicted| "
                  f"{np.median(ratio[inner]):.3f}, |corr| MC "
                  f"{np.median(corr(mc)[inner]):.3f}, predicted "
                  f"{np.median(corr(pred)[inner]):.3f}")
    for o in range(2):
        for i in range(2):
            ratio = mc[o, i, o, i].real / pred[o, i, o, i].real
            print(f"entry ({o}, {i}): MC variance / frf_cov_ "
                  f"{np.median(ratio[inner]):.3f}")


if __name__ == "__main__":
    main()
