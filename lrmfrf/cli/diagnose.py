"""``lrmfrf diagnose``: find what a plant model misses, given measured data.

The report, its JSON twin and the figure are computed first and then written
together with :func:`lrmfrf.io.atomic_group` (all or nothing).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from ._common import (
    CLIError,
    CLIUsageError,
    add_common,
    add_data_options,
    check_out_folder,
    nonnegative_int,
    one_line,
    output_folder,
    png_bytes,
    positive_int,
    read_data,
    say,
)

__all__ = ["DIAGNOSE_OUTPUTS", "add_parser", "run"]

DIAGNOSE_OUTPUTS = ("diagnosis.txt", "diagnosis.json", "diagnosis.png")


def add_parser(sub) -> None:
    """Add the ``diagnose`` subcommand to ``sub``."""
    diag = sub.add_parser(
        "diagnose",
        help="find what a plant model misses, given measured data",
        description="Compare a python-control plant model with a measured "
        "beyond-Nyquist FRF, name the missing effects (gain, delay, low_pass, "
        "missing_mode, mode_shift; MIMO also per channel: input_gain, "
        "output_gain, input_low_pass, input_delay), add them and report the gap before and "
        "after. "
        "The model is a Python file that defines `plant` (and optionally "
        "`controller`, for closed-loop data P/(1+CP)); the file is executed, so "
        "only pass files you trust. MIMO: name one data column per plant input "
        "and per plant output, in the plant's order, e.g. '--input-column u1,u2 "
        "--output-column y1,y2' for a plant with 2 outputs and 2 inputs; the "
        "controller then has the plant's inputs as outputs and its outputs as "
        "inputs (u = r - C y, closed loop P (I + C P)^-1), and all entries are "
        "compared together. Writes diagnosis.txt, diagnosis.json and "
        "diagnosis.png (MIMO: a Bode grid of all entries) into --out (all or "
        "nothing).",
    )
    diag.add_argument("model", type=Path, metavar="MODEL.py",
                      help="Python file defining `plant` (and `controller`), "
                      "SISO or MIMO python-control models")
    diag.add_argument("data", type=Path, metavar="DATA",
                      help=".csv (header row), .npz or .mat file")
    diag.add_argument("--out", type=output_folder, required=True, metavar="DIR",
                      help="output folder (created if needed)")
    add_data_options(diag, several=False, channels=True,
                     sample_time_else=", else the dt of a discrete-time plant")
    diag.add_argument("--open-loop", action="store_true",
                      help="ignore `controller`: the data are the plant itself")
    diag.add_argument("--steady-state", action="store_true",
                      help="the records are the periodic steady state of "
                      "periodic inputs (transient periods discarded), not a "
                      "start from rest: calibrate them the same way (a stable "
                      "measured system is needed)")
    diag.add_argument("--seed", type=nonnegative_int, default=0,
                      help="seed (rng) of the calibration simulations (default 0)")
    diag.add_argument("--smoothing-bins", type=positive_int, default=None,
                      metavar="N",
                      help="width in bins of the smoothing of the discrepancy "
                      "(default: diagnose's)")
    diag.add_argument("--no-plot", action="store_true",
                      help="do not draw diagnosis.png")
    add_common(diag)
    diag.set_defaults(handler=run)


def load_model(path: Path, open_loop: bool):
    """Run the user's model file and return ``(plant, controller)``."""
    import runpy

    if not path.is_file():
        raise CLIError(f"{path}: model file not found. Pass a .py file that "
                       "defines `plant`.")
    try:
        namespace = runpy.run_path(str(path))
    except Exception as exc:
        raise CLIError(
            f"{path}: the model file failed to run: {one_line(exc)}. Fix the "
            "file (run it with python to see the traceback)."
        ) from exc
    if "plant" not in namespace:
        raise CLIError(f"{path}: the model file defines no `plant`. Assign the "
                       "python-control plant model to a variable named plant.")
    controller = None if open_loop else namespace.get("controller")
    return namespace["plant"], controller


