"""Measure a target that must not be a timed test: simulation speed.

``lrmfrf.simulate.simulate`` on 1e6 samples (target: well under 1 s) for the
closed-loop stage ``G_y4`` and ``G_z`` (diagonal path) and the open-loop plant
with its double integrator (Schur path); best of ``--repeats``.

The speed and memory of reading files, measured here before, are measured by
``benchmarks/io_read.py`` (against ``pandas.read_csv``, and the peak memory of
a 1e7-sample read in a fresh subprocess).

Usage::

    nice -n 10 python scripts/measure_simulate_io.py [--sim-samples 1000000]
        [--repeats 3]

Prints a markdown table.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(REPO))

from lrmfrf.plants import wafer_stage  # noqa: E402
from lrmfrf.simulate import simulate  # noqa: E402

F = 3


def time_simulation(n_samples: int, repeats: int) -> list[dict]:
    stage = wafer_stage()
    rng = np.random.default_rng(0)
    u = rng.standard_normal(n_samples - n_samples % F)
    rows = []
    for name, system in (("G_y4", stage.G_y4), ("G_z", stage.G_z),
                         ("plant z (open loop)", stage.plant[1, 0])):
        best = np.inf
        for _ in range(repeats):
            start = time.perf_counter()
            simulate(system, u, F, snr_db=45.0, rng=1)
            best = min(best, time.perf_counter() - start)
        rows.append({"case": f"simulate {name}, {u.size:.0e} samples, "
                     f"{system.nstates} states", "seconds": best})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sim-samples", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)

    print("| case | seconds |\n|---|---|")
    for row in time_simulation(args.sim_samples, args.repeats):
        print(f"| {row['case']} | {row['seconds']:.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
