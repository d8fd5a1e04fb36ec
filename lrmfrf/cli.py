"""Command line: ``lrmfrf fit``, ``lrmfrf example-data`` and ``lrmfrf demo``.

Examples
--------
Copy the shipped example into the current folder and estimate its FRF
(F = 3, fast sample time 0.5 ms)::

    lrmfrf example-data
    lrmfrf fit wafer_stage_example.csv --F 3 --sample-time 0.5e-3 --out results

writes ``results/frf.csv``, ``results/frf.npz``, ``results/bode.png`` and
``results/report.txt``. With several data files each gets its own subfolder
``results/<file stem>/``.

Errors (missing file, bad column, NaN, lengths that do not match ``F``, an
existing output without ``--force`` ...) end the program with exit status 1
and one line on standard error naming the file, the problem and the fix;
``--debug`` shows the traceback instead. Usage errors exit with status 2.
The input files are never modified: outputs go through a temporary file and
``os.replace``, and an output path that is an input file is refused.
"""

from __future__ import annotations

import argparse
import logging
import math
import platform
import shlex
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["main", "build_parser"]

logger = logging.getLogger("lrmfrf.cli")

PROG = "lrmfrf"
OUTPUT_NAMES = ("frf.csv", "frf.npz", "bode.png", "report.txt")
EXAMPLE_FILES = ("wafer_stage_example.csv", "wafer_stage_example.npz")
#: Bode plots of longer FRFs draw this many log-spaced bins per curve.
PLOT_MAX_POINTS = 20_000

_METHOD_OPTIONS = {
    "lrm": {"half_window", "num_degree", "transient_degree", "den_degree"},
    "lpm": {"half_window", "degree", "transient_degree"},
    "sa": {"segment_length", "overlap"},
}
_METHOD_NAMES = {
    "lrm": "LRMBeyondNyquist",
    "lpm": "LPMBeyondNyquist",
    "sa": "SpectralAnalysis",
}


