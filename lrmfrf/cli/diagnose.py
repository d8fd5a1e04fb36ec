"""``lrmfrf diagnose``: find what a plant model misses, given measured data.

The report, its JSON twin and the figure are computed first and then written
together with :func:`lrmfrf.io.atomic_group` (all or nothing).
"""

from __future__ import annotations

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
        "missing_mode, mode_shift), add them and report the gap before and after. "
        "The model is a Python file that defines `plant` (and optionally "
        "`controller`, for closed-loop data P/(1+CP)); the file is executed, so "
        "only pass files you trust. Writes diagnosis.txt, diagnosis.json and "
        "diagnosis.png into --out (all or nothing).",
    )
    diag.add_argument("model", type=Path, metavar="MODEL.py",
                      help="Python file defining `plant` (and `controller`)")
    diag.add_argument("data", type=Path, metavar="DATA",
                      help=".csv (header row), .npz or .mat file")
    diag.add_argument("--out", type=output_folder, required=True, metavar="DIR",
                      help="output folder (created if needed)")
    add_data_options(diag, several=False,
                     sample_time_else=", else the dt of a discrete-time plant")
    diag.add_argument("--open-loop", action="store_true",
                      help="ignore `controller`: the data are the plant itself")
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

    for option, text in (("--input-column", args.input_column),
                         ("--output-column", args.output_column)):
        if "," in text:
            raise CLIUsageError(
                f"{option} {text!r} names several channels, but diagnose compares "
                "one input with one output. Pass one column name each"
            )
    plant, controller = load_model(args.model, args.open_loop)
    data = read_data(args.data, args)
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
    summary = report.summary()
    files = [summary.encode("utf-8"),
             json.dumps(report.to_dict(), indent=1).encode("utf-8")]
    if not args.no_plot:
        files.append(_figure_png(report))
    with atomic_group(overwrite=args.force, protect=protect) as group:
        for path, content in zip(outputs, files, strict=False):
            group.write_bytes(path, content)
    if not args.quiet:
        say(summary)
    return 0


def _diagnose_keywords(args, data, plant, controller) -> dict:
    """``diagnose``'s keywords: the seed, the smoothing width and the sample
    time (from the file, else from the model's or the controller's ``dt``)."""
    keywords = {"rng": args.seed}
    if args.smoothing_bins is not None:
        keywords["smoothing_bins"] = args.smoothing_bins
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


def _figure_png(report) -> bytes:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    figure, _ = report.plot()
    try:
        return png_bytes(figure, dpi=110)
    finally:
        plt.close(figure)
