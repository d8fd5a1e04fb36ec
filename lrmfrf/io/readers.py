"""Reading measured records: CSV, NumPy ``.npz`` and MATLAB ``.mat`` files.

:func:`read_measurement` takes a fast input ``u_h`` and a slow output ``y_l``
from

- **CSV** (``.csv``, ``.txt``): a header row naming the columns (comma,
  semicolon or tab separated; ``#`` comment lines before the header are
  skipped). The slow output is either its own column of ``M`` values (the
  shorter column padded with empty cells) or a fast-rate column that holds
  values only at rows ``m F`` and empty (or ``nan``) cells between them. The
  cells are parsed by pandas' C parser; a block that holds anything but plain
  numbers is parsed again cell by cell, to name the offending cell and line.
- **NumPy** ``.npz``: arrays named like the columns, loaded with
  ``allow_pickle=False`` after their headers were checked (numeric, real,
  1-D or a vector, size within the limit).
- **MATLAB** ``.mat`` (v4 to v7): variables named like the columns, checked
  with :func:`scipy.io.whosmat` (numeric class, vector, size) before they are
  loaded, and checked to be real after.

Several inputs or outputs (MIMO): pass a list of names for ``input_column``
or ``output_column`` (one CSV column or one vector variable each; the
command line takes them comma separated). The record is then channels first,
``u_h`` of shape ``(n_u, N)`` and ``y_l`` of shape ``(n_y, M)``, as the
estimators take one MIMO record; every channel gets the checks of a single
one, and all outputs must share one layout (slow column or fast column with
gaps).

Sample time and downsampling factor stored in the file are read and checked
against the values passed: an ``.npz`` or ``.mat`` file may hold scalars
``sample_time`` (seconds) and ``downsampling_factor`` (or ``F``); a CSV file
may hold a time column (:data:`TIME_COLUMNS`: ``t``, ``time``, ``time_s``,
``time_ms``, ...), whose uniform step is the sample time. A value passed that
contradicts the file is refused; a value not passed is taken from the file.

Every problem raises :class:`DataFileError` (a ``ValueError``) whose message
names the file, the problem and the fix. Inputs are never modified.

Size: CSV files are parsed in blocks of :data:`CSV_CHUNK_ROWS` rows into
``float64`` columns allocated once (from a count of the file's lines), so the
memory is about 8 bytes per row and column read (two, three with a time
column) plus one block. Files with more than ``max_samples`` rows (default
:data:`DEFAULT_MAX_SAMPLES`, 20 million) are refused with a message before
they fill memory. ``.npz`` and ``.mat`` sizes are checked from their headers
before loading, and the arrays are not copied again when they are ``float64``
already.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._validation import check_downsampling_factor, check_sample_time

__all__ = [
    "CSV_CHUNK_ROWS",
    "DEFAULT_MAX_SAMPLES",
    "SAMPLE_TIME_RTOL",
    "SUPPORTED_FORMATS",
    "TIME_COLUMNS",
    "DataFileError",
    "Measurement",
    "file_sha256",
    "read_measurement",
]

logger = logging.getLogger("lrmfrf.io")

#: Largest number of samples (CSV rows, array elements) read by default.
DEFAULT_MAX_SAMPLES = 20_000_000

#: CSV rows parsed per block (and written per block by the writers).
CSV_CHUNK_ROWS = 65_536

#: File suffixes and the reader used for them.
SUPPORTED_FORMATS = {".csv": "csv", ".txt": "csv", ".npz": "npz", ".mat": "mat"}

#: CSV column names (compared without case) read as time, with their unit in
#: seconds: the step of such a column is the fast sample time.
TIME_COLUMNS = {
    "t": 1.0,
    "time": 1.0,
    "t_s": 1.0,
    "time_s": 1.0,
    "t_ms": 1e-3,
    "time_ms": 1e-3,
    "t_us": 1e-6,
    "time_us": 1e-6,
}

#: Relative difference above which a sample time passed and the one stored in
#: the file contradict each other (0.1 %: a time column written with a few
#: digits still agrees, a factor 2 never does).
SAMPLE_TIME_RTOL = 1e-3

#: Largest deviation of one step of a time column from its mean step, relative
#: to the mean step, for the column to count as uniformly sampled.
_TIME_STEP_RTOL = 1e-2

#: Names of the scalars that store the sample time and the downsampling factor
#: in an .npz or .mat file.
_SAMPLE_TIME_KEYS = ("sample_time",)
_FACTOR_KEYS = ("downsampling_factor", "F")

#: Cells pandas reads as missing: empty, and NaN spelled as numpy writes it.
_NA_TEXT = ["", "nan", "NaN", "NAN"]

_MAT_NUMERIC_CLASSES = {
    "double",
    "single",
    "int8",
    "int16",
    "int32",
    "int64",
    "uint8",
    "uint16",
    "uint32",
    "uint64",
}


class DataFileError(ValueError):
    """A data file could not be read or failed a check.

    The message is ``"<file>: <problem>. <fix>"`` on one line.

    Parameters
    ----------
    path : str or Path
        The offending file.
    problem : str
        What is wrong, with the values received.
    fix : str
        What the user can do about it.
    """

    def __init__(self, path, problem: str, fix: str):
        self.path = Path(path)
        self.problem = problem
        self.fix = fix
        super().__init__(f"{path}: {problem}. {fix}")


@dataclass(frozen=True)
class Measurement:
    """One experiment read from a file: fast input, slow output and the checks.

    Attributes
    ----------
    path : Path
        The file read.
    file_format : str
        ``"csv"``, ``"npz"`` or ``"mat"``.
    input_column, output_column : str or tuple of str
        Names of the input and output columns or variables (a tuple when a
        list of names was passed).
    u_h : ndarray of shape (N,) or (n_u, N)
        Fast-rate input; channels first when ``input_column`` is a tuple.
    y_l : ndarray of shape (M,) or (n_y, M)
        Slow-rate output, ``N = F M``; channels first when ``output_column``
        is a tuple.
    downsampling_factor : int
        ``F``, passed or read from the file.
    output_layout : str
        ``"slow"`` (a column of ``M`` values) or ``"fast"`` (values at rows
        ``m F`` of a fast-rate column).
    sha256 : str
        SHA-256 of the file's bytes.
    checks : tuple of str
        The data checks performed, in words, for reports.
    sample_time : float or None
        Fast sample time in seconds, passed or read from the file; None when
        neither gave one.
    sample_time_source : str
        Where ``sample_time`` came from: ``"passed"``, ``"file"`` (or
        ``"passed, agrees with the file"``), or ``""`` when it is None.
    """

    path: Path
    file_format: str
    input_column: str | tuple[str, ...]
    output_column: str | tuple[str, ...]
    u_h: np.ndarray
    y_l: np.ndarray
    downsampling_factor: int
    output_layout: str
    sha256: str
    checks: tuple[str, ...] = field(default_factory=tuple)
    sample_time: float | None = None
    sample_time_source: str = ""

    @property
    def n_samples(self) -> int:
        """``N``, fast samples."""
        return int(self.u_h.shape[-1])

    @property
    def n_slow(self) -> int:
        """``M``, slow samples."""
        return int(self.y_l.shape[-1])

    @property
    def input_names(self) -> tuple[str, ...]:
        """Input column names, one per channel."""
        return _as_names(self.input_column)

    @property
    def output_names(self) -> tuple[str, ...]:
        """Output column names, one per channel."""
        return _as_names(self.output_column)


@dataclass
class _Raw:
    """What a format reader found, before the shared checks."""

    u: list  # one ndarray per input channel
    y: list  # one ndarray per output channel
    where: object
    checks: list
    sample_time: float | None = None
    sample_time_origin: str = ""
    factor: int | None = None
    factor_origin: str = ""
    sha256: str = ""


def read_measurement(
    path,
    *,
    F: int | None = None,
    sample_time: float | None = None,
    input_column: str | Sequence[str] = "u",
    output_column: str | Sequence[str] = "y",
    time_column: str | None = "auto",
    max_samples: int = DEFAULT_MAX_SAMPLES,
) -> Measurement:
    """Read and check a fast input and a slow output from a CSV, NPZ or MAT file.

    Parameters
    ----------
    path : str or Path
        ``.csv``/``.txt``, ``.npz`` or ``.mat`` file (see the module notes).
    F : int, optional
        Downsampling factor: the output is sampled every ``F`` input samples.
        Integral floats (``3.0``) are accepted. When omitted it is read from
        the file (an ``.npz``/``.mat`` scalar ``downsampling_factor`` or
        ``F``); when given and the file stores another, it is refused.
    sample_time : float, optional
        Fast sample time in seconds, checked against the file's (the scalar
        ``sample_time`` of an ``.npz``/``.mat`` file, the step of a CSV time
        column) to within :data:`SAMPLE_TIME_RTOL`. When omitted, the file's
        value (if any) is returned in :attr:`Measurement.sample_time`.
    input_column : str or sequence of str, default="u"
        Column (CSV) or variable (NPZ, MAT) holding the fast input; a list of
        names reads one input channel from each (``u_h`` of shape ``(n_u,
        N)``).
    output_column : str or sequence of str, default="y"
        Column or variable holding the slow output, either ``M = N/F`` values
        or a fast-rate column with values at rows ``m F`` only; a list of
        names reads one output channel from each (``y_l`` of shape ``(n_y,
        M)``, all in the same layout).
    time_column : str or None, default="auto"
        CSV only: the column holding the time of each row, in seconds (or in
        ms, us when its name ends in ``_ms``, ``_us``). ``"auto"`` uses the
        first column named like one of :data:`TIME_COLUMNS`, if any; None
        ignores any time column. It must be uniformly spaced (to 1 % of its
        step).
    max_samples : int, default=DEFAULT_MAX_SAMPLES
        Refuse files with more rows or array elements than this.

    Returns
    -------
    Measurement

    Raises
    ------
    DataFileError
        Missing or unreadable file, unknown format, missing column, empty or
        NaN values, non-numeric cells, lengths that do not match ``F``, a
        time column that is not uniform, an ``F`` or a sample time that
        contradicts the file, no ``F`` passed or stored.

    Examples
    --------
    >>> from importlib.resources import files
    >>> from lrmfrf.io import read_measurement
    >>> data = read_measurement(
    ...     files("lrmfrf") / "data" / "wafer_stage_example.csv", F=3)
    >>> data.u_h.shape, data.y_l.shape, data.sample_time
    ((1200,), (400,), 0.0005)
    """
    if F is not None:
        F = check_downsampling_factor(F)
    if sample_time is not None:
        sample_time = check_sample_time(sample_time)
    path = Path(path)
    inputs = _column_names(input_column, "input_column")
    outputs = _column_names(output_column, "output_column")
    _check_distinct(inputs, outputs)
    if not isinstance(input_column, str):
        input_column = inputs
    if not isinstance(output_column, str):
        output_column = outputs
    file_format = _check_readable(path)
    if file_format == "csv":
        raw = _read_csv(path, inputs, outputs, time_column, max_samples)
    elif file_format == "npz":
        raw = _read_npz(path, inputs, outputs, max_samples)
    else:
        raw = _read_mat(path, inputs, outputs, max_samples)
    checks = raw.checks
    F = _resolve_factor(path, F, raw, checks)
    sample_time, source = _resolve_sample_time(path, sample_time, raw, checks)
    u_h = [_check_input(path, u, name, raw.where, checks)
           for u, name in zip(raw.u, inputs, strict=True)]
    _check_equal_lengths(path, u_h, inputs, "input")
    y_l, layouts = [], []
    for y, name in zip(raw.y, outputs, strict=True):
        y_one, layout = _slow_output(path, y, u_h[0].size, F, name, raw.where,
                                     checks)
        y_l.append(y_one)
        layouts.append(layout)
    if len(set(layouts)) > 1:
        shown = ", ".join(f"{n!r} {lay}" for n, lay in zip(outputs, layouts,
                                                           strict=True))
        raise DataFileError(
            path,
            f"the outputs are stored in different layouts ({shown})",
            "Store every output the same way: all as slow columns of M values, "
            "or all as fast-rate columns with values every F rows",
        )
    layout = layouts[0]
    u_h = u_h[0] if isinstance(input_column, str) else np.stack(u_h)
    y_l = y_l[0] if isinstance(output_column, str) else np.stack(y_l)
    checks.append(f"input RMS {_rms(u_h.ravel()):.4g}, output RMS "
                  f"{_rms(y_l.ravel()):.4g}")
    digest = raw.sha256 or file_sha256(path)
    checks.append(f"file SHA-256 {digest}")
    logger.debug("read %s: N=%d, M=%d, layout=%s", path, u_h.size, y_l.size, layout)
    return Measurement(
        path=path,
        file_format=file_format,
        input_column=input_column,
        output_column=output_column,
        u_h=u_h,
        y_l=y_l,
        downsampling_factor=F,
        output_layout=layout,
        sha256=digest,
        checks=tuple(checks),
        sample_time=sample_time,
        sample_time_source=source,
    )


def _as_names(names) -> tuple[str, ...]:
    return (names,) if isinstance(names, str) else tuple(names)


def _column_names(names, parameter: str) -> tuple[str, ...]:
    """One name, or a non-empty sequence of distinct non-empty names."""
    if isinstance(names, str):
        names = (names,)
        one = True
    else:
        one = False
        try:
            names = tuple(names)
        except TypeError:
            raise TypeError(
                f"{parameter} must be a column name or a list of names. Got "
                f"{type(names).__name__}."
            ) from None
    if not names:
        raise ValueError(f"{parameter} is an empty list. Name at least one column.")
    for name in names:
        if not isinstance(name, str) or not name.strip():
            raise ValueError(
                f"{parameter} holds {name!r}, not a column name. Pass non-empty "
                "strings" + ("" if one else " (e.g. ['u1', 'u2'])") + "."
            )
    if len(set(names)) < len(names):
        raise ValueError(
            f"{parameter} names a column twice ({', '.join(map(repr, names))}). "
            "Name each channel once."
        )
    return names


def _check_distinct(inputs, outputs) -> None:
    both = [name for name in inputs if name in outputs]
    if both:
        raise ValueError(
            f"input_column and output_column are both {both[0]!r}. Name two "
            "different columns."
        )


def _check_equal_lengths(path, arrays, names, kind) -> None:
    sizes = [a.size for a in arrays]
    if len(set(sizes)) > 1:
        shown = ", ".join(f"{n!r} {s}" for n, s in zip(names, sizes, strict=True))
        raise DataFileError(
            path,
            f"the {kind} channels have different lengths ({shown} samples)",
            f"Every {kind} channel of one record must have the same length",
        )


def _rms(x: np.ndarray) -> float:
    """Root mean square through a dot product (no N-sized temporary), scaled
    first only when the squares overflow (|x| beyond about 1e154)."""
    with np.errstate(over="ignore", invalid="ignore"):
        square = np.dot(x, x)
    if np.isfinite(square):
        return float(np.sqrt(square / x.size))
    scale = max(float(np.max(x)), -float(np.min(x)))
    scaled = x / scale
    return scale * float(np.sqrt(np.dot(scaled, scaled) / x.size))


def file_sha256(path, *, block_size: int = 2**20) -> str:
    """SHA-256 hex digest of a file, read in blocks (bounded memory)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(block_size), b""):
            digest.update(block)
    return digest.hexdigest()