def run(args, parser) -> int:
    """Run ``lrmfrf diagnose``."""
    from ..discrepancy import diagnose
    from ..io import atomic_group, check_output_path

    plant, controller = load_model(args.model, args.open_loop)
    data = read_data(args.data, args)
    _check_dimensions(args, data, plant, controller)
    check_out_folder(args.out)
    protect = [args.data, args.model]
    outputs = [args.out / name for name in DIAGNOSE_OUTPUTS]
    for path in outputs:
        check_output_path(path, overwrite=args.force, protect=protect)
    keywords = _diagnose_keywords(args, data, plant, controller)
    try:
        report = diagnose(plant, data.u_h, data.y_l, data.downsampling_factor,
                          controller=controller, **keywords)
    except (ValueError, TypeError) as exc:
        raise CLIError(f"{args.data}: {one_line(exc)}") from exc
    if _is_mimo(data):
        report = _with_column_names(report, data)
    summary, content = report.summary(), report.to_dict()
    if _is_mimo(data):
        summary, content = _with_channels(summary, content, data)
    files = [summary.encode("utf-8"),
             json.dumps(content, indent=1).encode("utf-8")]
    if not args.no_plot:
        files.append(_figure_png(report, data))
    with atomic_group(overwrite=args.force, protect=protect) as group:
        for path, content in zip(outputs, files, strict=False):
            group.write_bytes(path, content)
    if not args.quiet:
        say(summary)
    return 0


def _channels(data) -> tuple[int, int]:
    """The data's ``(n_y, n_u)``: how many output and input columns."""
    return len(data.output_names), len(data.input_names)


def _is_mimo(data) -> bool:
    return _channels(data) != (1, 1)


def _count(number: int, what: str) -> str:
    return f"{number} {what}" + ("" if number == 1 else "s")


def _model_channels(model) -> tuple[int, int] | None:
    """A python-control model's ``(outputs, inputs)``, None for other objects
    (``diagnose`` refuses those with its own message)."""
    outputs, inputs = (getattr(model, name, None) for name in ("noutputs", "ninputs"))
    if isinstance(outputs, int) and isinstance(inputs, int):
        return outputs, inputs
    return None


def _check_dimensions(args, data, plant, controller) -> None:
    """The plant must have one output per output column and one input per
    input column; the controller the plant's inputs as outputs and its
    outputs as inputs (u = r - C y)."""
    n_y, n_u = _channels(data)
    shape = _model_channels(plant)
    if shape is not None and shape != (n_y, n_u):
        columns = (f"--output-column {','.join(data.output_names)!r} and "
                   f"--input-column {','.join(data.input_names)!r}")
        example = " ".join(
            f"{option} {','.join(f'{prefix}{k + 1}' for k in range(count))}"
            for option, prefix, count in (("--output-column", "y", shape[0]),
                                          ("--input-column", "u", shape[1])))
        raise CLIUsageError(
            f"{args.model}: `plant` has {_count(shape[0], 'output')} and "
            f"{_count(shape[1], 'input')}, but {columns} name "
            f"{_count(n_y, 'output column')} and {_count(n_u, 'input column')}. "
            "Name one column per plant output and input, comma separated in the "
            f"plant's order (e.g. {example}), or use a plant with "
            f"{_count(n_y, 'output')} and {_count(n_u, 'input')}"
        )
    if controller is None or shape is None:
        return
    given = _model_channels(controller)
    if given is not None and given != (shape[1], shape[0]):
        raise CLIError(
            f"{args.model}: `controller` has {_count(given[0], 'output')} and "
            f"{_count(given[1], 'input')}, but with a plant of "
            f"{_count(shape[0], 'output')} and {_count(shape[1], 'input')} it must "
            f"have {_count(shape[1], 'output')} (the plant's inputs) and "
            f"{_count(shape[0], 'input')} (the plant's outputs): u = r - C y. Fix "
            "`controller` in the model file, or pass --open-loop if the data are "
            "the plant's own (no feedback)."
        )


