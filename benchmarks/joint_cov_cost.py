"""What ``frf_joint_cov_`` costs against the fit it belongs to.

``frf_joint_cov_`` (the covariance of all entries of a bin, between output
rows too; :func:`lrmfrf.uncertainty.cross_row_covariance`) is computed on
first access, in numpy, from the rows' residuals in the same windows. This
script times it against the default ``LRMBeyondNyquist().fit`` on one 3x2
record set (a fixed stable 3-output, 2-input discrete plant, F = 3, P = 2
orthogonal multisine experiments, 1 % output noise), at M = 400 and M =
40000 slow samples; ``--weighted`` makes experiment 1 five times noisier,
so the rows are fitted with noise weights (``noise_weights_``; every row at
M = 400 and 40000, the count is printed: at M = 200 one row is not
flagged) and the covariance weighs their equations window by window. Per
repeat the fit and then the covariance of that fit are timed (wall clock,
one process, after a warm-up fit that compiles the kernel); the ratio is per
repeat, so a loaded machine shifts both alike. ``--memory`` also reports
the tracemalloc peak of the covariance on a fresh fit (slower: tracing).

Run::

    python benchmarks/joint_cov_cost.py [--weighted] [--repeats 3] [--memory]
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
import warnings
from pathlib import Path

import control
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lrmfrf import LRMBeyondNyquist  # noqa: E402
from lrmfrf.signals import orthogonal_multisines  # noqa: E402
from lrmfrf.simulate import simulate  # noqa: E402

F = 3


def records(M: int, weighted: bool, seed: int = 0):
    """Inputs (2, 2, N) and slow outputs (2, 3, M) of the 3x2 test plant."""
    N = F * M
    u = orthogonal_multisines(2, N, rng=seed)
    plant = control.ss([[0.5, 0.0], [0.0, 0.3]], [[1.0, 0.5], [0.2, 1.0]],
                       [[0.2, 0.0], [0.0, 0.1], [0.1, 0.1]], np.zeros((3, 2)), 1.0)
    rng = np.random.default_rng(seed + 1)
    y = np.stack([simulate(plant, u[p], F).y_l for p in range(2)])
    level = 0.01 * y.std(axis=-1, keepdims=True)
    if weighted:
        level = level * np.array([1.0, 5.0])[:, None, None]
    return u, y + level * rng.standard_normal(y.shape)


def timings(M: int, weighted: bool, repeats: int):
    """Per repeat (fit s, frf_joint_cov_ s), and how many rows are weighted."""
    u, y = records(M, weighted)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        LRMBeyondNyquist().fit(u, y, F)  # compiles the kernel
        out = []
        for _ in range(repeats):
            start = time.perf_counter()
            est = LRMBeyondNyquist().fit(u, y, F)
            fit = time.perf_counter() - start
            start = time.perf_counter()
            est.frf_joint_cov_  # noqa: B018 (computed on first access)
            out.append((fit, time.perf_counter() - start))
        n_weighted = int(np.sum(np.ptp(est.noise_weights_, axis=0) > 0))
        if weighted and not n_weighted:
            raise RuntimeError("the rows were not weighted: raise the noise ratio")
    return out, n_weighted


def peak_mib(M: int, weighted: bool) -> float:
    u, y = records(M, weighted)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = LRMBeyondNyquist().fit(u, y, F)
        tracemalloc.start()
        est.frf_joint_cov_  # noqa: B018
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak / 2**20


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weighted", action="store_true")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sizes", type=int, nargs="+", default=[400, 40000])
    parser.add_argument("--memory", action="store_true")
    args = parser.parse_args(argv)
    print(f"3x2, F = {F}, P = 2, {'weighted' if args.weighted else 'equal'} "
          "noise; per repeat: fit s, frf_joint_cov_ s, ratio")
    for M in args.sizes:
        rows, n_weighted = timings(M, args.weighted, args.repeats)
        text = ", ".join(f"{a:.3f} / {b:.3f} / {b / a:.1f}x" for a, b in rows)
        print(f"M = {M}: {text}"
              + (f" ({n_weighted} of 3 rows weighted)" if args.weighted else ""))
        if args.memory:
            print(f"M = {M}: tracemalloc peak of frf_joint_cov_ "
                  f"{peak_mib(M, args.weighted):.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