class CLIError(Exception):
    """A failure reported as one line on standard error (exit status 1)."""


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors are one line on stderr, status 2."""

    def error(self, message):  # noqa: D102 - argparse API
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _number(kind, ok, expected: str):
    """An argparse type: ``kind(text)`` that must satisfy ``ok``."""

    def convert(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not ok(value):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value

    convert.__name__ = expected
    return convert


_positive_int = _number(int, lambda v: v >= 1, "a positive integer")
_nonnegative_int = _number(int, lambda v: v >= 0, "an integer >= 0")
_positive_float = _number(
    float, lambda v: math.isfinite(v) and v > 0, "a positive number"
)
_finite_float = _number(float, math.isfinite, "a finite number")


def build_parser() -> argparse.ArgumentParser:
    """The ``lrmfrf`` argument parser (subcommands ``fit`` and ``demo``)."""
    from . import __version__

    parser = _Parser(
        prog=PROG,
        description="Fast-rate FRF identification beyond the Nyquist frequency of "
        "a slow-rate sensor (local rational modelling).",
    )
    parser.add_argument(
        "--version", action="version", version=f"%(prog)s {__version__}"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    _add_fit_parser(sub)
    _add_example_parser(sub)
    _add_demo_parser(sub)
    _add_diagnose_parser(sub)
    return parser


def _add_common(parser) -> None:
    parser.add_argument("--force", action="store_true",
                        help="replace existing output files")
    parser.add_argument("--debug", action="store_true",
                        help="show tracebacks and debug logging")
    parser.add_argument("--quiet", action="store_true",
                        help="print nothing but errors (no progress bar, warnings "
                        "or summary)")


def _add_fit_parser(sub) -> None:
    fit = sub.add_parser(
        "fit",
        help="estimate the FRF from measured data files",
        description="Estimate the fast-rate FRF from a fast input and a slow output "
        "read from CSV, NPZ or MAT files. Writes frf.csv, frf.npz, bode.png and "
        "report.txt into --out (one subfolder per file when several are given).",
    )
    fit.add_argument("data", nargs="+", metavar="DATA",
                     help=".csv (header row), .npz or .mat file(s)")
    fit.add_argument("--F", dest="F", type=_positive_int, required=True,
                     help="downsampling factor (slow / fast sample time)")
    fit.add_argument("--sample-time", type=_positive_float, required=True,
                     metavar="SECONDS",
                     help="fast sample time in seconds, e.g. 0.5e-3")
    fit.add_argument("--out", type=Path, required=True, metavar="DIR",
                     help="output folder (created if needed)")
    fit.add_argument("--method", choices=list(_METHOD_OPTIONS), default="lrm",
                     help="lrm (default), lpm or sa (spectral analysis)")
    group = fit.add_argument_group("method settings (default: the estimator's)")
    group.add_argument("--half-window", type=_positive_int, metavar="N",
                       help="lrm, lpm: window half width n (2n+1 slow bins)")
    group.add_argument("--num-degree", type=_nonnegative_int, metavar="N",
                       help="lrm: system numerator degree R_g")
    group.add_argument("--transient-degree", type=_nonnegative_int, metavar="N",
                       help="lrm, lpm: transient numerator degree R_t")
    group.add_argument("--den-degree", type=_nonnegative_int, metavar="N",
                       help="lrm: denominator degree R_e")
    group.add_argument("--degree", type=_nonnegative_int, metavar="N",
                       help="lpm: polynomial degree")
    group.add_argument("--segment-length", type=_positive_int, metavar="N",
                       help="sa: samples per segment")
    group.add_argument("--overlap", type=_nonnegative_int, metavar="N",
                       help="sa: samples shared by consecutive segments")
    columns = fit.add_argument_group("data columns")
    columns.add_argument("--input-column", default="u", metavar="NAME",
                         help="column or variable of the fast input (default u)")
    columns.add_argument("--output-column", default="y", metavar="NAME",
                         help="column or variable of the slow output (default y)")
    from .io import DEFAULT_MAX_SAMPLES

    columns.add_argument("--max-samples", type=_positive_int,
                         default=DEFAULT_MAX_SAMPLES, metavar="N",
                         help=f"refuse files with more rows (default "
                         f"{DEFAULT_MAX_SAMPLES})")
    fit.add_argument("--no-plot", action="store_true",
                     help="do not draw bode.png")
    _add_common(fit)
    fit.set_defaults(handler=_run_fit)


def _add_example_parser(sub) -> None:
    example = sub.add_parser(
        "example-data",
        help="copy the shipped example data into a folder",
        description="Copy the shipped example records (wafer stage, N=1200, F=3, "
        f"Ts=0.5 ms) {', '.join(EXAMPLE_FILES)} into --out.",
    )
    example.add_argument("--out", type=Path, default=Path("."), metavar="DIR",
                         help="destination folder (default: the current folder)")
    _add_common(example)
    example.set_defaults(handler=_run_example_data)


def _add_demo_parser(sub) -> None:
    demo = sub.add_parser(
        "demo",
        help="simulate the wafer stage, compare LRM, LPM and SA",
        description="Simulate the OAT-like wafer stage, identify it with LRM, LPM "
        "and SA, print an error table and write figures into --out.",
    )
    demo.add_argument("--out", type=Path, default=Path("lrmfrf-demo"), metavar="DIR",
                      help="output folder (default ./lrmfrf-demo)")
    demo.add_argument("--seed", type=_nonnegative_int, default=0,
                      help="random seed (default 0)")
    demo.add_argument("--snr", type=_finite_float, default=45.0, metavar="DB",
                      help="output signal-to-noise ratio in dB (default 45)")
    _add_common(demo)
    demo.set_defaults(handler=_run_demo)


def _add_diagnose_parser(sub) -> None:
    diag = sub.add_parser(
        "diagnose",
        help="find what a plant model misses, given measured data",
        description="Compare a python-control plant model with a measured "
        "beyond-Nyquist FRF, name the missing effects (gain, delay, low_pass, "
        "missing_mode, mode_shift), add them and report the gap before and after. "
        "The model is a Python file that defines `plant` (and optionally "
        "`controller`, for closed-loop data P/(1+CP)); the file is executed, so "
        "only pass files you trust. Writes diagnosis.txt, diagnosis.json and "
        "diagnosis.png into --out.",
    )
    diag.add_argument("model", type=Path, metavar="MODEL.py",
                      help="Python file defining `plant` (and `controller`)")
    diag.add_argument("data", type=Path, metavar="DATA",
                      help=".csv (header row), .npz or .mat file")
    diag.add_argument("--F", dest="F", type=_positive_int, required=True,
                      help="downsampling factor (slow / fast sample time)")
    diag.add_argument("--sample-time", type=_positive_float, required=True,
                      metavar="SECONDS", help="fast sample time in seconds")
    diag.add_argument("--out", type=Path, required=True, metavar="DIR",
                      help="output folder (created if needed)")
    diag.add_argument("--open-loop", action="store_true",
                      help="ignore `controller`: the data are the plant itself")
    diag.add_argument("--seed", type=_nonnegative_int, default=0,
                      help="seed of the calibration simulations (default 0)")
    diag.add_argument("--input-column", default="u", metavar="NAME")
    diag.add_argument("--output-column", default="y", metavar="NAME")
    diag.add_argument("--no-plot", action="store_true",
                      help="do not draw diagnosis.png")
    _add_common(diag)
    diag.set_defaults(handler=_run_diagnose)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit status.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        0 on success, 1 when a file or a computation failed, 2 for usage
        errors, 130 when interrupted.
    """
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    args.argv = argv
    _configure_logging(args)
    try:
        return args.handler(args, parser)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # one line for the user, traceback with --debug
        if args.debug:
            raise
        print(f"{PROG}: error: {_one_line(exc)}", file=sys.stderr)
        return 1