# --------------------------------------------------------------------------
# Private helpers: F and the sample time, passed or stored
# --------------------------------------------------------------------------


def _resolve_factor(path, F, raw: _Raw, checks: list) -> int:
    if raw.factor is None:
        if F is None:
            raise DataFileError(
                path,
                "no downsampling factor F was passed and the file stores none "
                f"(no scalar {' or '.join(map(repr, _FACTOR_KEYS))})",
                "Pass F (--F), the ratio of the slow to the fast sample time",
            )
        return F
    if F is None:
        checks.append(f"downsampling factor F={raw.factor} read from "
                      f"{raw.factor_origin}")
        return raw.factor
    if F != raw.factor:
        raise DataFileError(
            path,
            f"F={F} was passed but {raw.factor_origin} says F={raw.factor}",
            "Pass the file's F (or omit --F to use it), or correct the file",
        )
    checks.append(f"downsampling factor F={F} agrees with {raw.factor_origin}")
    return F


def _resolve_sample_time(path, sample_time, raw: _Raw, checks: list):
    stored = raw.sample_time
    if stored is None:
        return sample_time, ("passed" if sample_time is not None else "")
    if sample_time is None:
        checks.append(f"sample time {stored:.6g} s read from {raw.sample_time_origin}")
        return stored, "file"
    if not math.isclose(sample_time, stored, rel_tol=SAMPLE_TIME_RTOL):
        raise DataFileError(
            path,
            f"the sample time {sample_time:g} s was passed but "
            f"{raw.sample_time_origin} says {stored:.6g} s (ratio "
            f"{sample_time / stored:.4g}); every frequency would be off by that "
            "factor",
            "Pass the file's sample time (or omit --sample-time to use it), or "
            "correct the file",
        )
    checks.append(f"sample time {sample_time:g} s agrees with "
                  f"{raw.sample_time_origin} ({stored:.6g} s)")
    return sample_time, "passed, agrees with the file"


