"""Fit time of a long noise-free record against the same record with noise.

Noise-free local dynamics need fewer poles than ``den_degree``: the
denominator block of every window is rank-deficient, the compiled kernel's
pivot check fails and the window goes to the dense numpy route: the solve
(:func:`lrmfrf.solvers._solve_dense`, the QR fallback), which since stop38
also computes the errors-in-variables terms of its well-posed windows from
its own factors; the separate dense route of the terms
(:func:`lrmfrf.uncertainty._terms_of_chunk`) is then only taken by windows
left without them.
This prints, per case (noise-free / 60 dB, ``std_method`` default "eiv" and
"lemma2"), the wall time of each ``LRMBeyondNyquist().fit`` (after one
warm-up fit), and how many windows went dense in the solve and in the eiv
terms, with the time spent in each. The eiv count is of the windows whose
terms are computed in numpy: on the compiled backend (the default N) those
that fail its pivot check, but on the numpy backend (small N, e.g.
``--n-samples 6000``, or ``LRMFRF_DISABLE_NUMBA=1``) every window; the
printed backend says which.

``--std`` only prints the noise-free default fit's ``frf_std_ / |frf_|``
over the bins (its size: round-off). (The ``--ab`` option of 2026-11-28, the
pseudo-inverse's einsum against its matmul, went with that code in stop 38:
the dense route of the terms forms ``A (A^H A)^+`` from the SVD's ``U`` now.)

Run::

    python benchmarks/noise_free_speed.py [--n-samples 120000] [--repeats 3]
        [--std]
"""

from __future__ import annotations

import argparse
import functools
import time

import numpy as np

import lrmfrf.solvers as solvers
import lrmfrf.uncertainty as uncertainty
from lrmfrf import LRMBeyondNyquist
from lrmfrf.paper import paper_experiment
from lrmfrf.plants import wafer_stage

COUNTS: dict = {}


def _counted(module, name, n_windows):
    function = getattr(module, name)

    @functools.wraps(function)
    def counted(*args, **kwargs):
        start = time.perf_counter()
        result = function(*args, **kwargs)
        entry = COUNTS.setdefault(name, [0, 0.0])
        entry[0] += n_windows(args)
        entry[1] += time.perf_counter() - start
        return result

    setattr(module, name, counted)


# the solve's dense windows (A of shape (B, L, p)) and the eiv terms' (the
# slow bins of the chunk)
_counted(solvers, "_solve_dense", lambda args: args[0].shape[0])
_counted(uncertainty, "_terms_of_chunk", lambda args: len(args[4]))

def timed_fit(u, y, method):
    """Wall time of one fit, the counts of :data:`COUNTS`, and the backend
    its eiv terms take (``"auto"`` as the fit resolves it: the slow
    windows and the layout's size)."""
    COUNTS.clear()
    start = time.perf_counter()
    est = LRMBeyondNyquist(std_method=method).fit(u, y, 3)
    elapsed = time.perf_counter() - start
    backend = solvers.resolve_backend("auto", y.shape[-1] // 2 + 1,
                                      est.layout_.n_params, eiv=True)
    return elapsed, {k: list(v) for k, v in COUNTS.items()}, backend


def print_relative_std(plant, n_samples: int) -> None:
    """``frf_std_ / |frf_|`` of the default (eiv) fit of the noise-free
    record: the size of the std on noise-free data."""
    e = paper_experiment(plant, rng=0, n_samples=n_samples, snr_db=None)
    est = LRMBeyondNyquist().fit(e.u_h, e.y_l, 3)
    G, std = np.ravel(est.frf_), np.ravel(est.frf_std_)
    r = std / np.abs(G)
    top = int(np.argmax(r))
    print(f"N = {n_samples}, wafer_stage().G_y4, F = 3, rng = 0, noise-free, "
          f"default fit: frf_std_ / |frf_| over {r.size} bins: median "
          f"{np.median(r):.1e}, 95 % {np.percentile(r, 95):.1e}, 99 % "
          f"{np.percentile(r, 99):.1e}, largest {r[top]:.1e} at bin {top} "
          f"(|frf_| {abs(G[top]):.1e}, frf_std_ {std[top]:.1e}); the next "
          f"largest {np.sort(r)[-2]:.1e}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-samples", type=int, default=120_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--std", action="store_true",
                        help="only frf_std_ / |frf_| of the noise-free fit")
    args = parser.parse_args()
    plant = wafer_stage().G_y4
    if args.std:
        print_relative_std(plant, args.n_samples)
        return
    print(f"N = {args.n_samples}, wafer_stage().G_y4, F = 3, rng = 0, "
          f"repeats {args.repeats} (after one warm-up fit)", flush=True)
    for snr in (None, 60.0):
        e = paper_experiment(plant, rng=0, n_samples=args.n_samples, snr_db=snr)
        for method in ("eiv", "lemma2"):
            timed_fit(e.u_h, e.y_l, method)  # warm-up (numba, caches)
            runs = [timed_fit(e.u_h, e.y_l, method) for _ in range(args.repeats)]
            times = [t for t, _, _ in runs]
            counts, backend = runs[-1][1], runs[-1][2]
            solve = counts.get("_solve_dense", [0, 0.0])
            terms = counts.get("_terms_of_chunk", [0, 0.0])
            label = "noise-free" if snr is None else f"{snr:g} dB"
            where = "dense" if backend == "numba" else "numpy backend: all"
            print(f"{label:10s} {method:6s}: median {np.median(times):7.3f} s "
                  f"(all {np.round(times, 3)}); dense windows: solve "
                  f"{solve[0]} ({solve[1]:.2f} s), eiv terms ({where}) "
                  f"{terms[0]} ({terms[1]:.2f} s)", flush=True)


if __name__ == "__main__":
    main()
