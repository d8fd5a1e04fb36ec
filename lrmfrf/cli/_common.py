"""What the subcommands share: errors, argument types, options, messages."""

from __future__ import annotations

import argparse
import math
import sys
import warnings
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "PROG",
    "CLIError",
    "CLIUsageError",
    "add_common",
    "add_data_options",
    "one_line",
]

PROG = "lrmfrf"


class CLIError(Exception):
    """A failure reported as one line on standard error (exit status 1)."""

    exit_status = 1


class CLIUsageError(CLIError):
    """A usage error found after parsing (exit status 2, like argparse's)."""

    exit_status = 2


class Parser(argparse.ArgumentParser):
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


positive_int = _number(int, lambda v: v >= 1, "a positive integer")
nonnegative_int = _number(int, lambda v: v >= 0, "an integer >= 0")
positive_float = _number(
    float, lambda v: math.isfinite(v) and v > 0, "a positive number"
)
finite_float = _number(float, math.isfinite, "a finite number")


def downsampling_factor(text: str) -> int:
    """``--F``: the API's rule, integral values such as ``3.0`` read as 3."""
    from .._validation import check_downsampling_factor

    try:
        value = float(text)
        return check_downsampling_factor(value)
    except (TypeError, ValueError, OverflowError):
        raise argparse.ArgumentTypeError(
            f"expected a positive integer, got {text!r}"
        ) from None


downsampling_factor.__name__ = "a positive integer"


def output_folder(text: str) -> Path:
    """``--out``: a folder name; the empty string is refused."""
    if not text.strip():
        raise argparse.ArgumentTypeError(
            f"expected a folder name, got {text!r} (use '.' for the current "
            "folder)"
        )
    return Path(text)


output_folder.__name__ = "a folder name"


def add_common(parser) -> None:
    """``--force``, ``--debug`` and ``--quiet``."""
    parser.add_argument("--force", action="store_true",
                        help="replace existing output files")
    parser.add_argument("--debug", action="store_true",
                        help="show tracebacks and debug logging")
    parser.add_argument("--quiet", action="store_true",
                        help="print nothing but errors (no progress bar, warnings "
                        "or summary)")


def add_data_options(parser, *, several: bool, sample_time_else: str = "",
                     channels: bool = False) -> None:
    """``--F``, ``--sample-time`` and the column options of a data file
    (``several``: of each of several files; ``channels``: the column options
    take comma-separated lists of channels)."""
    files = "each file" if several else "the file"
    parser.add_argument(
        "--F", dest="F", type=downsampling_factor, default=None,
        help="downsampling factor: slow / fast sample time (an integer; 3.0 is "
        f"read as 3). Default: the value {files} stores (.npz/.mat "
        "'downsampling_factor' or 'F'); a value that contradicts the file is "
        "refused")
    parser.add_argument(
        "--sample-time", type=positive_float, default=None, metavar="SECONDS",
        help="fast sample time in seconds, e.g. 0.5e-3. Default: the value "
        f"{files} stores (.npz/.mat 'sample_time', or the step of a CSV time "
        f"column){sample_time_else}; a value that contradicts the file is refused")
    from ..io import DEFAULT_MAX_SAMPLES, TIME_COLUMNS

    columns = parser.add_argument_group("data columns")
    def several_channels(example: str) -> str:
        return (f", or several comma separated (e.g. {example}) for a MIMO "
                "record" if channels else "")

    columns.add_argument("--input-column", default="u", metavar="NAME",
                         help="column (CSV) or variable (.npz, .mat) of the fast "
                         f"input (default u){several_channels('u1,u2')}")
    columns.add_argument("--output-column", default="y", metavar="NAME",
                         help="column or variable of the slow output: M values, "
                         "or a fast-rate column with values every F rows and "
                         f"empty cells between (default y){several_channels('y1,y2')}")
    columns.add_argument("--time-column", default="auto", metavar="NAME",
                         help="CSV column of the time in seconds (ms, us when "
                         "named *_ms, *_us), checked against --sample-time; "
                         "default: the first column named "
                         + ", ".join(sorted(TIME_COLUMNS)) + "; 'none' ignores "
                         "any time column")
    columns.add_argument("--max-samples", type=positive_int,
                         default=DEFAULT_MAX_SAMPLES, metavar="N",
                         help=f"refuse files with more rows (default "
                         f"{DEFAULT_MAX_SAMPLES})")


def read_data(path, args):
    """:func:`lrmfrf.io.read_measurement` with the data options of ``args``."""
    from ..io import read_measurement

    time_column = None if args.time_column.lower() == "none" else args.time_column
    return read_measurement(
        path,
        F=args.F,
        sample_time=args.sample_time,
        input_column=column_names(args.input_column),
        output_column=column_names(args.output_column),
        time_column=time_column,
        max_samples=args.max_samples,
    )


def column_names(text: str):
    """``--input-column``/``--output-column``: one name, or a tuple of names
    when the text is comma separated (``"u1,u2"``; blanks around names are
    dropped)."""
    if "," not in text:
        return text
    names = tuple(name.strip() for name in text.split(","))
    if not all(names):
        raise CLIUsageError(
            f"the column list {text!r} has an empty name. Separate the names by "
            "single commas, e.g. u1,u2"
        )
    return names


def check_out_folder(folder: Path) -> Path:
    """``--out`` must be, or be creatable as, a folder (one-line error)."""
    from ..io import check_output_folder

    try:
        return check_output_folder(folder)
    except ValueError as exc:
        raise CLIError(str(exc)) from None


def say(text: str, *, error: bool = False) -> None:
    """One line on stdout, or on stderr for warnings and errors."""
    print(text, file=sys.stderr if error else sys.stdout)


@contextmanager
def warnings_to_lines(args, collected: list | None = None):
    """Show Python warnings as one ``lrmfrf: warning:`` line each (none with
    ``--quiet``) instead of Python's two-line format with a source line; with
    ``collected``, also append each message (for the reports)."""

    def show(message, category, filename, lineno, file=None, line=None):
        text = " ".join(str(message).split())
        if category is not UserWarning:  # e.g. "RuntimeWarning: overflow ..."
            text = f"{category.__name__}: {text}"
        if collected is not None:
            collected.append(text)
        if not args.quiet:
            say(f"{PROG}: warning: {text}", error=True)

    with warnings.catch_warnings():
        warnings.showwarning = show
        yield


def seconds(value: float) -> str:
    """A time in s, ms or us for titles: ``0.5e-3`` -> ``"0.5 ms"``."""
    for scale, unit in ((1.0, "s"), (1e-3, "ms"), (1e-6, "us")):
        if abs(value) >= 0.1 * scale:
            return f"{value / scale:.4g} {unit}"
    return f"{value:.4g} s"


def one_line(exc) -> str:
    """The message of an exception (or warning) on one line, for stderr."""
    from ..io import OutputExistsError

    if isinstance(exc, OutputExistsError):  # the CLI's words, not the API's
        return (f"{exc.path}: the output file exists already. Pass --force to "
                "replace it, or choose another output folder (--out).")
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


def png_bytes(figure, *, dpi: int) -> bytes:
    """A matplotlib figure as PNG bytes (written later, with the other files)."""
    import io

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()
