"""Issue 15 item 6: the generalisation tables on a fixed set of random stages.

Runs, in turn, the three studies of how the package's promises hold on stages
it was never tuned on (``lrmfrf.plants.random_stage``; tuning seeds
1000-1019, held-out seeds 2000-2019, fixed so that every run draws the same
stages):

- ``std``: calibration of ``frf_std_`` against Monte Carlo, per covariance
  route, F = 2, 3, 5 at 25/30/45/70 dB (``generalisation_std.py``);
- ``selection``: ``LRMBeyondNyquistCV``'s pick against the per-record oracle
  of its grid, per criterion (``generalisation_selection.py``);
- ``per_band``: ``LRMBeyondNyquistCV(per_band=True)`` against the best single
  setting of the grid on cluster stages (``generalisation_selection.py
  --per-band``; tuning seeds 1-8, held-out seeds 11-18: these stages are drawn
  by ``cluster_stage``, not ``random_stage``);
- ``diagnose``: false alarms and hits of ``lrmfrf.diagnose`` with one
  experiment at 40 dB, closed and open loop (``generalisation_diagnose.py``).

Each study is also a script of its own with more options (MIMO, refined fits,
...). Run::

    nice -n 5 python benchmarks/generalisation.py              # tuning seeds
    nice -n 5 python benchmarks/generalisation.py --held-out   # held-out seeds
    python benchmarks/generalisation.py --quick                # smoke run, minutes
    python benchmarks/generalisation.py --part std --held-out

The full tables take hours on a 2-core machine (the std study alone runs 100
Monte-Carlo fits per system, SNR and F); ``--quick`` uses 3 stages and few
runs (its figures are not the published ones).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import generalisation_diagnose  # noqa: E402
import generalisation_selection  # noqa: E402
import generalisation_std  # noqa: E402

TUNING = "1000-1019"
HELD_OUT = "2000-2019"
PARTS = ("std", "selection", "per_band", "diagnose")
#: Seeds of the per-band study's cluster stages.
PER_BAND_TUNING = "1-8"
PER_BAND_HELD_OUT = "11-18"


def part_arguments(part: str, seeds: str, quick: bool) -> list[str]:
    """Command-line arguments of one study's ``main``."""
    if part == "std":
        args = ["--seeds", seeds, "--F", "2", "3", "5",
                "--snr", "25", "30", "45", "70", "--runs", "100"]
        if quick:
            args = ["--seeds", seeds, "--F", "3", "--snr", "45", "--runs", "20",
                    "--no-wafer"]
        return args
    if part == "selection":
        return ["--seeds", seeds] + ([] if quick else ["--wafer"])
    if part == "per_band":
        return ["--per-band", "--seeds", seeds]
    args = ["--seeds", seeds]
    if quick:
        args += ["--null-repeats", "1", "--calibration-runs", "5"]
    return args


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", nargs="+", choices=PARTS, default=list(PARTS))
    parser.add_argument("--held-out", action="store_true",
                        help=f"the held-out seeds {HELD_OUT} (default: tuning "
                        f"seeds {TUNING})")
    parser.add_argument("--quick", action="store_true",
                        help="3 stages, few runs: a smoke run")
    args = parser.parse_args(argv)
    seeds = HELD_OUT if args.held_out else TUNING
    if args.quick:
        first = int(seeds.split("-")[0])
        seeds = f"{first}-{first + 2}"
    modules = {"std": generalisation_std, "selection": generalisation_selection,
               "diagnose": generalisation_diagnose}
    modules["per_band"] = generalisation_selection
    for part in args.part:
        start = time.perf_counter()
        part_seeds = seeds
        if part == "per_band":
            part_seeds = PER_BAND_HELD_OUT if args.held_out else PER_BAND_TUNING
            if args.quick:
                first = int(part_seeds.split("-")[0])
                part_seeds = f"{first}-{first + 1}"
        print(f"\n## {part} (seeds {part_seeds})\n", flush=True)
        modules[part].main(part_arguments(part, part_seeds, args.quick))
        print(f"\n({part}: {time.perf_counter() - start:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