def _stored_factor(path, value, origin: str) -> int:
    try:
        return check_downsampling_factor(value)
    except (TypeError, ValueError):
        raise DataFileError(
            path,
            f"{origin} is {value!r}, not a positive integer",
            "Store the downsampling factor as a positive integer, or remove it",
        ) from None


def _stored_sample_time(path, value, origin: str) -> float:
    try:
        return check_sample_time(value)
    except (TypeError, ValueError):
        raise DataFileError(
            path,
            f"{origin} is {value!r}, not a positive number of seconds",
            "Store the fast sample time in seconds, or remove it",
        ) from None


def _check_readable(path: Path) -> str:
    if not path.exists():
        raise DataFileError(
            path, "no such file", "Check the path and the current folder"
        )
    if path.is_dir():
        raise DataFileError(
            path, "is a folder, not a data file", "Pass a .csv, .npz or .mat file"
        )
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_FORMATS:
        raise DataFileError(
            path,
            f"unknown file format {suffix or '(no suffix)'!r}",
            "Save the data as .csv (header row with column names), .npz or .mat",
        )
    if not os.access(path, os.R_OK):
        raise DataFileError(
            path, "cannot be read (permission denied)", "Check the file permissions"
        )
    return SUPPORTED_FORMATS[suffix]


def _check_input(path, u_raw: np.ndarray, name: str, where, checks: list) -> np.ndarray:
    bad = ~np.isfinite(u_raw)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DataFileError(
            path,
            f"input {name!r} has {int(bad.sum())} empty, NaN or inf value(s), the "
            f"first at {where(first)}",
            "The fast input must be complete: fill in or interpolate the missing "
            "samples, or trim the record",
        )
    if u_raw.size < 2:
        raise DataFileError(
            path,
            f"input {name!r} has {u_raw.size} sample(s)",
            "Pass a record with many samples (a multiple of F)",
        )
    if np.ptp(u_raw) == 0:
        raise DataFileError(
            path,
            f"input {name!r} is constant ({u_raw[0]:g}): it excites nothing",
            "Check the column; the input must excite the system (e.g. a "
            "random-phase multisine)",
        )
    checks.append(f"input {name!r}: {u_raw.size} samples, all finite")
    return u_raw


