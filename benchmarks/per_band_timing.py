"""Per-band fit time by the candidates' std route (issue 15 item 4).

Wall time of ``LRMBeyondNyquistCV(per_band=True).fit`` with the candidates'
``std_method`` ``"eiv"`` (the default) and ``"eiv_robust"``, alternated,
after one warm-up fit of each, on the first SISO (``G_y4``) and 2x2 cluster
records of ``generalisation_selection.py --per-band`` (seed 1): the median
of the repeats and their ratio.

Run:  python benchmarks/per_band_timing.py
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import generalisation_selection as gs  # noqa: E402

from lrmfrf import LRMBeyondNyquistCV  # noqa: E402


def records():
    """``(label, u, y, repeats)`` of the SISO and the 2x2 record of seed 1."""
    _, _, _, u_mimo, y_mimo = gs.cluster_mimo_record(1)
    stage, _ = gs.cluster_stage(1, "closed")
    rng = np.random.default_rng(10_000 + 1)  # as gs.per_band_record
    u = gs.multisine(3 * gs.SLOW_SAMPLES, rng=rng)
    y = gs.simulate(stage.G_y4, u, 3, snr_db=40.0, rng=rng).y_l
    return [("SISO seed 1 G_y4", u, y, 5), ("2x2 seed 1", u_mimo, y_mimo, 3)]


def main() -> None:
    for label, u, y, repeats in records():
        times = {"eiv": [], "eiv_robust": []}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for method in times:  # warm-up (numba, caches)
                LRMBeyondNyquistCV(per_band=True, std_method=method).fit(u, y, 3)
            for _ in range(repeats):
                for method in times:
                    start = time.perf_counter()
                    LRMBeyondNyquistCV(per_band=True,
                                       std_method=method).fit(u, y, 3)
                    times[method].append(time.perf_counter() - start)
        a, b = np.median(times["eiv"]), np.median(times["eiv_robust"])
        print(f"{label}: eiv {a:.2f} s, eiv_robust {b:.2f} s (medians of "
              f"{repeats}), ratio {b / a:.2f}; all: "
              f"{np.round(times['eiv'], 2)} / {np.round(times['eiv_robust'], 2)}",
              flush=True)


if __name__ == "__main__":
    main()
