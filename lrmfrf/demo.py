"""``lrmfrf demo``: the paper's comparison on the OAT-like stage, in seconds.

Simulates one experiment with the paper's settings (Table I) on both
equivalent systems ``G_y4`` and ``G_z``, fits LRM, LPM and SA, and writes into
the output folder a Bode plot per system (with a +/-2 std band and the slow
Nyquist frequency) and a CSV of the FRFs. It never overwrites a file it did not
write: the files it writes are listed with their SHA-256 in
``lrmfrf-demo-manifest.json``, and a later run replaces only files that are
listed there and unchanged (or any file with ``overwrite=True``). Every target
is checked before any work is done, so a refused run writes nothing. Without
matplotlib the CSVs are written and the PNGs skipped, with a note.
"""

from __future__ import annotations

import io
import json
import logging
import numbers
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

logger = logging.getLogger(__name__)

MANIFEST = "lrmfrf-demo-manifest.json"
SYSTEMS = ("G_y4", "G_z")
_WRITER = "lrmfrf demo"
_PLOT_HINT = (
    'Bode PNGs not drawn: matplotlib is missing (pip install "lrmfrf[plot]")'
)


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
    notes : list of str
        What was skipped and why (e.g. the PNGs without matplotlib).
    """

    table: str
    results: dict
    files: list = field(default_factory=list)
    notes: list = field(default_factory=list)


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
        Seed (>= 0) of the multisine phases and the noise.
    snr_db : float, default=45
        Output signal-to-noise ratio in dB.
    overwrite : bool, default=False
        Replace existing files even if this demo did not write them.
    plot : bool, default=True
        Write the Bode PNGs (skipped, with a note in ``notes``, when
        matplotlib is not installed).

    Returns
    -------
    DemoResult

    Raises
    ------
    ValueError
        For a bad ``seed`` or ``snr_db``, or an ``out_dir`` that is a file.
    FileExistsError
        If a target file exists that this demo did not write (or changed
        since) and ``overwrite`` is False; nothing is written then.
    """
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0. Got {seed!r}.")
    if not (isinstance(snr_db, numbers.Real) and np.isfinite(snr_db)):
        raise ValueError(f"snr_db must be a finite number of dB. Got {snr_db!r}.")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} exists and is not a folder. Choose another --out.")
    notes = []
    if plot and not _have_matplotlib():
        plot = False
        notes.append(_PLOT_HINT)
        logger.warning(_PLOT_HINT)
    targets = {
        name: (out / f"frf_{name}.csv", out / f"bode_{name}.png" if plot else None)
        for name in SYSTEMS
    }
    manifest = _read_manifest(out, overwrite)
    for csv_path, png_path in targets.values():
        for path in (csv_path, png_path):
            if path is not None:
                _check_target(path, manifest, overwrite)
    out.mkdir(parents=True, exist_ok=True)
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
        csv_path, png_path = targets[name]
        _write(csv_path, _frf_csv(experiment, estimators), manifest, overwrite)
        files.append(csv_path)
        manifest[csv_path.name] = file_sha256(csv_path)
        if png_path is not None:
            _write(png_path, _bode_png(system, estimators, name), manifest, overwrite)
            files.append(png_path)
            manifest[png_path.name] = file_sha256(png_path)
        _write_manifest(out, manifest)
    return DemoResult(table=format_table(results), results=results, files=files,
                      notes=notes)


def _have_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


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
        units="m/N",
    )
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return buffer.getvalue()


def _read_manifest(out: Path, overwrite: bool) -> dict:
    """Files this demo wrote in ``out``, ``{name: sha256}``.

    A manifest file that this demo did not write (not a JSON object with
    ``"written_by": "lrmfrf demo"``) is a user's file: refused unless
    ``overwrite``.
    """
    path = out / MANIFEST
    if not path.exists():
        return {}
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        content = None
    if (
        isinstance(content, dict)
        and content.get("written_by") == _WRITER
        and isinstance(content.get("files"), dict)
    ):
        return {str(k): str(v) for k, v in content["files"].items()}
    if _is_legacy_manifest(content):  # lrmfrf 0.1 wrote {name: sha256} only
        return dict(content)
    if overwrite:
        return {}
    raise FileExistsError(
        f"{path}: exists and was not written by lrmfrf demo. Choose another --out "
        "folder, or pass --force (overwrite=True) to replace it."
    )


def _is_legacy_manifest(content) -> bool:
    names = {f"{kind}_{name}.{ext}" for name in SYSTEMS
             for kind, ext in (("frf", "csv"), ("bode", "png"))}
    return (
        isinstance(content, dict)
        and bool(content)
        and all(key in names for key in content)
        and all(
            isinstance(value, str)
            and len(value) == 64
            and all(c in "0123456789abcdef" for c in value)
            for value in content.values()
        )
    )


def _check_target(path: Path, manifest: dict, overwrite: bool) -> None:
    if not path.exists() or overwrite:
        if path.is_dir():
            raise ValueError(f"{path}: an output name is taken by a folder. "
                             "Choose another --out.")
        return
    if manifest.get(path.name) != file_sha256(path):
        raise FileExistsError(
            f"{path}: exists already and was not written by lrmfrf demo (or was "
            "changed since). Choose another --out folder, or pass --force "
            "(overwrite=True) to replace it."
        )


def _write(path: Path, data: bytes, manifest: dict, overwrite: bool) -> None:
    ours = path.exists() and manifest.get(path.name) == file_sha256(path)
    with atomic_open(path, overwrite=overwrite or ours) as fh:
        fh.write(data)


def _write_manifest(out: Path, manifest: dict) -> None:
    """Write the manifest (checked to be the demo's own by _read_manifest)."""
    content = {"written_by": _WRITER, "files": dict(sorted(manifest.items()))}
    with atomic_open(out / MANIFEST, overwrite=True) as fh:
        fh.write(json.dumps(content, indent=1).encode())