def _slow_output(
    path, y_raw: np.ndarray, n_fast: int, F: int, name: str, where, checks: list
) -> tuple[np.ndarray, str]:
    """Extract ``y_l`` (M,) from a slow column or a fast column with gaps."""
    fast_layout = (F > 1 and y_raw.size == n_fast and n_fast > 1
                   and np.isnan(y_raw[1]))
    if fast_layout:
        if n_fast % F:
            raise DataFileError(
                path,
                f"the input has N={n_fast} samples, not a multiple of F={F}",
                f"Check --F, or trim the record to {n_fast - n_fast % F} samples",
            )
        # Rows between the slow samples, one row of the view per slow sample:
        # no N-sized temporaries.
        off_grid = y_raw.reshape(-1, F)[:, 1:]
        off_values = ~np.isnan(off_grid)
        if off_values.any():
            row, column = np.argwhere(off_values)[0]
            first = int(row) * F + 1 + int(column)
            raise DataFileError(
                path,
                f"output {name!r} is stored at the fast rate but has values "
                f"between the slow samples, the first at {where(first)} (values "
                f"are expected only every F={F} rows, starting at the first)",
                "Check --F; a fully sampled fast output must be downsampled "
                "(keep rows 0, F, 2F, ...) or given as its own column of M values",
            )
        y_l = y_raw[::F]
        bad = ~np.isfinite(y_l)
        if bad.any():
            first = int(np.flatnonzero(bad)[0]) * F
            raise DataFileError(
                path,
                f"output {name!r} has {int(bad.sum())} empty, NaN or inf value(s) "
                f"where slow samples belong (every F={F} rows), the first at "
                f"{where(first)}",
                "The slow output must be complete: fill in the missing samples "
                "or check --F",
            )
        checks.append(
            f"output {name!r}: fast-rate column with slow samples at every "
            f"F={F}-th row, M={y_l.size} samples, empty between them"
        )
        checks.append(f"lengths: N = F*M = {F}*{y_l.size} = {n_fast}")
        return y_l.copy(), "fast"
    present = np.flatnonzero(~np.isnan(y_raw))
    n_used = int(present[-1]) + 1 if present.size else 0
    y_l = y_raw[:n_used]
    padding = y_raw.size - n_used
    bad = ~np.isfinite(y_l)
    if y_l.size == 0:
        raise DataFileError(
            path,
            f"output {name!r} has no values",
            "Fill in the slow output samples",
        )
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DataFileError(
            path,
            f"output {name!r} has {int(bad.sum())} empty, NaN or inf value(s) "
            f"inside the record, the first at {where(first)}",
            "The slow output must be complete: fill in or interpolate the "
            "missing samples",
        )
    M = y_l.size
    if n_fast != F * M:
        hint = ""
        if M == n_fast:
            hint = " (as many values as the input: is it the fast-rate output?)"
        elif n_fast % M == 0:
            hint = f" (N/M = {n_fast // M}: is F={n_fast // M}?)"
        raise DataFileError(
            path,
            f"lengths do not match F={F}: input has N={n_fast} samples and output "
            f"{name!r} M={M}, but N must equal F*M = {F * M}{hint}",
            "Check --F, or trim the records so that N = F*M (the output sample m "
            "is taken at input sample m*F)",
        )
    note = f" ({padding} empty cells after them)" if padding else ""
    checks.append(f"output {name!r}: slow-rate column of M={M} samples{note}")
    checks.append(f"lengths: N = F*M = {F}*{M} = {n_fast}")
    return y_l.copy(), "slow"


