"""Measure two targets that must not be timed tests: simulation speed and the
memory used to read a 1e7-sample file.

1. ``lrmfrf.simulate.simulate`` on 1e6 samples (target: well under 1 s) for
   the closed-loop stage ``G_y4`` and ``G_z`` (diagonal path) and the open-loop
   plant with its double integrator (Schur path); best of ``--repeats``.
2. ``lrmfrf.io.read_measurement`` on a 1e7-sample CSV (fast layout: the slow
   output in every F-th row) and NPZ, each read in a fresh subprocess that
   reports its resident memory before reading and its peak while reading
   (Linux ``/proc/self/status``; the peak is reset after the imports).
   The two ``float64`` records take 8 bytes per value; a reader that streams
   needs about that plus one chunk, one that loads the text needs many times
   more.

Usage::

    nice -n 10 python scripts/measure_simulate_io.py [--samples 10000000]
        [--repeats 3] [--keep DIR]

Prints a markdown table. The data files go to a temporary folder that is
removed afterwards (or to ``--keep DIR``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(REPO))

from lrmfrf.plants import wafer_stage  # noqa: E402
from lrmfrf.simulate import simulate  # noqa: E402

F = 3

_READER = """
import json, sys, time
sys.path.insert(0, {repo!r})
import numpy as np
from lrmfrf.io import read_measurement


def status():
    values = {{}}
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(("VmRSS", "VmHWM")):
                key, value = line.split(":")
                values[key] = int(value.split()[0])
    return values


# Reset the peak (VmHWM) to the current RSS: imports peak higher than they end.
with open("/proc/self/clear_refs", "w") as fh:
    fh.write("5")
before = status()
start = time.perf_counter()
data = read_measurement({path!r}, F={F}, max_samples={limit})
seconds = time.perf_counter() - start
after = status()
print(json.dumps({{"seconds": seconds, "rss_before_kib": before["VmRSS"],
                   "peak_kib": after["VmHWM"], "n": int(data.u_h.size),
                   "m": int(data.y_l.size)}}))
"""


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


def write_files(folder: Path, n_samples: int) -> dict[str, Path]:
    rng = np.random.default_rng(1)
    n = n_samples - n_samples % F
    u = rng.standard_normal(n)
    y = rng.standard_normal(n // F)
    csv_path = folder / "big.csv"
    with open(csv_path, "w", encoding="utf-8") as fh:
        fh.write("u,y\n")
        block = 300_000  # a multiple of F
        for start in range(0, n, block):
            chunk = u[start:start + block]
            y_cells = np.full(chunk.size, "", dtype=object)
            y_cells[::F] = [f"{v:.10g}" for v in y[start // F:(start + block) // F]]
            fh.writelines(f"{a:.10g},{b}\n" for a, b in zip(chunk, y_cells,
                                                           strict=True))
    npz_path = folder / "big.npz"
    np.savez(npz_path, u=u, y=y)
    return {"csv": csv_path, "npz": npz_path}


def measure_read(path: Path, limit: int) -> dict:
    code = _READER.format(repo=str(REPO), path=str(path), F=F, limit=limit)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True,
                          text=True, check=True)
    return json.loads(done.stdout)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=10_000_000,
                        help="samples of the large file (default 1e7)")
    parser.add_argument("--sim-samples", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--keep", type=Path, default=None,
                        help="write the data files here and keep them")
    args = parser.parse_args(argv)

    print("| case | seconds |\n|---|---|")
    for row in time_simulation(args.sim_samples, args.repeats):
        print(f"| {row['case']} | {row['seconds']:.3f} |")

    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        files = write_files(folder, args.samples)
        print(f"\nwrote the {args.samples:.0e}-sample files in "
              f"{time.perf_counter() - start:.1f} s: "
              + ", ".join(f"{p.name} {p.stat().st_size / 2**20:.0f} MiB"
                          for p in files.values()))
        print("\n| file | read s | RSS before read MiB | peak RSS during read MiB "
              "| increase MiB | records (u + y) MiB |\n|---|---|---|---|---|---|")
        for kind, path in files.items():
            r = measure_read(path, limit=max(args.samples, 20_000_000))
            records = 8 * (r["n"] + r["m"]) / 2**20
            print(f"| {kind} | {r['seconds']:.1f} | {r['rss_before_kib'] / 1024:.0f} "
                  f"| {r['peak_kib'] / 1024:.0f} "
                  f"| {(r['peak_kib'] - r['rss_before_kib']) / 1024:.0f} "
                  f"| {records:.0f} |")
        over = measure_refusal(files["csv"], args.samples)
        print(f"\nwith max_samples below the file's length: {over}")
    return 0


def measure_refusal(path: Path, n_samples: int) -> str:
    """The clear failure of a file above the limit, and how early it comes."""
    from lrmfrf.io import DataFileError, read_measurement

    start = time.perf_counter()
    try:
        read_measurement(path, F=F, max_samples=n_samples // 10)
    except DataFileError as exc:
        return f"{exc} (after {time.perf_counter() - start:.1f} s)"
    return "NOT REFUSED"


if __name__ == "__main__":
    raise SystemExit(main())
