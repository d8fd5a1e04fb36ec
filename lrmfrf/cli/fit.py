"""``lrmfrf fit``: estimate the FRF of measured data files.

Each data file is read and checked, the estimator is fitted, and everything
written is computed first (FRF table, metadata, Bode PNG, report); the four
files are then written together with :func:`lrmfrf.io.atomic_group`, so a
failure leaves none of them.
"""

from __future__ import annotations

import platform
import re
import shlex
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..estimators.selection import CRITERIA
from ._common import (
    PROG,
    CLIError,
    CLIUsageError,
    add_common,
    add_data_options,
    check_out_folder,
    nonnegative_int,
    one_line,
    output_folder,
    png_bytes,
    positive_float,
    positive_int,
    read_data,
    say,
    seconds,
)

__all__ = ["OUTPUT_NAMES", "PLOT_MAX_POINTS", "add_parser", "run"]

OUTPUT_NAMES = ("frf.csv", "frf.npz", "bode.png", "report.txt")
#: Bode plots of longer FRFs draw this many log-spaced bins per curve.
PLOT_MAX_POINTS = 20_000

#: Estimator parameters each method takes from the command line.
METHOD_OPTIONS = {
    "lrm": {"half_window", "num_degree", "transient_degree", "den_degree",
            "sk_iterations"},
    "lpm": {"half_window", "num_degree", "transient_degree"},
    "sa": {"segment_length", "overlap"},
}
METHOD_NAMES = {
    "lrm": "LRMBeyondNyquist",
    "lpm": "LPMBeyondNyquist",
    "sa": "SpectralAnalysis",
}
#: Estimators that choose the window and degrees with --select.
SELECT_NAMES = {"lrm": "LRMBeyondNyquistCV", "lpm": "LPMBeyondNyquistCV"}


def add_parser(sub) -> None:
    """Add the ``fit`` subcommand to ``sub``."""
    fit = sub.add_parser(
        "fit",
        help="estimate the FRF from measured data files",
        description="Estimate the fast-rate FRF from a fast input and a slow output "
        "read from CSV, NPZ or MAT files. Writes frf.csv, frf.npz, bode.png and "
        "report.txt into --out (one subfolder per file when several are given); "
        "the files of one data file are written all or nothing.",
    )
    fit.add_argument("data", nargs="+", metavar="DATA",
                     help=".csv (header row), .npz or .mat file(s)")
    fit.add_argument("--out", type=output_folder, required=True, metavar="DIR",
                     help="output folder (created if needed)")
    fit.add_argument("--method", choices=list(METHOD_OPTIONS), default="lrm",
                     help="lrm (default), lpm or sa (spectral analysis)")
    add_data_options(fit, several=True, channels=True)
    group = fit.add_argument_group("method settings (default: the estimator's)")
    group.add_argument("--half-window", type=positive_int, metavar="N",
                       help="lrm, lpm: window half width n (2n+1 slow bins)")
    group.add_argument("--num-degree", type=nonnegative_int, metavar="N",
                       help="lrm, lpm: system numerator (lpm: polynomial) degree "
                       "R_g")
    group.add_argument("--transient-degree", type=nonnegative_int, metavar="N",
                       help="lrm, lpm: transient numerator degree R_t")
    group.add_argument("--den-degree", type=nonnegative_int, metavar="N",
                       help="lrm: denominator degree R_e")
    group.add_argument("--sk-iterations", type=nonnegative_int, metavar="N",
                       help="lrm: Sanathanan-Koerner refinement iterations "
                       "(default 0)")
    group.add_argument("--degree", type=nonnegative_int, metavar="N",
                       help="deprecated: use --num-degree (lpm)")
    group.add_argument("--segment-length", type=positive_int, metavar="N",
                       help="sa: samples per segment")
    group.add_argument("--overlap", type=nonnegative_int, metavar="N",
                       help="sa: samples shared by consecutive segments")
    group.add_argument("--select", choices=CRITERIA, metavar="CRITERION",
                       help="lrm, lpm: choose the window and degrees from the "
                       "data by a closed-form criterion, one of "
                       f"{', '.join(CRITERIA)} (LRMBeyondNyquistCV, "
                       "LPMBeyondNyquistCV); the choice is in report.txt")
    plot = fit.add_argument_group("Bode plot")
    plot.add_argument("--no-plot", action="store_true",
                      help="do not draw bode.png")
    plot.add_argument("--freq-range", type=positive_float, nargs=2,
                      metavar=("LO", "HI"),
                      help="draw only LO to HI Hz (a zoom, e.g. on a resonance)")
    plot.add_argument("--units", metavar="TEXT",
                      help="units of G for the magnitude axis, e.g. m/N "
                      "(dB re 1 TEXT)")
    add_common(fit)
    fit.set_defaults(handler=run)