def _with_channels(summary: str, content: dict, data) -> tuple[str, dict]:
    """Name the data's columns in a MIMO report: a line after the summary's
    ``compared:`` line, and ``output_columns``/``input_columns`` in the JSON."""
    n_y, n_u = _channels(data)
    line = (f"  entries: {_count(n_y, 'output')} x {_count(n_u, 'input')}, "
            "outputs " + ", ".join(f"{k}={name}" for k, name in
                                   enumerate(data.output_names))
            + "; inputs " + ", ".join(f"{k}={name}" for k, name in
                                      enumerate(data.input_names))
            + "; gaps and tests over all entries together")
    lines = summary.split("\n")
    lines.insert(min(2, len(lines)), line)
    content = {**content, "n_outputs": n_y, "n_inputs": n_u,
               "output_columns": list(data.output_names),
               "input_columns": list(data.input_names)}
    return "\n".join(lines), content


def _with_column_names(report, data):
    """The report with each per-channel finding naming its data column.

    The library names input ``j`` ``u{j}`` and output ``i`` ``y{i}``
    (0-based), which a file's columns need not match: with columns ``u1,u2``
    the library's ``u1`` is column ``u2``. Findings whose parameters hold an
    ``input`` or ``output`` index get ``(input 1 is data column 'u2')`` after
    their description (text and JSON).
    """
    findings = list(getattr(report, "findings", []))
    named = [_finding_with_column_names(finding, data) for finding in findings]
    if all(new is old for new, old in zip(named, findings, strict=True)):
        return report
    return dataclasses.replace(report, findings=named)


def _finding_with_column_names(finding, data):
    notes = []
    for side, names in (("output", data.output_names), ("input", data.input_names)):
        index = finding.parameters.get(side)
        if isinstance(index, int) and 0 <= index < len(names):
            notes.append(f"{side} {index} is data column {names[index]!r}")
    if not notes:
        return finding
    return dataclasses.replace(
        finding, description=f"{finding.description} ({'; '.join(notes)})")


def _diagnose_keywords(args, data, plant, controller) -> dict:
    """``diagnose``'s keywords: the seed, the smoothing width, steady state
    (only when asked) and the sample time (from the file, else from the
    model's or the controller's ``dt``)."""
    keywords = {"rng": args.seed}
    if args.smoothing_bins is not None:
        keywords["smoothing_bins"] = args.smoothing_bins
    if args.steady_state:
        keywords["steady_state"] = True
    sample_time = data.sample_time
    for model in (plant, controller):
        if sample_time is None:
            sample_time = _model_sample_time(model)
    if sample_time is None:
        raise CLIUsageError(
            f"{args.data}: neither the file nor the model ({args.model}) gives "
            "the sample time, so --sample-time is required. Pass --sample-time "
            "SECONDS, or a discrete-time plant (dt > 0)."
        )
    keywords["sample_time"] = sample_time
    return keywords


def _model_sample_time(plant) -> float | None:
    """The ``dt`` of a discrete python-control model, else None."""
    dt = getattr(plant, "dt", None)
    if dt is None or dt is True or isinstance(dt, bool) or not dt > 0:
        return None
    return float(dt)


def _figure_png(report, data) -> bytes:
    """SISO: :meth:`DiagnosisReport.plot`; MIMO: :meth:`DiagnosisReport.plot_grid`
    with the data's column names."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    if _is_mimo(data):
        figure, _ = report.plot_grid(output_labels=data.output_names,
                                     input_labels=data.input_names)
    else:
        figure, _ = report.plot()
    try:
        return png_bytes(figure, dpi=110)
    finally:
        plt.close(figure)
