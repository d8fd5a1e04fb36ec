"""Wall time of grid searches and batches: serial, n_jobs=2, local Dask cluster.

Three workloads on wafer-stage data (G_z, F = 3, 45 dB, N = 6000 by default:
at N = 1200 one fit takes ~50 ms and per-task overhead shows):

- GridSearchCV: ``GridSearchCV(LRMBeyondNyquist(), grid, cv=KFold(4))`` over
  8 experiments; the grid has 24 candidates (half_window in {18, 24, 30, 36} x
  num_degree in {4, 6} x den_degree in {4, 7, 8}), i.e. 96 fits + 1 refit;
- LRMBeyondNyquistCV: the same 24 candidates (R_t = R_g) scored in closed
  form on one record;
- fit_many: a batch of 64 independent records with the Table I setting.

Each is timed serially, with joblib's process backend (n_jobs=2) and on a
``distributed.LocalCluster`` (2 worker processes, 1 thread each) through
``joblib.parallel_config(backend="dask")``, twice: with distributed's default
worker environment, and with ``MALLOC_TRIM_THRESHOLD_`` removed from it (see
``lrmfrf.parallel``: distributed sets it to 65536 for every worker, which
disables glibc's adaptive mmap threshold, so every large temporary array of a
fit is a fresh mmap and page-faults; a fit then costs about 2.3x the CPU).
Workers are warmed up with one small fit first, so the times exclude worker
start-up and imports (reported separately). The machine's core count, and the
other processes running on it (report ``uptime``), bound the speed-up.

Run:  python3 benchmarks/scaleout.py [--n-samples 6000]
Writes benchmarks/results/scaleout.csv.
"""

from __future__ import annotations

import argparse
import csv
import os
import pathlib
import time
import warnings

import joblib
import numpy as np
from sklearn.model_selection import GridSearchCV, KFold

from lrmfrf.estimators import LRMBeyondNyquist
from lrmfrf.estimators.selection import LRMBeyondNyquistCV
from lrmfrf.parallel import fit_many
from lrmfrf.plants import wafer_stage
from lrmfrf.signals import multisine
from lrmfrf.simulate import simulate

F, SNR_DB = 3, 45.0
GRID = {"half_window": [18, 24, 30, 36], "num_degree": [4, 6], "den_degree": [4, 7, 8]}
TABLE_I = {"half_window": 18, "num_degree": 4, "transient_degree": 4, "den_degree": 7}


def data(n_records: int, seed: int, N: int) -> tuple[np.ndarray, np.ndarray]:
    system = wafer_stage().G_z
    rng = np.random.default_rng(seed)
    u = np.array([multisine(N, rms=1.44, rng=rng) for _ in range(n_records)])
    y = np.array([simulate(system, row, F, snr_db=SNR_DB, rng=rng).y_l for row in u])
    return u, y


def workloads(n_jobs, N):
    u8, y8 = data(8, 0, N)
    u64, y64 = data(64, 1, N)
    cv_grid = {"half_windows": GRID["half_window"], "num_degrees": GRID["num_degree"],
               "den_degrees": GRID["den_degree"]}
    return {
        "GridSearchCV, 24 candidates x 4 folds, P=8": lambda: GridSearchCV(
            LRMBeyondNyquist(), GRID, cv=KFold(4), n_jobs=n_jobs
        ).fit(list(u8), list(y8), F=F),
        "LRMBeyondNyquistCV, 24 candidates, 1 record": lambda: LRMBeyondNyquistCV(
            **cv_grid, n_jobs=n_jobs
        ).fit(u8[0], y8[0], F),
        "fit_many, 64 records": lambda: fit_many(
            LRMBeyondNyquist(**TABLE_I), u64, y64, F, n_jobs=n_jobs
        ),
    }


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def small_fit() -> None:
    """One small fit: imports lrmfrf and its dependencies in a worker."""
    import warnings

    from lrmfrf.estimators import LRMBeyondNyquist
    from lrmfrf.signals import multisine

    u = multisine(600, rng=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        LRMBeyondNyquist(half_window=9, num_degree=1, transient_degree=1,
                         den_degree=2).fit(u, u[::F], F)


def on_dask(N, *, default_environ: bool):
    """Start-up time and workload times on a 2-worker LocalCluster."""
    import dask
    from distributed import Client, LocalCluster

    key = "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"
    config = {} if default_environ else {key: None}
    start = time.perf_counter()
    with (
        dask.config.set(config),
        LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                     host="127.0.0.1", dashboard_address=None) as cluster,
        Client(cluster) as client,
        joblib.parallel_config(backend="dask"),
    ):
        client.run(small_fit)  # warm-up on every worker
        startup = time.perf_counter() - start
        times = {name: timed(fn) for name, fn in workloads(-1, N).items()}
    return startup, times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-samples", type=int, default=6000)
    N = parser.parse_args().n_samples
    warnings.simplefilter("ignore")
    small_fit()
    serial = {name: timed(fn) for name, fn in workloads(1, N).items()}

    start = time.perf_counter()
    joblib.Parallel(n_jobs=2)(joblib.delayed(small_fit)() for _ in range(4))
    loky_start = time.perf_counter() - start
    loky = {name: timed(fn) for name, fn in workloads(2, N).items()}

    dask_start, dask = on_dask(N, default_environ=False)
    dask0_start, dask0 = on_dask(N, default_environ=True)

    print(f"N = {N}. Wall time in s on {os.cpu_count()} cores (start-up and warm-up "
          f"excluded: loky {loky_start:.1f} s, Dask LocalCluster {dask_start:.1f} s "
          f"/ {dask0_start:.1f} s)")
    print("dask x2: MALLOC_TRIM_THRESHOLD_ unset; dask x2 default: distributed's "
          "default worker environment. Speed-up = serial / parallel.")
    print(f"{'workload':46s}{'serial':>8s}{'n_jobs=2':>10s}{'dask x2':>9s}"
          f"{'dask x2 default':>17s}{'speed-up (n_jobs / dask / default)':>36s}")
    rows = []
    for name in serial:
        print(f"{name:46s}{serial[name]:8.2f}{loky[name]:10.2f}{dask[name]:9.2f}"
              f"{dask0[name]:17.2f}{serial[name] / loky[name]:16.2f} /"
              f"{serial[name] / dask[name]:5.2f} /{serial[name] / dask0[name]:5.2f}")
        rows.append({"workload": name, "n_samples": N, "serial_s": serial[name],
                     "loky_2_s": loky[name], "dask_2_s": dask[name],
                     "dask_2_default_environ_s": dask0[name]})
    out = pathlib.Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    with open(out / "scaleout.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()
