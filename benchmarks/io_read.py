"""Speed and memory of ``lrmfrf.io.read_measurement`` against ``pandas.read_csv``.

1. Speed: a CSV of ``--rows`` rows (default 5e6) with columns ``u`` (fast
   input) and ``y`` (the slow output as a fast-rate column: a value every
   ``F = 3`` rows, empty cells between) is read by ``pandas.read_csv(path)``
   (defaults: C parser, all columns) and by ``read_measurement(path, F=3)``
   (the same parser plus every check, the file's SHA-256 and the line count
   that sizes the columns). Each is timed ``--repeats`` times, alternating,
   in this process; the best times and their ratio are printed. The target
   of issue 12 is a ratio of at most 2.
2. Memory: a ``--memory-samples`` (default 1e7) sample CSV of the same layout
   and its ``.npz`` twin (``u`` of N values, ``y`` of N/F) are each read in a
   fresh subprocess that reports the resident memory before the read and the
   peak during it (``VmRSS`` and ``VmHWM`` of ``/proc/self/status``, Linux;
   the peak is reset to the current RSS after the imports). The records take
   8 bytes per value.

Run::

    nice -n 10 python benchmarks/io_read.py [--rows 5000000] [--repeats 3]
        [--memory-samples 10000000] [--keep DIR]

Prints two markdown tables and writes ``benchmarks/results/io_read.csv``.
The data files go to a temporary folder removed afterwards (or ``--keep``).
"""

from __future__ import annotations

import argparse
import csv
import gc
import json
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(REPO))

F = 3
RESULTS = REPO / "benchmarks" / "results" / "io_read.csv"

_MEMORY_PROBE = """
import json, sys, time
sys.path.insert(0, {repo!r})
from lrmfrf.io import read_measurement


def status():
    values = {{}}
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(("VmRSS", "VmHWM")):
                key, value = line.split(":")
                values[key] = int(value.split()[0])
    return values


import pandas  # noqa: F401  (imported before the peak is reset)
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


def write_csv(path: pathlib.Path, n_rows: int, seed: int = 1) -> tuple[int, int]:
    """Write ``u`` and a fast-rate ``y`` column (10 significant digits)."""
    rng = np.random.default_rng(seed)
    n = n_rows - n_rows % F
    block = 300_000  # a multiple of F
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("u,y\n")
        for start in range(0, n, block):
            u = rng.standard_normal(min(block, n - start))
            y = rng.standard_normal(u.size // F)
            y_cells = np.full(u.size, "", dtype=object)
            y_cells[::F] = [f"{v:.10g}" for v in y]
            fh.writelines(f"{a:.10g},{b}\n" for a, b in zip(u, y_cells, strict=True))
    return n, n // F


def write_npz(path: pathlib.Path, n_rows: int, seed: int = 1) -> None:
    rng = np.random.default_rng(seed)
    n = n_rows - n_rows % F
    np.savez(path, u=rng.standard_normal(n), y=rng.standard_normal(n // F))


def time_reads(path: pathlib.Path, repeats: int) -> dict[str, float]:
    """Best wall time of pandas.read_csv and of read_measurement, alternating."""
    import pandas as pd

    from lrmfrf.io import read_measurement

    best = {"pandas.read_csv": np.inf, "read_measurement": np.inf}
    for _ in range(repeats):
        for name in best:
            gc.collect()
            start = time.perf_counter()
            if name == "pandas.read_csv":
                result = pd.read_csv(path)
            else:
                result = read_measurement(path, F=F, max_samples=10**9)
            best[name] = min(best[name], time.perf_counter() - start)
            del result
    return best


def measure_memory(path: pathlib.Path, limit: int) -> dict:
    code = _MEMORY_PROBE.format(repo=str(REPO), path=str(path), F=F, limit=limit)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True,
                          text=True, check=True)
    return json.loads(done.stdout)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=5_000_000,
                        help="rows of the speed file (default 5e6)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--memory-samples", type=int, default=10_000_000,
                        help="samples of the memory files (default 1e7; 0 skips)")
    parser.add_argument("--keep", type=pathlib.Path, default=None,
                        help="write the data files here and keep them")
    args = parser.parse_args(argv)
    import pandas as pd

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or pathlib.Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        speed_csv = folder / f"speed_{args.rows}.csv"
        if not speed_csv.exists():
            write_csv(speed_csv, args.rows)
        size_mib = speed_csv.stat().st_size / 2**20
        best = time_reads(speed_csv, args.repeats)
        ratio = best["read_measurement"] / best["pandas.read_csv"]
        print(f"python {platform.python_version()}, numpy {np.__version__}, "
              f"pandas {pd.__version__}\n")
        print(f"| reader ({args.rows:.0e} rows, {size_mib:.0f} MiB CSV, best of "
              f"{args.repeats}) | seconds |\n|---|---|")
        for name, seconds in best.items():
            print(f"| {name} | {seconds:.2f} |")
            rows.append({"case": f"speed {name}", "samples": args.rows,
                         "seconds": seconds, "peak_mib": "", "data_mib": ""})
        print(f"| ratio read_measurement / pandas.read_csv | {ratio:.2f} "
              "(target <= 2) |")
        rows.append({"case": "speed ratio", "samples": args.rows,
                     "seconds": ratio, "peak_mib": "", "data_mib": ""})

        if args.memory_samples:
            files = {"csv": folder / f"memory_{args.memory_samples}.csv",
                     "npz": folder / f"memory_{args.memory_samples}.npz"}
            if not files["csv"].exists():
                write_csv(files["csv"], args.memory_samples)
            if not files["npz"].exists():
                write_npz(files["npz"], args.memory_samples)
            print(f"\n| file ({args.memory_samples:.0e} samples) | read s | RSS "
                  "before MiB | peak MiB | increase MiB | data (u + y) MiB |\n"
                  "|---|---|---|---|---|---|")
            for kind, path in files.items():
                r = measure_memory(path, limit=max(args.memory_samples, 20_000_000))
                data_mib = 8 * (r["n"] + r["m"]) / 2**20
                peak = r["peak_kib"] / 1024
                print(f"| {kind} | {r['seconds']:.2f} | "
                      f"{r['rss_before_kib'] / 1024:.0f} | {peak:.0f} | "
                      f"{(r['peak_kib'] - r['rss_before_kib']) / 1024:.0f} | "
                      f"{data_mib:.0f} |")
                rows.append({"case": f"memory {kind}",
                             "samples": args.memory_samples,
                             "seconds": r["seconds"], "peak_mib": peak,
                             "data_mib": data_mib})
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    with open(RESULTS, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"\nwrote {RESULTS.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