@dataclass
class _Job:
    data: Path
    out_dir: Path

    def outputs(self) -> list[Path]:
        return [self.out_dir / name for name in OUTPUT_NAMES]


def run(args, parser) -> int:
    """Run ``lrmfrf fit``; the exit status is the worst over the files."""
    from ..progress import progress

    settings = method_settings(args)
    jobs = _plan_jobs(args)
    status = 0
    show_bar = not args.quiet and len(jobs) > 1
    bar = progress(jobs, enabled=None if show_bar else False, desc="files",
                   unit="file")
    # Lines printed while a bar is drawn go through tqdm.write (no garbling).
    write = getattr(bar, "write", None) or (lambda text, file: print(text, file=file))
    for job in bar:
        try:
            summary = _fit_one(job, args, settings, [j.data for j in jobs], write)
        except Exception as exc:
            if args.debug:
                raise
            write(f"{PROG}: error: {one_line(exc)}", file=sys.stderr)
            status = max(status, getattr(exc, "exit_status", 1))
            continue
        if not args.quiet:
            write(summary, file=sys.stdout)
    return status


def method_settings(args) -> dict:
    """Estimator keyword arguments from the options; refuse foreign options."""
    if args.degree is not None:
        if args.num_degree is not None:
            raise CLIUsageError("--degree and --num-degree name the same setting. "
                                "Pass only --num-degree.")
        if not args.quiet:
            say(f"{PROG}: warning: --degree is deprecated and will be removed in "
                "the next release; use --num-degree", error=True)
        args.num_degree = args.degree
    every = set().union(*METHOD_OPTIONS.values())
    given = {name for name in every if getattr(args, name) is not None}
    foreign = sorted(given - METHOD_OPTIONS[args.method])
    if foreign:
        raise CLIUsageError(
            f"{_options(foreign)} {_verb(foreign)} not apply to --method "
            f"{args.method} (see {PROG} fit --help)"
        )
    if args.select is not None:
        if args.method not in SELECT_NAMES:
            raise CLIUsageError(
                f"--select applies to --method lrm or lpm, not {args.method} "
                f"(see {PROG} fit --help)")
        if given:
            raise CLIUsageError(
                f"{_options(sorted(given))} {_verb(given)} not apply with --select, "
                "which chooses the window and degrees. Drop one or the other.")
    if args.freq_range is not None and not args.freq_range[0] < args.freq_range[1]:
        low, high = args.freq_range
        raise CLIUsageError(f"--freq-range {low:g} {high:g}: LO must be below HI")
    if args.no_plot and (args.freq_range is not None or args.units is not None):
        raise CLIUsageError("--freq-range and --units set up bode.png, which "
                            "--no-plot leaves out. Drop one or the other.")
    return {name: getattr(args, name) for name in sorted(given)}


def _options(names) -> str:
    return ", ".join("--" + name.replace("_", "-") for name in sorted(names))


def _verb(names) -> str:
    return "does" if len(names) == 1 else "do"


