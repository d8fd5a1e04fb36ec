"""Write the shipped example data set ``lrmfrf/data/wafer_stage_example.{csv,npz}``.

One period (N = 1200 samples, fast sample time 0.5 ms) of a random-phase
multisine (RMS 1.44 N, all bins) applied to the closed-loop wafer stage
``G_z`` of :func:`lrmfrf.plants.wafer_stage`, the output ``z`` sampled every
``F = 3`` samples (M = 400) with white noise at 45 dB output SNR: the paper's
experimental settings (Table "Experimental settings"). The system starts at
rest, so the record holds a transient.

Files:

- ``wafer_stage_example.csv``: columns ``time_s``, ``u`` (fast input, N) and
  ``y`` (slow output as a fast column: values at rows ``m F``, empty cells
  between them).
- ``wafer_stage_example.npz``: ``u`` (N,), ``y`` (M,), ``sample_time``,
  ``downsampling_factor``, ``snr_db``, ``seed``, and the true FRF ``frf_true``
  on ``frequency_hz`` (fast DFT grid ``k = 0..N//2``) for comparisons.

Usage::

    python scripts/make_example_data.py [--out lrmfrf/data] [--seed 8] [--force]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(REPO))

from lrmfrf.io import atomic_open  # noqa: E402
from lrmfrf.plants import wafer_stage  # noqa: E402
from lrmfrf.signals import multisine  # noqa: E402
from lrmfrf.simulate import frequency_grid, simulate, true_frf  # noqa: E402

N_SAMPLES = 1200
F = 3
SAMPLE_TIME = 0.5e-3
INPUT_RMS = 1.44
SNR_DB = 45.0
STEM = "wafer_stage_example"


def make_example(out_dir: Path, *, seed: int = 8, overwrite: bool = False):
    """Simulate the example and write the CSV and NPZ files.

    Parameters
    ----------
    out_dir : Path
        Folder for the two files (created if needed).
    seed : int, default=8
        Seed of the multisine phases and the noise.
    overwrite : bool, default=False
        Replace existing files.

    Returns
    -------
    list of Path
        The files written.
    """
    rng = np.random.default_rng(seed)
    stage = wafer_stage(sample_time=SAMPLE_TIME, downsampling_factor=F)
    u = multisine(N_SAMPLES, rms=INPUT_RMS, rng=rng)
    result = simulate(stage.G_z, u, F, sample_time=SAMPLE_TIME, snr_db=SNR_DB, rng=rng)
    y_l = np.asarray(result.y_l, dtype=float)
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path = out_dir / f"{STEM}.csv"
    npz_path = out_dir / f"{STEM}.npz"
    lines = ["time_s,u,y"]
    for n in range(N_SAMPLES):
        y_cell = f"{y_l[n // F]:.10g}" if n % F == 0 else ""
        lines.append(f"{n * SAMPLE_TIME:.4f},{u[n]:.10g},{y_cell}")
    with atomic_open(csv_path, overwrite=overwrite) as fh:
        fh.write(("\n".join(lines) + "\n").encode("utf-8"))
    with atomic_open(npz_path, overwrite=overwrite) as fh:
        np.savez(
            fh,
            u=u,
            y=y_l,
            sample_time=np.float64(SAMPLE_TIME),
            downsampling_factor=np.int64(F),
            snr_db=np.float64(SNR_DB),
            seed=np.int64(seed),
            frequency_hz=frequency_grid(N_SAMPLES, SAMPLE_TIME),
            frf_true=true_frf(stage.G_z, N_SAMPLES),
        )
    return [csv_path, npz_path]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "lrmfrf" / "data")
    parser.add_argument("--seed", type=int, default=8)
    parser.add_argument("--force", action="store_true", help="replace existing files")
    args = parser.parse_args(argv)
    for path in make_example(args.out, seed=args.seed, overwrite=args.force):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
