"""Our LRM with SK10 against SDynPy's LRM at F = 1 (issue 14 item 4).

SDynPy (Sandia, GPL-3) is an optional benchmark dependency only: the package
never imports it. Install it in a separate virtual environment together with
this package, e.g.::

    python -m venv /tmp/venv-sdynpy  # SDynPy's LRM also needs psutil, joblib
    /tmp/venv-sdynpy/bin/pip install sdynpy psutil joblib -e ".[fast]"
    /tmp/venv-sdynpy/bin/pip install "numpy<2" "pandas<2.3"
    QT_QPA_PLATFORM=offscreen /tmp/venv-sdynpy/bin/python \
        benchmarks/sdynpy_comparison.py

(the SDynPy release of 2026-11 fails in its LRM band parsing with numpy 2:
``TypeError: 'numpy.bool' object cannot be interpreted as an integer``).

Data: white-noise input (not periodic: the transient is estimated by both)
through the lightly damped wafer stage ``G_y4`` of :mod:`lrmfrf.plants` at the
fast rate (F = 1), 45 dB output SNR, ``N = 2^14`` and ``2^18`` samples.

Methods, one local model per bin with the same window and degrees:

- ours: ``LRMBeyondNyquist(sk_iterations=10)`` (n = 18, R_g = R_t = 4,
  R_e = 7), compiled kernel;
- SDynPy: ``timedata2frf(u, y, method='LRM', modelset=[[4, 4, 7]],
  transient=True, bandwidth=(2n+1) df, export_ratio=0.5/(2n+1))`` (window of
  2n+1 bins, only the centre exported; it iterates SK itself, up to 50
  iterations), its joblib pool on all cores.

Accuracy: median and 90th percentile over the bins (edges of n bins left out)
of the relative error against the true FRF. Speed: best wall time of
``--repeats`` runs of each (after a warm-up of ours: JIT, caches). Prints a
table and the speed ratio (target: ours >= 5x faster at equal accuracy).
Skips (exit 0, a message) when sdynpy is not importable.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

HALF_WINDOW = 18
DEGREES = {"num_degree": 4, "transient_degree": 4, "den_degree": 7}


def make_data(n_samples: int, seed: int = 0):
    """White-noise input, slow = fast output (F = 1) at 45 dB; true FRF."""
    from lrmfrf.plants import wafer_stage
    from lrmfrf.simulate import simulate, true_frf

    system = wafer_stage().G_y4
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n_samples)
    y = simulate(system, u, 1, snr_db=45, rng=rng).y_l
    return u, y, true_frf(system, n_samples)


def ours(u, y):
    from lrmfrf import LRMBeyondNyquist

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = LRMBeyondNyquist(
            half_window=HALF_WINDOW, sk_iterations=10, **DEGREES
        ).fit(u, y, 1)
    return est.frf_


def theirs(u, y):
    import sdynpy as sdpy

    n = HALF_WINDOW
    df = 1.0 / u.size  # dt = 1
    _, H = sdpy.frf.timedata2frf(
        u, y, dt=1.0, method="LRM",
        modelset=[[DEGREES["num_degree"], DEGREES["transient_degree"],
                   DEGREES["den_degree"]]],
        transient=True, bandwidth=(2 * n + 1) * df, export_ratio=0.5 / (2 * n + 1),
        print_time=False,
    )
    return np.asarray(H)[:, 0, 0]


def errors(frf, G):
    n = HALF_WINDOW
    rel = np.abs(frf[n:-n] - G[n:-n]) / np.abs(G[n:-n])
    return float(np.nanmedian(rel)), float(np.nanpercentile(rel, 90))


def best_time(fn, u, y, repeats):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(u, y)
        times.append(time.perf_counter() - t0)
    return min(times), out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[2**14, 2**18])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    try:
        import sdynpy  # noqa: F401
    except ImportError:
        print("sdynpy is not importable: nothing to compare (see the docstring).")
        return
    u, y, _ = make_data(4096)
    ours(u, y)  # warm-up: JIT or cache load
    print("| N | ours (s) | SDynPy (s) | SDynPy / ours | ours median / p90 err | "
          "SDynPy median / p90 err |\n|---:|---:|---:|---:|---|---|")
    for N in args.sizes:
        u, y, G = make_data(N)
        t_ours, frf_ours = best_time(ours, u, y, args.repeats)
        t_theirs, frf_theirs = best_time(theirs, u, y, args.repeats)
        e_ours, e_theirs = errors(frf_ours, G), errors(frf_theirs, G)
        print(f"| {N} | {t_ours:.3g} | {t_theirs:.3g} | {t_theirs / t_ours:.1f}x | "
              f"{e_ours[0]:.2e} / {e_ours[1]:.2e} | "
              f"{e_theirs[0]:.2e} / {e_theirs[1]:.2e} |", flush=True)
    print(f"\n{os.cpu_count()} CPUs; target: SDynPy / ours >= 5x at equal accuracy.")


if __name__ == "__main__":
    main()