def _plan_jobs(args) -> list[_Job]:
    """Output folder per input; check every output before any work is done."""
    from ..io import check_output_path

    inputs = [Path(p) for p in args.data]
    out = check_out_folder(args.out)
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


#: The estimators' parameters named in their errors, and this command's flags.
_FLAGS = {name: "--" + name.replace("_", "-") for name in (
    "half_window", "num_degree", "transient_degree", "den_degree",
    "sk_iterations", "segment_length", "overlap")}


def _cli_words(text: str) -> str:
    """An estimator's error in this command's words: its parameters as flags
    (``half_window=40`` becomes ``--half-window=40``, which the command takes),
    and, where it advises more experiments, that each file is fitted as one."""
    for name, flag in _FLAGS.items():
        # prose only: not in a formula such as "(num_degree+1)*F*n_u"
        text = re.sub(rf"(?<![\w(-]){name}\b(?!\s*\+|\s+=)", flag, text)
    if re.search(r"\bexperiments\b", text):
        text += (" (lrmfrf fit fits each file as one experiment: fit several "
                 "experiments together in Python, "
                 "`est.fit([u1, u2], [y1, y2], F)`.)")
    return text


def _fit_one(job: _Job, args, settings: dict, inputs: list[Path], write) -> str:
    from ..io import atomic_group, frf_table, write_frf_csv, write_frf_npz

    data = read_data(job.data, args)
    if data.sample_time is None:
        raise CLIUsageError(
            f"{job.data}: the file stores no sample time (no time column, no "
            "'sample_time'), so --sample-time is required. Pass --sample-time "
            "SECONDS, the fast sample time."
        )
    estimator = make_estimator(args.method, settings, args.select)
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            # one experiment, as a list of one record: a 2-D MIMO record
            # passed bare would add the estimators' hint about 2-D arrays
            # (Python layouts) to a shape error, which means nothing here
            estimator.fit([data.u_h], [data.y_l], data.downsampling_factor,
                          sample_time=data.sample_time)
        except (ValueError, TypeError) as exc:
            raise CLIError(f"{job.data}: {_cli_words(one_line(exc))}") from exc
    elapsed = time.perf_counter() - start
    messages = [one_line(w.message) for w in caught]
    table = frf_table(estimator)
    _check_finite(job, table)
    numbers = _summary_numbers(estimator, table, elapsed)
    png, plot_note = _bode_png(estimator, data, args)
    report = _report_text(args, data, settings, estimator, numbers, messages,
                          plot_note)
    if not args.quiet:
        for message in messages + ([plot_note] if plot_note else []):
            write(f"{PROG}: warning: {job.data}: {message}", file=sys.stderr)
    out_csv, out_npz, out_png, out_report = job.outputs()
    with atomic_group(overwrite=args.force, protect=inputs) as group:
        write_frf_csv(out_csv, table, group=group)
        write_frf_npz(out_npz, table, metadata=_metadata(args, data, settings),
                      group=group)
        if png is not None:
            group.write_bytes(out_png, png)
        group.write_bytes(out_report, report.encode("utf-8"))
        written = ", ".join(p.name for p in group.paths)
    return (
        f"{job.data} -> {job.out_dir}/ ({written}): {numbers['n_valid']} of "
        f"{numbers['n_bins']} bins valid, median std/|G| "
        f"{numbers['median_rel_std_below']:.3g} below and "
        f"{numbers['median_rel_std_above']:.3g} above the slow Nyquist frequency"
    )


def make_estimator(method: str, settings: dict, select: str | None = None):
    """The estimator of ``--method`` (or its CV class with ``--select``)."""
    from .. import estimators

    if select is not None:
        from ..estimators import selection

        return getattr(selection, SELECT_NAMES[method])(criterion=select)
    return getattr(estimators, METHOD_NAMES[method])(**settings)