# --------------------------------------------------------------------------
# Private helpers: CSV
# --------------------------------------------------------------------------


def _read_csv(path: Path, inputs: tuple, outputs: tuple, time_column,
              max_samples: int) -> _Raw:
    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            header, delimiter, header_line = _csv_header(path, fh)
    except UnicodeDecodeError as exc:
        raise _not_utf8(path, exc) from exc
    indices = [
        _column_index(path, header, name, option)
        for names, option in ((inputs, "--input-column"), (outputs, "--output-column"))
        for name in names
    ]
    n_u, n_y = len(inputs), len(outputs)
    time_index, time_unit = _time_column_index(path, header, time_column, indices)
    if time_index is not None:
        indices.append(time_index)
    n_lines, digest = _scan(path)
    columns = _csv_columns(
        path, header, delimiter, header_line, indices, max_samples,
        capacity=n_lines, n_data=n_u + n_y,
    )
    shown = ", ".join(repr(h) for h in header)
    checks = [
        f"format: CSV, delimiter {delimiter!r}, header line {header_line} with "
        f"columns {shown}",
        f"read {columns[0].size} data rows, all cells numeric or empty",
    ]

    def where(index: int) -> str:
        return f"line {header_line + 1 + index}"

    raw = _Raw(columns[:n_u], columns[n_u:n_u + n_y], where, checks, sha256=digest)
    if time_index is not None:
        name = header[time_index]
        raw.sample_time = _time_step(path, columns[-1] * time_unit, name, where)
        raw.sample_time_origin = f"its time column {name!r}"
    return raw


def _not_utf8(path, exc: UnicodeDecodeError) -> DataFileError:
    byte = exc.object[exc.start:exc.start + 1] if exc.object else b""
    return DataFileError(
        path,
        f"is not a UTF-8 text file (undecodable byte {byte!r})",
        "Export the data as a UTF-8 CSV, or save them as .npz or .mat",
    )


def _csv_header(path: Path, fh) -> tuple[list[str], str, int]:
    import csv

    line_number = 0
    for line in iter(fh.readline, ""):
        line_number += 1
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        delimiter = next((d for d in (",", ";", "\t") if d in line), ",")
        cells = next(csv.reader([line], delimiter=delimiter))
        header = [cell.strip() for cell in cells]
        if all(_is_number(cell) for cell in header):
            raise DataFileError(
                path,
                f"the first row (line {line_number}) holds numbers, not column names",
                "Add a header row naming the columns, e.g. 'u,y'",
            )
        return header, delimiter, line_number
    raise DataFileError(
        path, "is empty (no header row)", "Write a header row and the data rows"
    )


def _column_index(path: Path, header: Sequence[str], name: str, option: str) -> int:
    hits = [i for i, cell in enumerate(header) if cell == name]
    shown = ", ".join(repr(h) for h in header)
    if not hits:
        raise DataFileError(
            path,
            f"no column named {name!r} (the header has {shown})",
            f"Pass the right name with {option}, or rename the column",
        )
    if len(hits) > 1:
        raise DataFileError(
            path,
            f"the header names {len(hits)} columns {name!r}",
            "Give every column a distinct name",
        )
    return hits[0]


