"""Peak resident memory of the estimators on long records (issue 14 item 3).

Every case runs in a FRESH subprocess (``python benchmarks/memory.py --child
...``) and reads the peak resident set size ``VmHWM`` from
``/proc/self/status`` (``resource.getrusage().ru_maxrss`` can carry the size of
the parent across ``exec``). The child imports the package, generates its data
and then fits once; it reports

- ``hwm_before``: ``VmHWM`` before the fit (interpreter, imports, data and the
  peak of generating them),
- ``rss_before``: ``VmRSS`` before the fit,
- ``peak``: ``VmHWM`` after the fit, the figure of the target (<= 1.0 GiB for
  ``LRMBeyondNyquist().fit(u, y, 3)`` at N = 1.2e7),
- ``fitted``: bytes of the array attributes the fitted estimator holds,
- ``fit_s``: wall time of the fit.

Data (lean, float64 ``u`` and ``y`` only): white noise through three lightly
damped modes (90, 235, 440 Hz at 2 kHz, a ``scipy.signal`` sos filter run in
chunks of 2**20 samples), 45 dB output noise, ``y = y_h[::F]``. The MIMO case
is two orthogonal-in-expectation white-noise experiments (P = 2) through a
2x2 system of the same modes with different gains, u (2, 2, N), y (2, 2, M).
Before the children run, a warm-up child fits a short record so that numba's
cache holds the compiled kernel (no compilation inside a measured child).

Cases: ``LRM`` (the closed form, default degrees), ``LPM`` and ``SA`` (for
information) at N = 1.2e6 (and 1.2e7 with ``--huge``), and ``LRM 2x2 P=2`` at
N = 1.2e6, all with F = 3.

Run::

    nice -n 5 python benchmarks/memory.py           # N = 1.2e6, ~1 minute
    nice -n 5 python benchmarks/memory.py --huge    # also N = 1.2e7

Prints a markdown table and writes ``benchmarks/results/memory.csv`` (or
``--out``).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

RESULTS = Path(__file__).resolve().parent / "results"
GIB = 2.0**30
F = 3
SAMPLE_TIME = 0.5e-3
CHUNK = 2**20  # samples filtered at once (bounded generation memory)


# --------------------------------------------------------------------------
# memory figures of this process
# --------------------------------------------------------------------------


def proc_status(field: str) -> float:
    """A ``/proc/self/status`` size (``VmHWM``, ``VmRSS``) in bytes."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return float(line.split()[1]) * 1024  # reported in kB
    raise RuntimeError(f"{field} not in /proc/self/status (Linux only)")


def fitted_bytes(est) -> int:
    """Bytes of the distinct arrays the fitted estimator holds (in ``vars``,
    also inside lists, tuples and dataclasses one level down)."""
    seen, total = set(), 0

    def add(value, depth=0):
        nonlocal total
        if isinstance(value, np.ndarray):
            base = value
            while base.base is not None and isinstance(base.base, np.ndarray):
                base = base.base
            if id(base) not in seen:
                seen.add(id(base))
                total += base.nbytes
        elif depth < 2 and isinstance(value, (list, tuple)):
            for item in value:
                add(item, depth + 1)
        elif depth < 2 and hasattr(value, "__dict__"):
            for item in vars(value).values():
                add(item, depth + 1)

    for value in vars(est).values():
        add(value)
    return total


# --------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------


def _modes_sos(gains=(1.0, 0.5, 0.4)):
    """Three lightly damped modes (90, 235, 440 Hz) in parallel, ZOH, as sos."""
    import warnings

    from scipy.linalg import block_diag
    from scipy.signal import cont2discrete, ss2zpk, zpk2sos

    blocks, inputs, outputs = [], [], []
    for (freq, zeta), gain in zip(
        [(90.0, 0.02), (235.0, 0.008), (440.0, 0.012)], gains, strict=True
    ):
        w = 2 * np.pi * freq
        blocks.append(np.array([[0.0, 1.0], [-w * w, -2 * zeta * w]]))
        inputs.append(np.array([[0.0], [1.0]]))
        outputs.append(np.array([[gain * w * w, 0.0]]))
    system = (
        block_diag(*blocks), np.vstack(inputs), np.hstack(outputs), np.zeros((1, 1))
    )
    a, b, c, d, _ = cont2discrete(system, SAMPLE_TIME, method="zoh")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return zpk2sos(*ss2zpk(a, b, c, d))