def _check_finite(job: _Job, table: dict) -> None:
    """Bins marked valid must hold finite numbers: never write garbage."""
    valid = table["valid"]
    bad = valid & ~(np.isfinite(table["real"]) & np.isfinite(table["imag"])
                    & np.isfinite(table["std"]))
    if bad.any():
        raise CLIError(
            f"{job.data}: the estimate is not finite at {int(bad.sum())} of "
            f"{int(valid.sum())} bins marked valid, so nothing was written. "
            "Check the data's scale and content (a constant or huge signal), or "
            "try another --method"
        )


def _bode_png(estimator, data, args) -> tuple[bytes | None, str | None]:
    """bode.png as bytes, or None and a note saying why it was not drawn."""
    if args.no_plot:
        return None, None
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        from matplotlib.figure import Figure
    except ImportError:
        return None, ('bode.png not drawn: matplotlib is missing (pip install '
                      '"lrmfrf[plot]")')
    from ..plotting import plot_frf

    mimo = np.ndim(estimator.frf_) == 3
    if mimo:
        n_y, n_u = np.shape(estimator.frf_)[:2]
        fig = Figure(figsize=(max(6.0, 3.2 * n_u), max(4.0, 2.4 * n_y)),
                     layout="constrained")
        axes = np.asarray(fig.subplots(n_y, n_u, sharex=True, squeeze=False))
        drawn = _Labelled(estimator, data.input_names, data.output_names)
    else:
        fig = Figure(figsize=(9, 6.5), layout="constrained")
        axes = fig.subplots(2, 1, sharex=True)
        drawn = estimator
    extra = {}
    if args.freq_range is not None:
        extra["freq_range"] = tuple(args.freq_range)
    if args.units is not None:
        extra["units"] = args.units
    label = f"{args.method.upper()} estimate"
    if args.select:
        label += f" ({args.select.upper()} selection)"
    plot_frf(
        drawn,
        ax=axes,
        labels=[label],
        max_points=PLOT_MAX_POINTS,
        title=f"{data.path.name}: F = {data.downsampling_factor}, "
        f"Ts = {seconds(data.sample_time)}, N = {data.n_samples}",
        **extra,
    )
    return png_bytes(fig, dpi=120), None


class _Labelled:
    """A fitted MIMO estimate with the data's column names as channel labels
    (what :func:`lrmfrf.plotting.plot_frf` reads for the panel titles)."""

    def __init__(self, estimator, inputs, outputs):
        for name in ("frequencies_", "frf_", "frf_std_", "valid_",
                     "downsampling_factor_", "sample_time_", "n_samples_"):
            if hasattr(estimator, name):
                setattr(self, name, getattr(estimator, name))
        self.input_labels_ = list(inputs)
        self.output_labels_ = list(outputs)


def _summary_numbers(estimator, table: dict, elapsed: float) -> dict:
    valid = table["valid"]
    freq = np.broadcast_to(table["frequency_hz"], valid.shape)
    magnitude = np.abs(table["real"] + 1j * table["imag"])
    F = estimator.downsampling_factor_
    slow_nyquist = 1.0 / (2.0 * F * estimator.sample_time_)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_std = table["std"] / magnitude
    below = valid & (freq > 0) & (freq <= slow_nyquist) & np.isfinite(rel_std)
    above = valid & (freq > slow_nyquist) & np.isfinite(rel_std)
    candidates = valid & (freq > 0) & np.isfinite(magnitude)
    peak_index = (int(np.argmax(np.where(candidates, magnitude, -np.inf)))
                  if candidates.any() else None)
    peak_entry = (tuple(int(i) for i in np.unravel_index(peak_index, valid.shape)[:-1])
                  if peak_index is not None else ())
    freq, magnitude = freq.ravel(), magnitude.ravel()
    return {
        "peak_entry": peak_entry,
        "n_bins": int(freq.size),
        "n_valid": int(valid.sum()),
        "n_frequencies": int(table["frequency_hz"].size),
        "slow_nyquist_hz": slow_nyquist,
        "fast_nyquist_hz": 1.0 / (2.0 * estimator.sample_time_),
        "resolution_hz": float(table["frequency_hz"][1] - table["frequency_hz"][0])
        if table["frequency_hz"].size > 1 else float("nan"),
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
        "sample_time": data.sample_time,
        "n_samples": data.n_samples,
        "n_slow": data.n_slow,
        "input_file": str(data.path),
        "input_sha256": data.sha256,
        "input_columns": ",".join(data.input_names),
        "output_columns": ",".join(data.output_names),
    }
    meta.update({f"setting_{k}": v for k, v in settings.items()})
    if args.select:
        meta["select"] = args.select
    return meta