# --------------------------------------------------------------------------
# fit
# --------------------------------------------------------------------------


@dataclass
class _Job:
    data: Path
    out_dir: Path

    def outputs(self) -> list[Path]:
        return [self.out_dir / name for name in OUTPUT_NAMES]


def _run_fit(args, parser) -> int:
    from .progress import progress

    settings = _method_settings(args, parser)
    jobs = _plan_jobs(args)
    status = 0
    show_bar = not args.quiet and len(jobs) > 1
    bar = progress(jobs, enabled=None if show_bar else False, desc="files",
                   unit="file")
    # Lines printed while a bar is drawn go through tqdm.write (no garbling).
    say = getattr(bar, "write", None) or (lambda text, file: print(text, file=file))
    for job in bar:
        try:
            summary = _fit_one(job, args, settings, [j.data for j in jobs], say)
        except Exception as exc:
            if args.debug:
                raise
            say(f"{PROG}: error: {_one_line(exc)}", file=sys.stderr)
            status = 1
            continue
        if not args.quiet:
            say(summary, file=sys.stdout)
    return status


def _method_settings(args, parser) -> dict:
    """Estimator keyword arguments from the options; reject foreign options."""
    every = set().union(*_METHOD_OPTIONS.values())
    given = {name for name in every if getattr(args, name) is not None}
    foreign = sorted(given - _METHOD_OPTIONS[args.method])
    if foreign:
        options = ", ".join("--" + name.replace("_", "-") for name in foreign)
        verb = "does" if len(foreign) == 1 else "do"
        parser.exit(
            2,
            f"{PROG} fit: error: {options} {verb} not apply to --method "
            f"{args.method} (see {PROG} fit --help)\n",
        )
    return {name: getattr(args, name) for name in sorted(given)}


def _plan_jobs(args) -> list[_Job]:
    """Output folder per input; check every output before any work is done."""
    from .io import check_output_path

    inputs = [Path(p) for p in args.data]
    out = args.out
    if out.exists() and not out.is_dir():
        raise CLIError(f"{out}: --out is a file, not a folder. Choose a folder name.")
    if len(inputs) == 1:
        jobs = [_Job(inputs[0], out)]
    else:
        folders = _subfolder_names(inputs)
        jobs = [_Job(p, out / name) for p, name in zip(inputs, folders, strict=True)]
    for job in jobs:
        for path in job.outputs():
            check_output_path(path, overwrite=args.force, protect=inputs)
    return jobs


def _subfolder_names(inputs: list[Path]) -> list[str]:
    """File stems; ``stem_suffix`` where stems clash (``a.csv``, ``a.npz``)."""
    stems = [p.stem for p in inputs]
    names = [
        p.stem if stems.count(p.stem) == 1 else p.name.replace(".", "_")
        for p in inputs
    ]
    clashes = sorted({n for n in names if names.count(n) > 1})
    if clashes:
        raise CLIError(
            f"several input files are named like {clashes[0]!r}, so their output "
            "subfolders would clash. Fit them in separate runs with different "
            "--out folders."
        )
    return names