def _filtered_slow(u: np.ndarray, sos: np.ndarray) -> np.ndarray:
    """``sosfilt(sos, u)[::F]`` in chunks (no full-size fast output)."""
    from scipy.signal import sosfilt, sosfilt_zi

    zi = sosfilt_zi(sos) * 0.0
    y = np.empty(u.size // F)
    step = CHUNK - CHUNK % F
    for start in range(0, u.size, step):
        stop = min(u.size, start + step)
        part, zi = sosfilt(sos, u[start:stop], zi=zi)
        y[start // F : stop // F] = part[::F]
    return y


def _add_noise(y: np.ndarray, rng) -> None:
    y += 10 ** (-45 / 20) * np.std(y) * rng.standard_normal(y.shape)


def make_siso(n_samples: int, seed: int = 0):
    """u (N,), y (N/F,): white noise through the modes, 45 dB."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n_samples)
    y = _filtered_slow(u, _modes_sos())
    _add_noise(y, rng)
    return u, y


def make_mimo(n_samples: int, seed: int = 1):
    """u (2, 2, N), y (2, 2, N/F): two experiments through a 2x2 system."""
    rng = np.random.default_rng(seed)
    gains = {
        (0, 0): (1.0, 0.5, 0.4), (0, 1): (0.3, -0.6, 0.2),
        (1, 0): (-0.4, 0.7, 0.1), (1, 1): (0.8, 0.2, -0.5),
    }
    sos = {key: _modes_sos(g) for key, g in gains.items()}
    u = rng.standard_normal((2, 2, n_samples))
    y = np.zeros((2, 2, n_samples // F))
    for p in range(2):
        for o in range(2):
            for i in range(2):
                y[p, o] += _filtered_slow(u[p, i], sos[(o, i)])
            _add_noise(y[p, o], rng)
    return u, y


# --------------------------------------------------------------------------
# one case (child process)
# --------------------------------------------------------------------------


def run_case(method: str, n_samples: int) -> dict:
    from lrmfrf import LPMBeyondNyquist, LRMBeyondNyquist, SpectralAnalysis

    mimo = method == "LRM 2x2 P=2"
    u, y = make_mimo(n_samples) if mimo else make_siso(n_samples)
    estimator = {
        "LRM": LRMBeyondNyquist, "LRM 2x2 P=2": LRMBeyondNyquist,
        "LPM": LPMBeyondNyquist, "SA": SpectralAnalysis,
    }[method]()
    out = {
        "method": method, "N": n_samples, "F": F,
        "data_gib": (u.nbytes + y.nbytes) / GIB,
        "hwm_before_gib": proc_status("VmHWM") / GIB,
        "rss_before_gib": proc_status("VmRSS") / GIB,
    }
    t0 = time.perf_counter()
    estimator.fit(u, y, F)
    out["fit_s"] = time.perf_counter() - t0
    out["peak_gib"] = proc_status("VmHWM") / GIB
    out["rss_after_gib"] = proc_status("VmRSS") / GIB
    out["fitted_gib"] = fitted_bytes(estimator) / GIB
    out["n_valid"] = int(np.count_nonzero(estimator.valid_))
    return out


def warm_up() -> None:
    """Compile (or load from cache) the numba kernel on a short record."""
    from lrmfrf import LRMBeyondNyquist
    from lrmfrf.solvers import COMPILED_MIN_WORK

    n_samples = 3 * 2 * (COMPILED_MIN_WORK // 27**2 + 100)
    u, y = make_siso(n_samples)
    LRMBeyondNyquist().fit(u, y, F)
    u, y = make_mimo(3 * 2 * (COMPILED_MIN_WORK // 47**2 + 100))
    LRMBeyondNyquist().fit(u, y, F)


# --------------------------------------------------------------------------
# driver
# --------------------------------------------------------------------------


def _run_child(case: tuple[str, int]) -> dict:
    command = [sys.executable, __file__, "--child", json.dumps(list(case))]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode:
        return {"method": case[0], "N": case[1], "error": done.stderr[-400:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


COLUMNS = [
    ("method", "case", "{}"), ("N", "N", "{:.1e}"),
    ("data_gib", "data GiB", "{:.3f}"),
    ("hwm_before_gib", "VmHWM before fit GiB", "{:.3f}"),
    ("rss_before_gib", "VmRSS before fit GiB", "{:.3f}"),
    ("peak_gib", "peak VmHWM GiB", "{:.3f}"),
    ("fitted_gib", "fitted attrs GiB", "{:.3f}"),
    ("fit_s", "fit s", "{:.2f}"),
]


def print_table(rows: list[dict]) -> None:
    print("| " + " | ".join(title for _, title, _ in COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    for row in rows:
        if "error" in row:
            print(f"| {row['method']} | {row['N']:.1e} | error: "
                  f"{row['error'].splitlines()[-1] if row['error'] else '?'} |")
            continue
        cells = [fmt.format(row[key]) for key, _, fmt in COLUMNS]
        print("| " + " | ".join(cells) + " |")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--huge", action="store_true", help="also N = 1.2e7")
    parser.add_argument("--only", help="run only this case name (e.g. LRM)")
    parser.add_argument("--out", default=str(RESULTS / "memory.csv"))
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--warm-up", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.warm_up:
        warm_up()
        return
    if args.child:
        method, n_samples = json.loads(args.child)
        print(json.dumps(run_case(method, int(n_samples))))
        return
    subprocess.run([sys.executable, __file__, "--warm-up"], check=True)
    cases = [("LRM", 1_200_000), ("LPM", 1_200_000), ("SA", 1_200_000),
             ("LRM 2x2 P=2", 1_200_000)]
    if args.huge:
        cases += [("LRM", 12_000_000), ("LPM", 12_000_000), ("SA", 12_000_000)]
    if args.only:
        cases = [case for case in cases if case[0] == args.only]
    rows = [_run_child(case) for case in cases]
    print_table(rows)
    out = Path(args.out)
    out.parent.mkdir(exist_ok=True)
    keys = ["method", "N", "F"] + [key for key, _, _ in COLUMNS[2:]] + [
        "rss_after_gib", "n_valid", "error"]
    with out.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=keys, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