def _report_text(args, data, settings, estimator, numbers, messages, plot_note) -> str:
    from .. import __version__

    params = estimator.get_params()
    Ts = data.sample_time
    mimo = np.ndim(estimator.frf_) == 3
    if mimo and numbers["peak_entry"]:
        o, i = numbers["peak_entry"]
        peak_name = f"{data.input_names[i]} -> {data.output_names[o]}"
    else:
        peak_name = ""
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
        "columns: input " + ", ".join(map(repr, data.input_names)) + "; output "
        + ", ".join(map(repr, data.output_names)),
        f"downsampling factor F: {data.downsampling_factor}",
        f"fast sample time: {Ts:g} s (slow sample time "
        f"{Ts * data.downsampling_factor:g} s; {_source(data)})",
        f"method: {args.method} ({type(estimator).__name__})",
        "estimator parameters: "
        + ", ".join(f"{k}={v!r}" for k, v in sorted(params.items())),
        "set on the command line: "
        + (", ".join(f"{k}={v!r}" for k, v in settings.items()) or "nothing"),
    ]
    if args.select:
        best = getattr(estimator, "best_params_", {})
        lines.append(f"selected by {args.select}: "
                     + ", ".join(f"{k}={v!r}" for k, v in sorted(best.items())))
    lines += [
        "",
        "Data checks",
        "-----------",
        *[f"- {check}" for check in data.checks],
        "",
        "Summary",
        "-------",
        f"N = {data.n_samples} fast samples, M = {data.n_slow} slow samples",
        f"frequency grid: {numbers['n_frequencies']} bins from 0 to "
        f"{numbers['fast_nyquist_hz']:.6g} Hz, resolution "
        f"{numbers['resolution_hz']:.6g} Hz",
        f"slow Nyquist frequency: {numbers['slow_nyquist_hz']:.6g} Hz",
        f"valid bins: {numbers['n_valid']} of {numbers['n_bins']}"
        + (" (over all entries)" if mimo else ""),
        f"largest |G|: {numbers['peak_db']:.4g} dB at {numbers['peak_hz']:.6g} Hz"
        + (f" (entry {peak_name})" if mimo else ""),
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
        *(["  MIMO: frf.csv has leading columns output, input (0-based indices: "
           "outputs " + ", ".join(f"{k}={n}" for k, n in enumerate(data.output_names))
           + "; inputs " + ", ".join(f"{k}={n}" for k, n in enumerate(data.input_names))
           + "), one block of rows per entry; frf.npz arrays have shape (n_y, n_u, "
           "n_freq)"] if mimo else []),
        "  (std: standard deviation of the complex estimate; valid = 0 rows are NaN)",
        ("bode.png: an n_y x n_u grid of magnitudes with a +/-2 std band; "
         "dotted line at the slow Nyquist frequency" if mimo else
         "bode.png: magnitude and phase with a +/-2 std band; dotted line at the "
         "slow Nyquist frequency"),
        "",
    ]
    return "\n".join(lines)


def _source(data) -> str:
    return {
        "file": "read from the file",
        "passed": "from --sample-time",
        "passed, agrees with the file": "from --sample-time, agrees with the file",
    }.get(data.sample_time_source, data.sample_time_source)