def _time_column_index(path, header, time_column, taken):
    """Index and unit (s) of the time column; ``(None, None)`` when none."""
    if time_column is None:
        return None, None
    if time_column == "auto":
        hits = [i for i, cell in enumerate(header)
                if cell.lower() in TIME_COLUMNS and i not in taken]
        if not hits:
            return None, None
        index = hits[0]
    else:
        index = _column_index(path, header, time_column, "--time-column")
        if index in taken:
            raise DataFileError(
                path,
                f"the time column {time_column!r} is also the input or the output",
                "Name a separate time column with --time-column, or none",
            )
    return index, TIME_COLUMNS.get(header[index].lower(), 1.0)


def _time_step(path, time: np.ndarray, name: str, where) -> float:
    """The uniform step of a time column, in seconds."""
    bad = ~np.isfinite(time)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DataFileError(
            path,
            f"time column {name!r} has {int(bad.sum())} empty, NaN or inf "
            f"value(s), the first at {where(first)}",
            "Fill in the time column, or ignore it with --time-column none "
            "(time_column=None)",
        )
    if time.size < 2:
        raise DataFileError(
            path, f"time column {name!r} has fewer than 2 values",
            "Write a record of many samples",
        )
    step = (time[-1] - time[0]) / (time.size - 1)
    steps = np.diff(time)
    worst = float(np.max(np.abs(steps - step))) if step > 0 else math.inf
    if not worst <= _TIME_STEP_RTOL * step:
        first = int(np.argmax(np.abs(steps - step))) if step > 0 else 0
        raise DataFileError(
            path,
            f"time column {name!r} is not uniformly increasing (mean step "
            f"{step:.6g} s, the step from {where(first)} to the next row is "
            f"{float(steps[first]):.6g} s)",
            "The records must be sampled uniformly at the fast rate; write the "
            "time with more digits, or ignore it with --time-column none "
            "(time_column=None)",
        )
    return float(step)


def _count_lines(path: Path, block_size: int = 2**20) -> int:
    """Number of line breaks + 1: an upper bound on the rows (bounded memory)."""
    return _scan(path, block_size)[0]


def _scan(path: Path, block_size: int = 2**20) -> tuple[int, str]:
    """Line breaks + 1 and the SHA-256 of a file, in one pass over its bytes."""
    count = 1
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(block_size), b""):
            count += block.count(b"\n")
            digest.update(block)
    return count, digest.hexdigest()


def _csv_blocks(path, header, delimiter, header_line, indices):
    """pandas' C parser over the data rows, :data:`CSV_CHUNK_ROWS` at a time."""
    import pandas as pd

    return pd.read_csv(
        path,
        sep=delimiter,
        header=None,
        names=list(range(len(header))),
        usecols=sorted(indices),  # other columns are not converted; extra
        index_col=False,  # cells in a row are ignored, as before
        skiprows=header_line,
        skip_blank_lines=False,  # blank rows keep their line numbers
        skipinitialspace=True,
        keep_default_na=False,
        na_values=_NA_TEXT,
        encoding="utf-8-sig",
        engine="c",
        low_memory=False,
        chunksize=CSV_CHUNK_ROWS,
    )


def _csv_columns(path, header, delimiter, header_line, indices, max_samples, *,
                 capacity: int, n_data: int | None = None) -> list[np.ndarray]:
    """Parse the chosen columns, block by block, into preallocated arrays."""
    import pandas as pd

    size = max(min(capacity, max_samples + 1), 1)
    columns = [np.empty(size) for _ in indices]
    n_rows = 0
    try:
        with _csv_blocks(path, header, delimiter, header_line, indices) as blocks:
            for block in blocks:
                n_block = len(block)
                if n_rows + n_block > max_samples:
                    raise DataFileError(
                        path,
                        f"has more than {max_samples} data rows, the reader's "
                        "limit (about 16 bytes of memory per row)",
                        "Raise the limit with --max-samples (max_samples=) if "
                        "memory allows, or split the record",
                    )
                if n_rows + n_block > size:  # the file grew while being read
                    size = min(2 * (n_rows + n_block), max_samples + 1)
                    columns = [np.concatenate([c[:n_rows], np.empty(size - n_rows)])
                               for c in columns]
                for column, index in zip(columns, indices, strict=True):
                    column[n_rows:n_rows + n_block] = _block_values(
                        path, block[index], header[index], header_line + 1 + n_rows
                    )
                n_rows += n_block
    except UnicodeDecodeError as exc:
        raise _not_utf8(path, exc) from exc
    except pd.errors.EmptyDataError:
        n_rows = 0
    except pd.errors.ParserError as exc:
        raise DataFileError(
            path,
            f"is not a valid CSV file ({' '.join(str(exc).split())})",
            "Check the quoting in the file",
        ) from exc
    if n_rows == 0:
        raise DataFileError(
            path, "has a header but no data rows", "Write the data below the header"
        )
    data = columns[:n_data] if n_data is not None else columns[:2]
    keep = _rows_before_blank_tail([c[:n_rows] for c in data])
    return [col[:keep] for col in columns]


