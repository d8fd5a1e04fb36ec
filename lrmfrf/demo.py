"""``lrmfrf demo``: the paper's comparison on the OAT-like stage, in seconds.

Simulates one experiment with the paper's settings (Table I) on both
equivalent systems ``G_y4`` and ``G_z``, fits LRM, LPM and SA, and writes into
the output folder a Bode plot per system (with a +/-2 std band and the slow
Nyquist frequency) and a CSV of the FRFs. It never overwrites a file it did not
write: the files it writes are listed with their SHA-256 in
``lrmfrf-demo-manifest.json``, and a later run replaces only files that are
listed there and unchanged (or any file with ``overwrite=True``).
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io import atomic_open, file_sha256
from .paper import (
    TABLE_I,
    compare_methods,
    on_grid,
    paper_experiment,
    table1_estimators,
)
from .plants import wafer_stage

__all__ = ["DemoResult", "run_demo", "format_table"]

MANIFEST = "lrmfrf-demo-manifest.json"
SYSTEMS = ("G_y4", "G_z")


@dataclass
class DemoResult:
    """What :func:`run_demo` produced.

    Attributes
    ----------
    table : str
        Markdown table of the errors.
    results : dict
        ``results[system][method]``: the error summary of
        :func:`lrmfrf.paper.compare_methods`.
    files : list of Path
        Files written.
    """

    table: str
    results: dict
    files: list = field(default_factory=list)


def format_table(results: dict) -> str:
    """Markdown table of median relative errors and cumulative errors."""
    lines = [
        "| system | method | median rel. error < Nyquist | > Nyquist "
        "| near resonances | cumulative error (SA grid) | vs LRM |",
        "|---|---|---|---|---|---|---|",
    ]
    for system, per_method in results.items():
        reference = per_method["LRM"]["cumulative_error_common"]
        for method, s in per_method.items():
            cumulative = s["cumulative_error_common"]
            lines.append(
                f"| {system} | {method} | {s['median_relative_below']:.3g} "
                f"| {s['median_relative_above']:.3g} "
                f"| {s['median_relative_resonance']:.3g} | {cumulative:.3g} "
                f"| {cumulative / reference:.2f}x |"
            )
    return "\n".join(lines)


def run_demo(
    out_dir="lrmfrf-demo",
    *,
    seed: int = 0,
    snr_db: float = TABLE_I["snr_db"],
    overwrite: bool = False,
    plot: bool = True,
) -> DemoResult:
    """Run the paper's comparison once and write the figures and FRFs.

    Parameters
    ----------
    out_dir : str or Path, default="lrmfrf-demo"
        Created if missing.
    seed : int, default=0
        Seed of the multisine phases and the noise.
    snr_db : float, default=45
        Output signal-to-noise ratio in dB.
    overwrite : bool, default=False
        Replace existing files even if this demo did not write them.
    plot : bool, default=True
        Write the Bode PNGs (needs matplotlib).

    Returns
    -------
    DemoResult
    """
    if not np.isfinite(snr_db):
        raise ValueError(f"snr_db must be a finite number of dB. Got {snr_db!r}.")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} exists and is not a folder. Choose another --out.")
    out.mkdir(parents=True, exist_ok=True)
    manifest = _read_manifest(out)
    stage = wafer_stage()
    rng = np.random.default_rng(seed)
    results, files = {}, []
    for name in SYSTEMS:
        system = getattr(stage, name)
        experiment = paper_experiment(system, rng=rng, snr_db=snr_db)
        estimators = table1_estimators()
        results[name] = compare_methods(
            experiment, estimators, resonances=stage.resonance_frequencies_hz
        )
        csv_path = out / f"frf_{name}.csv"
        _write(csv_path, _frf_csv(experiment, estimators), manifest, overwrite)
        files.append(csv_path)
        if plot:
            png_path = out / f"bode_{name}.png"
            _write(png_path, _bode_png(system, estimators, name), manifest, overwrite)
            files.append(png_path)
    _write_manifest(out, manifest, files)
    return DemoResult(table=format_table(results), results=results, files=files)


def _frf_csv(experiment, estimators) -> bytes:
    """FRFs on the fast grid: true, LRM and LPM (with std), SA at its bins."""
    f = experiment.frequencies
    columns = {"frequency_hz": f, "true_real": experiment.frf_true.real,
               "true_imag": experiment.frf_true.imag}
    for name, est in estimators.items():
        if est.frequencies_.size == f.size:
            values, std = est.frf_, est.frf_std_
        else:  # SA: its coarse bins, NaN between them
            values = np.full(f.size, np.nan, dtype=complex)
            std = np.full(f.size, np.nan)
            index = np.searchsorted(f, est.frequencies_)
            values[index] = on_grid(est.frequencies_, est.frf_, f[index])
            std[index] = est.frf_std_
        columns[f"{name.lower()}_real"] = values.real
        columns[f"{name.lower()}_imag"] = values.imag
        columns[f"{name.lower()}_std"] = std
    buffer = io.StringIO()
    buffer.write(",".join(columns) + "\n")
    np.savetxt(buffer, np.column_stack(list(columns.values())), delimiter=",",
               fmt="%.10g")
    return buffer.getvalue().encode()


def _bode_png(system, estimators, name: str) -> bytes:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from .plotting import plot_frf

    fig, _ = plot_frf(
        *estimators.values(), true=system, labels=list(estimators), std_band=2,
        title=f"{name}: LRM, LPM and SA beyond the slow Nyquist frequency",
    )
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return buffer.getvalue()


def _read_manifest(out: Path) -> dict:
    path = out / MANIFEST
    if not path.exists():
        return {}
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def _write(path: Path, data: bytes, manifest: dict, overwrite: bool) -> None:
    ours = path.exists() and manifest.get(path.name) == file_sha256(path)
    with atomic_open(path, overwrite=overwrite or ours) as fh:
        fh.write(data)


def _write_manifest(out: Path, manifest: dict, files: list) -> None:
    manifest = dict(manifest)
    manifest.update({path.name: file_sha256(path) for path in files})
    path = out / MANIFEST
    ours = path.exists()  # the manifest is always the demo's own file
    with atomic_open(path, overwrite=ours) as fh:
        fh.write(json.dumps(manifest, indent=1, sort_keys=True).encode())