def _fit_one(job: _Job, args, settings: dict, inputs: list[Path], say) -> str:
    from .io import frf_table, read_measurement, write_frf_csv, write_frf_npz

    data = read_measurement(
        job.data,
        F=args.F,
        input_column=args.input_column,
        output_column=args.output_column,
        max_samples=args.max_samples,
    )
    estimator = _make_estimator(args.method, settings)
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            estimator.fit(data.u_h, data.y_l, data.downsampling_factor,
                          sample_time=args.sample_time)
        except (ValueError, TypeError) as exc:
            raise CLIError(f"{job.data}: {_one_line(exc)}") from exc
    elapsed = time.perf_counter() - start
    messages = [_one_line(w.message) for w in caught]
    if not args.quiet:
        for message in messages:
            say(f"{PROG}: warning: {job.data}: {message}", file=sys.stderr)
    job.out_dir.mkdir(parents=True, exist_ok=True)
    table = frf_table(estimator)
    write = {"overwrite": args.force, "protect": inputs}
    out_csv, out_npz, out_png, out_report = job.outputs()
    write_frf_csv(out_csv, table, **write)
    metadata = _metadata(args, data, settings)
    write_frf_npz(out_npz, table, metadata=metadata, **write)
    plot_note = _write_plot(out_png, estimator, data, args, write)
    if plot_note and not args.quiet:
        say(f"{PROG}: warning: {job.data}: {plot_note}", file=sys.stderr)
    numbers = _summary_numbers(estimator, table, elapsed)
    report = _report_text(args, data, settings, estimator, numbers, messages,
                          plot_note)
    from .io import atomic_open

    with atomic_open(out_report, **write) as fh:
        fh.write(report.encode("utf-8"))
    written = ", ".join(p.name for p in job.outputs() if p.exists())
    return (
        f"{job.data} -> {job.out_dir}/ ({written}): {numbers['n_valid']} of "
        f"{numbers['n_bins']} bins valid, median std/|G| "
        f"{numbers['median_rel_std_below']:.3g} below and "
        f"{numbers['median_rel_std_above']:.3g} above the slow Nyquist frequency"
    )


def _make_estimator(method: str, settings: dict):
    from . import estimators

    return getattr(estimators, _METHOD_NAMES[method])(**settings)


def _write_plot(path: Path, estimator, data, args, write) -> str | None:
    """Draw bode.png; return a note when it was not drawn."""
    if args.no_plot:
        return None
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        from matplotlib.figure import Figure
    except ImportError:
        return 'bode.png not drawn: matplotlib is missing (pip install "lrmfrf[plot]")'
    from .io import atomic_open
    from .plotting import plot_frf

    fig = Figure(figsize=(9, 6.5), layout="constrained")
    axes = fig.subplots(2, 1, sharex=True)
    plot_frf(
        estimator,
        ax=axes,
        labels=[f"{args.method.upper()} estimate"],
        max_points=PLOT_MAX_POINTS,
        title=f"{data.path.name}: F = {data.downsampling_factor}, "
        f"Ts = {_seconds(args.sample_time)}, N = {data.n_samples}",
    )
    with atomic_open(path, **write) as fh:
        fig.savefig(fh, format="png", dpi=120)
    return None


def _summary_numbers(estimator, table: dict, elapsed: float) -> dict:
    freq = table["frequency_hz"]
    valid = table["valid"]
    magnitude = np.abs(table["real"] + 1j * table["imag"])
    F = estimator.downsampling_factor_
    slow_nyquist = 1.0 / (2.0 * F * estimator.sample_time_)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_std = table["std"] / magnitude
    below = valid & (freq > 0) & (freq <= slow_nyquist) & np.isfinite(rel_std)
    above = valid & (freq > slow_nyquist) & np.isfinite(rel_std)
    peak_index = int(np.nanargmax(np.where(valid & (freq > 0), magnitude, np.nan))) \
        if (valid & (freq > 0)).any() else None
    return {
        "n_bins": int(freq.size),
        "n_valid": int(valid.sum()),
        "slow_nyquist_hz": slow_nyquist,
        "fast_nyquist_hz": 1.0 / (2.0 * estimator.sample_time_),
        "resolution_hz": float(freq[1] - freq[0]) if freq.size > 1 else float("nan"),
        "median_rel_std_below": float(np.median(rel_std[below])) if below.any()
        else float("nan"),
        "median_rel_std_above": float(np.median(rel_std[above])) if above.any()
        else float("nan"),
        "peak_hz": float(freq[peak_index]) if peak_index is not None else float("nan"),
        "peak_db": float(20 * np.log10(magnitude[peak_index]))
        if peak_index is not None else float("nan"),
        "fit_seconds": elapsed,
    }