def _rows_before_blank_tail(columns: list, block: int = 4096) -> int:
    """Rows up to the last one with an input or output value: blank lines at the
    end of a file are not data (scanned from the end, block by block)."""
    stop = columns[0].size
    while stop > 0:
        start = max(stop - block, 0)
        filled = ~np.logical_and.reduce([np.isnan(c[start:stop]) for c in columns])
        if filled.any():
            return start + int(np.flatnonzero(filled)[-1]) + 1
        stop = start
    return 0


def _block_values(path, cells, name: str, first_line: int) -> np.ndarray:
    """One column of a block as float64; non-numbers are parsed cell by cell."""
    if cells.dtype.kind in "fiu":
        return cells.to_numpy(dtype=np.float64)
    # A cell pandas did not read as a number (text, surrounding blanks, inf,
    # integers beyond 64 bits): parse each as numpy does, to name the bad one.
    text = ["" if _is_missing(cell) else str(cell) for cell in cells.to_numpy(
        dtype=object)]
    return _parse_cells(path, text, name, first_line)


def _is_missing(cell) -> bool:
    return cell is None or (isinstance(cell, float) and math.isnan(cell))


def _parse_cells(path, cells: list[str], name: str, first_line: int) -> np.ndarray:
    text = np.char.strip(np.array(cells, dtype=str))
    # "nan" needs three characters: a column of one-character cells is '<U1'.
    text = np.where(text == "", np.array("nan", dtype="<U3"), text)
    try:
        return text.astype(np.float64)
    except ValueError:
        for offset, cell in enumerate(text):
            if not _is_number(cell, strict=True):
                raise DataFileError(
                    path,
                    f"non-numeric cell {str(cell)[:40]!r} in column {name!r} at "
                    f"line {first_line + offset}",
                    "Use numbers with a decimal point (no units or thousands "
                    "separators); leave missing output samples empty",
                ) from None
        raise  # pragma: no cover - numpy and float() disagree


def _is_number(text: str, *, strict: bool = False) -> bool:
    """Does ``text`` parse as a float (``strict``: as numpy parses it)?"""
    try:
        if strict:
            np.array(text, dtype=str).astype(np.float64)
        else:
            float(text)
    except ValueError:
        return False
    return True



# --------------------------------------------------------------------------
# Private helpers: NPZ and MAT
# --------------------------------------------------------------------------


def _index_where(index: int) -> str:
    return f"index {index}"


def _check_array_meta(path, name, shape, dtype_text, numeric, max_samples, kind):
    size = int(np.prod(shape)) if len(shape) else 1
    if not numeric:
        raise DataFileError(
            path,
            f"{kind} {name!r} is not numeric (type {dtype_text})",
            f"Store {name!r} as a real floating-point vector",
        )
    if sum(dim > 1 for dim in shape) > 1 or size == 0:
        raise DataFileError(
            path,
            f"{kind} {name!r} has shape {tuple(shape)}, not a non-empty vector",
            f"Store one record per file as a 1-D vector named {name!r}; several "
            "channels as one vector each (e.g. 'u1', 'u2'), named with "
            "--input-column u1,u2 (input_column=['u1', 'u2']) or "
            "--output-column",
        )
    if size > max_samples:
        raise DataFileError(
            path,
            f"{kind} {name!r} has {size} elements, more than the limit "
            f"{max_samples}",
            "Raise the limit with --max-samples (max_samples=) if memory "
            "allows, or split the record",
        )


def _real_vector(path, array: np.ndarray, name: str, kind: str) -> np.ndarray:
    if np.iscomplexobj(array):
        raise DataFileError(
            path,
            f"{kind} {name!r} is complex",
            "Store the measured real time samples, not their DFT",
        )
    if not (np.issubdtype(array.dtype, np.number) or array.dtype == bool):
        raise DataFileError(
            path,
            f"{kind} {name!r} is not numeric (dtype {array.dtype})",
            f"Store {name!r} as a real floating-point vector",
        )
    # No copy when the array is float64 already (it is fresh from the file).
    return np.asarray(array, dtype=np.float64).ravel()


def _read_npz(path: Path, inputs: tuple, outputs: tuple, max_samples: int):
    try:
        with zipfile.ZipFile(path) as archive:
            members = set(archive.namelist())
            names = sorted(m[:-4] for m in members if m.endswith(".npy"))
            for group, option in ((inputs, "--input-column"),
                                  (outputs, "--output-column")):
                for name in group:
                    if f"{name}.npy" not in members:
                        raise DataFileError(
                            path,
                            f"no array named {name!r} (the file has "
                            f"{', '.join(map(repr, names)) or 'no arrays'})",
                            f"Pass the right name with {option}, or save the "
                            "array under that name",
                        )
                    with archive.open(f"{name}.npy") as member:
                        shape, dtype = _npy_header(member)
                    numeric = (not dtype.hasobject) and (
                        np.issubdtype(dtype, np.number) or dtype.kind == "b"
                    )
                    _check_array_meta(
                        path, name, shape, str(dtype), numeric, max_samples, "array"
                    )
            scalars = {
                key: _npz_scalar(archive, f"{key}.npy")
                for key in (*_SAMPLE_TIME_KEYS, *_FACTOR_KEYS)
                if f"{key}.npy" in members
            }
        with np.load(path, allow_pickle=False) as data:
            u_raw = [_real_vector(path, data[name], name, "array") for name in inputs]
            y_raw = [_real_vector(path, data[name], name, "array") for name in outputs]
            scalars = {key: data[key] if ok else None
                       for key, ok in scalars.items()}
    except DataFileError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise DataFileError(
            path,
            f"is not a readable .npz archive ({type(exc).__name__}: {exc})",
            "Save the data with numpy.savez(path, u=u, y=y)",
        ) from exc
    shown = " and ".join(", ".join(map(repr, g)) for g in (inputs, outputs))
    checks = [
        f"format: NumPy .npz loaded with allow_pickle=False, arrays {shown} "
        "numeric, real, 1-D"
    ]
    raw = _Raw(u_raw, y_raw, _index_where, checks)
    _stored_scalars(path, raw, scalars, "array")
    return raw


