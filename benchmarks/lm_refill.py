"""CPU time of the compiled LM with lane refill against lane-group packing.

The compiled guarded LM (``lrmfrf._compiled_refine``) either refills a lane
with the next window as soon as its window stops (``_LM_REFILL = True``, the
default) or packs the windows still active after the iterations in
``_LM_STAGES`` into new lane groups. Both give the same results (checked
here, bit for bit but the per-iteration cost sums). This times
``refine_local_models(..., lm_iterations=50)`` from the same closed form
both ways, interleaved, best of ``--repeats`` each, in one process, and
prints the ratio of the CPU times (refill over packing; all threads) and of
the wall times. Data: the wafer stage of ``benchmarks/speed.py``, F = 3.

Run:  NUMBA_NUM_THREADS=1 python benchmarks/lm_refill.py            # N = 1.2e6
      python benchmarks/lm_refill.py --samples 120000 --repeats 2   # quick
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import numpy as np
from speed import make_data

from lrmfrf import _compiled_refine
from lrmfrf.local_models import dft, fit_local_models
from lrmfrf.refinement import refine_local_models
from lrmfrf.windows import LocalModelLayout


def compare(n_samples: int, repeats: int = 3, lm_iterations: int = 50) -> dict:
    """Best-of CPU and wall seconds of LM with refill and with packing."""
    F = 3
    u, y, _ = make_data(n_samples, F)
    U, Y = dft(u)[None], dft(y)[None]
    layout = LocalModelLayout(F=F, half_window=18, num_degree=4,
                              transient_degree=4, den_degree=7)
    closed = fit_local_models(U, Y, layout)

    def run(refill: bool):
        _compiled_refine._LM_REFILL = refill
        t0, c0 = time.perf_counter(), time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = refine_local_models(U, Y, layout, closed, backend="numba",
                                      lm_iterations=lm_iterations)
        return out, time.perf_counter() - t0, time.process_time() - c0

    default = _compiled_refine._LM_REFILL
    try:
        results = {True: run(True)[0], False: run(False)[0]}  # warm-up, check
        best = {on: [np.inf, np.inf] for on in (True, False)}
        for _ in range(repeats):
            for on in (True, False):
                _, wall, cpu = run(on)
                best[on] = [min(best[on][0], wall), min(best[on][1], cpu)]
    finally:
        _compiled_refine._LM_REFILL = default
    a, b = results[True].local_fit, results[False].local_fit
    same = all(np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True)
               for name in ("theta", "system", "rss", "system_var"))
    return {"N": n_samples, "windows": closed.slow_bins.size, "same": same,
            "refill_s": best[True][0], "packing_s": best[False][0],
            "refill_cpu_s": best[True][1], "packing_cpu_s": best[False][1]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1_200_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    r = compare(args.samples, args.repeats)
    print(f"LM50 at N = {r['N']} ({r['windows']} windows), best of "
          f"{args.repeats}; results identical: {r['same']}")
    print(f"refill   wall {r['refill_s']:7.2f} s  CPU {r['refill_cpu_s']:7.2f} s")
    print(f"packing  wall {r['packing_s']:7.2f} s  CPU {r['packing_cpu_s']:7.2f} s")
    print(f"refill / packing: wall {r['refill_s'] / r['packing_s']:.3f}x, "
          f"CPU {r['refill_cpu_s'] / r['packing_cpu_s']:.3f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