def _metadata(args, data, settings: dict) -> dict:
    meta = {
        "method": args.method,
        "downsampling_factor": data.downsampling_factor,
        "sample_time": args.sample_time,
        "n_samples": data.n_samples,
        "n_slow": data.n_slow,
        "input_file": str(data.path),
        "input_sha256": data.sha256,
    }
    meta.update({f"setting_{k}": v for k, v in settings.items()})
    return meta


def _report_text(args, data, settings, estimator, numbers, messages, plot_note) -> str:
    from . import __version__

    params = estimator.get_params()
    lines = [
        "lrmfrf fit report",
        "=================",
        f"command: {PROG} " + " ".join(shlex.quote(a) for a in args.argv),
        f"lrmfrf {__version__}, numpy {np.__version__}, python "
        f"{platform.python_version()}",
        "",
        "Settings",
        "--------",
        f"input file: {data.path} ({data.file_format})",
        f"columns: input {data.input_column!r}, output {data.output_column!r}",
        f"downsampling factor F: {data.downsampling_factor}",
        f"fast sample time: {args.sample_time:g} s "
        f"(slow sample time {args.sample_time * data.downsampling_factor:g} s)",
        f"method: {args.method} ({type(estimator).__name__})",
        "estimator parameters: "
        + ", ".join(f"{k}={v!r}" for k, v in sorted(params.items())),
        "set on the command line: "
        + (", ".join(f"{k}={v!r}" for k, v in settings.items()) or "nothing"),
        "",
        "Data checks",
        "-----------",
        *[f"- {check}" for check in data.checks],
        "",
        "Summary",
        "-------",
        f"N = {data.n_samples} fast samples, M = {data.n_slow} slow samples",
        f"frequency grid: {numbers['n_bins']} bins from 0 to "
        f"{numbers['fast_nyquist_hz']:.6g} Hz, resolution "
        f"{numbers['resolution_hz']:.6g} Hz",
        f"slow Nyquist frequency: {numbers['slow_nyquist_hz']:.6g} Hz",
        f"valid bins: {numbers['n_valid']} of {numbers['n_bins']}",
        f"largest |G|: {numbers['peak_db']:.4g} dB at {numbers['peak_hz']:.6g} Hz",
        "median std/|G| below the slow Nyquist frequency: "
        f"{numbers['median_rel_std_below']:.4g}",
        "median std/|G| above the slow Nyquist frequency: "
        f"{numbers['median_rel_std_above']:.4g}",
    ]
    if hasattr(estimator, "n_params_"):
        lines.append(
            f"local model: {estimator.n_params_} parameters, {estimator.dof_} "
            "residual degrees of freedom per window"
        )
    lines.append(f"fit time: {numbers['fit_seconds']:.3g} s")
    lines += ["", "Warnings", "--------"]
    notes = list(messages) + ([plot_note] if plot_note else [])
    lines += [f"- {m}" for m in notes] or ["none"]
    lines += [
        "",
        "Files",
        "-----",
        "frf.csv, frf.npz: columns frequency_hz, real, imag, magnitude_db, "
        "phase_deg, std, valid",
        "  (std: standard deviation of the complex estimate; valid = 0 rows are NaN)",
        "bode.png: magnitude and phase with a +/-2 std band; dotted line at the "
        "slow Nyquist frequency",
        "",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------
# example-data
# --------------------------------------------------------------------------


def _run_example_data(args, parser) -> int:
    from importlib.resources import files

    from .io import atomic_open, check_output_path

    source = files("lrmfrf") / "data"
    if args.out.exists() and not args.out.is_dir():
        raise CLIError(f"{args.out}: --out is a file, not a folder. Choose a folder.")
    targets = [args.out / name for name in EXAMPLE_FILES]
    for target in targets:
        check_output_path(target, overwrite=args.force)
    args.out.mkdir(parents=True, exist_ok=True)
    for name, target in zip(EXAMPLE_FILES, targets, strict=True):
        with atomic_open(target, overwrite=args.force) as fh:
            fh.write((source / name).read_bytes())
        if not args.quiet:
            print(f"wrote {target}")
    return 0


# --------------------------------------------------------------------------
# demo
# --------------------------------------------------------------------------


def _run_demo(args, parser) -> int:
    try:
        from .demo import run_demo
    except ImportError as exc:
        raise CLIError(
            f"the demo is not available in this installation ({_one_line(exc)}). "
            "Reinstall lrmfrf or update it."
        ) from exc
    result = run_demo(args.out, seed=args.seed, snr_db=args.snr, overwrite=args.force)
    if not args.quiet:
        print(result.table)
        for path in result.files:
            print(f"wrote {path}")
        for note in getattr(result, "notes", ()):
            print(f"{PROG}: warning: {note}", file=sys.stderr)
    return 0


# --------------------------------------------------------------------------
# diagnose
# --------------------------------------------------------------------------

DIAGNOSE_OUTPUTS = ("diagnosis.txt", "diagnosis.json", "diagnosis.png")


def _load_model(path: Path, open_loop: bool):
    """Run the user's model file and return ``(plant, controller)``."""
    import runpy

    if not path.is_file():
        raise CLIError(f"{path}: model file not found. Pass a .py file that "
                       "defines `plant`.")
    try:
        namespace = runpy.run_path(str(path))
    except Exception as exc:
        raise CLIError(
            f"{path}: the model file failed to run: {_one_line(exc)}. Fix the "
            "file (run it with python to see the traceback)."
        ) from exc
    if "plant" not in namespace:
        raise CLIError(f"{path}: the model file defines no `plant`. Assign the "
                       "python-control plant model to a variable named plant.")
    controller = None if open_loop else namespace.get("controller")
    return namespace["plant"], controller


def _run_diagnose(args, parser) -> int:
    import json

    from .discrepancy import diagnose
    from .io import atomic_open, check_output_path, read_measurement

    plant, controller = _load_model(args.model, args.open_loop)
    data = read_measurement(args.data, F=args.F, input_column=args.input_column,
                            output_column=args.output_column)
    if args.out.exists() and not args.out.is_dir():
        raise CLIError(f"{args.out}: --out is a file, not a folder. Choose a folder.")
    protect = [args.data, args.model]
    outputs = [args.out / name for name in DIAGNOSE_OUTPUTS]
    for path in outputs:
        check_output_path(path, overwrite=args.force, protect=protect)
    try:
        report = diagnose(plant, data.u_h, data.y_l, args.F,
                          sample_time=args.sample_time, controller=controller,
                          random_state=args.seed)
    except (ValueError, TypeError) as exc:
        raise CLIError(f"{args.data}: {_one_line(exc)}") from exc
    args.out.mkdir(parents=True, exist_ok=True)
    write = {"overwrite": args.force, "protect": protect}
    text_path, json_path, png_path = outputs
    with atomic_open(text_path, **write) as fh:
        fh.write(report.summary().encode("utf-8"))
    with atomic_open(json_path, **write) as fh:
        fh.write(json.dumps(report.to_dict(), indent=1).encode("utf-8"))
    if not args.no_plot:
        import io as _io

        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        drawn = report.plot()
        buffer = _io.BytesIO()
        drawn["figure"].savefig(buffer, format="png", dpi=110)
        plt.close(drawn["figure"])
        with atomic_open(png_path, **write) as fh:
            fh.write(buffer.getvalue())
    if not args.quiet:
        print(report.summary())
    return 0


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------


def _seconds(value: float) -> str:
    """A time in s, ms or us for titles: ``0.5e-3`` -> ``"0.5 ms"``."""
    for scale, unit in ((1.0, "s"), (1e-3, "ms"), (1e-6, "us")):
        if abs(value) >= 0.1 * scale:
            return f"{value / scale:.4g} {unit}"
    return f"{value:.4g} s"


def _configure_logging(args) -> None:
    level = logging.DEBUG if args.debug else (
        logging.ERROR if args.quiet else logging.WARNING
    )
    logging.basicConfig(level=level, format=f"{PROG}: %(levelname)s: %(message)s")


def _one_line(exc) -> str:
    text = " ".join(str(exc).split())
    if isinstance(exc, BaseException) and not isinstance(
        exc, (CLIError, ValueError, TypeError, OSError)
    ):
        text = f"{type(exc).__name__}: {text}"
    if isinstance(exc, OSError) and getattr(exc, "filename", None) and (
        str(exc.filename) not in text
    ):
        text = f"{exc.filename}: {text}"
    return text or type(exc).__name__


if __name__ == "__main__":
    raise SystemExit(main())