def _npz_scalar(archive, member_name: str) -> bool:
    """Is the archive member a numeric array of one element (checked header)?"""
    with archive.open(member_name) as member:
        shape, dtype = _npy_header(member)
    numeric = (not dtype.hasobject) and np.issubdtype(dtype, np.number)
    return numeric and int(np.prod(shape)) == 1


def _stored_scalars(path, raw: _Raw, scalars: dict, kind: str) -> None:
    """Fill ``raw.sample_time`` and ``raw.factor`` from the file's scalars.

    ``scalars`` maps a key present in the file to its value (None when the
    entry is not a numeric scalar, which is refused).
    """
    for keys, attribute in ((_SAMPLE_TIME_KEYS, "sample_time"),
                            (_FACTOR_KEYS, "factor")):
        found = [key for key in keys if key in scalars]
        if not found:
            continue
        values = {}
        for key in found:
            origin = f"its {kind} {key!r}"
            value = scalars[key]
            if value is None or np.iscomplexobj(value):
                raise DataFileError(
                    path,
                    f"{origin} is not a real number",
                    f"Store {key!r} as one real number, or remove it",
                )
            value = np.asarray(value).reshape(-1)[0].item()
            if attribute == "factor":
                values[key] = _stored_factor(path, value, origin)
            else:
                values[key] = _stored_sample_time(path, value, origin)
        if len(set(values.values())) > 1:
            shown = ", ".join(f"{k}={v!r}" for k, v in values.items())
            raise DataFileError(
                path, f"the file stores contradicting values {shown}",
                "Keep one of them",
            )
        setattr(raw, attribute, values[found[0]])
        setattr(raw, f"{attribute}_origin", f"its {kind} {found[0]!r}")


def _npy_header(member) -> tuple[tuple[int, ...], np.dtype]:
    version = np.lib.format.read_magic(member)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(member)
    else:
        shape, _, dtype = np.lib.format.read_array_header_2_0(member)
    return tuple(shape), np.dtype(dtype)


def _read_mat(path: Path, inputs: tuple, outputs: tuple, max_samples: int):
    import scipy.io

    try:
        contents = {name: (shape, cls) for name, shape, cls in scipy.io.whosmat(path)}
    except NotImplementedError as exc:
        raise DataFileError(
            path,
            "is a MATLAB v7.3 (HDF5) file, which scipy cannot read",
            "Save it in MATLAB with save(..., '-v7'), or export CSV or .npz",
        ) from exc
    except Exception as exc:  # scipy raises many types for foreign files
        raise DataFileError(
            path,
            f"is not a readable MATLAB file ({type(exc).__name__}: {exc})",
            "Save it in MATLAB with save(..., '-v7'), or export CSV or .npz",
        ) from exc
    wanted = [(name, option) for group, option in (
        (inputs, "--input-column"), (outputs, "--output-column")) for name in group]
    for name, option in wanted:
        if name not in contents:
            raise DataFileError(
                path,
                f"no variable named {name!r} (the file has "
                f"{', '.join(map(repr, sorted(contents))) or 'no variables'})",
                f"Pass the right name with {option}, or save the variable under "
                "that name",
            )
        shape, cls = contents[name]
        _check_array_meta(
            path, name, shape, cls, cls in _MAT_NUMERIC_CLASSES, max_samples, "variable"
        )
    stored = [key for key in (*_SAMPLE_TIME_KEYS, *_FACTOR_KEYS) if key in contents]
    try:
        data = scipy.io.loadmat(
            path, variable_names=[*inputs, *outputs, *stored],
            squeeze_me=False,
        )
    except Exception as exc:  # pragma: no cover - whosmat read it already
        raise DataFileError(
            path,
            f"could not be loaded ({type(exc).__name__}: {exc})",
            "Save it in MATLAB with save(..., '-v7'), or export CSV or .npz",
        ) from exc
    u_raw = [_real_vector(path, data[name], name, "variable") for name in inputs]
    y_raw = [_real_vector(path, data[name], name, "variable") for name in outputs]
    shown = " and ".join(", ".join(map(repr, g)) for g in (inputs, outputs))
    checks = [
        f"format: MATLAB .mat, variables {shown} checked (numeric class, real, "
        "vector) before use"
    ]
    raw = _Raw(u_raw, y_raw, _index_where, checks)
    scalars = {
        key: data[key] if contents[key][1] in _MAT_NUMERIC_CLASSES
        and int(np.prod(contents[key][0])) == 1 else None
        for key in stored
    }
    _stored_scalars(path, raw, scalars, "variable")
    return raw
