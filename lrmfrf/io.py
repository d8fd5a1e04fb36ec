"""Reading measured records and writing results safely.

Reading (:func:`read_measurement`) takes a fast input ``u_h`` and a slow output
``y_l`` from

- **CSV** (``.csv``, ``.txt``): a header row naming the columns (comma,
  semicolon or tab separated; ``#`` comment lines before the header are
  skipped). The slow output is either its own column of ``M`` values (the
  shorter column padded with empty cells) or a fast-rate column that holds
  values only at rows ``m F`` and empty (or ``nan``) cells between them.
- **NumPy** ``.npz``: arrays named like the columns, loaded with
  ``allow_pickle=False`` after their headers were checked (numeric, real,
  1-D or a vector, size within the limit).
- **MATLAB** ``.mat`` (v4 to v7): variables named like the columns, checked
  with :func:`scipy.io.whosmat` (numeric class, vector, size) before they are
  loaded, and checked to be real after.

Every problem raises :class:`DataFileError` (a ``ValueError``) whose message
names the file, the problem and the fix. Inputs are never modified.

Size: CSV files are streamed in chunks of :data:`CSV_CHUNK_ROWS` rows into two
``float64`` columns allocated once (from a count of the file's lines), so the
memory is about 16 bytes per row (the two columns) plus one chunk, and the slow
output at most 8 more per row after the record is complete. Files with more
than ``max_samples`` rows (default :data:`DEFAULT_MAX_SAMPLES`, 20 million)
are refused with a message before they fill memory. ``.npz`` and ``.mat``
sizes are checked from their headers before loading, and the arrays are not
copied again when they are ``float64`` already.

Writing (:func:`atomic_open`, :func:`write_frf_csv`, :func:`write_frf_npz`)
goes to a temporary file in the target folder, then ``os.replace``: a reader
never sees a half-written file, an existing file is kept unless
``overwrite=True``, and a file listed in ``protect`` (the inputs) is never
replaced.
"""

from __future__ import annotations

import csv
import hashlib
import io
import itertools
import logging
import os
import tempfile
import zipfile
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ._validation import check_downsampling_factor

__all__ = [
    "CSV_CHUNK_ROWS",
    "DEFAULT_MAX_SAMPLES",
    "FRF_COLUMNS",
    "SUPPORTED_FORMATS",
    "DataFileError",
    "Measurement",
    "atomic_open",
    "check_output_path",
    "file_sha256",
    "frf_table",
    "read_measurement",
    "write_frf_csv",
    "write_frf_npz",
]

logger = logging.getLogger(__name__)

#: Largest number of samples (CSV rows, array elements) read by default.
DEFAULT_MAX_SAMPLES = 20_000_000

#: CSV rows parsed per chunk.
CSV_CHUNK_ROWS = 65_536

#: File suffixes and the reader used for them.
SUPPORTED_FORMATS = {".csv": "csv", ".txt": "csv", ".npz": "npz", ".mat": "mat"}

#: Columns of the FRF table written by :func:`write_frf_csv`.
FRF_COLUMNS = (
    "frequency_hz",
    "real",
    "imag",
    "magnitude_db",
    "phase_deg",
    "std",
    "valid",
)

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
    input_column, output_column : str
        Names of the input and output columns or variables.
    u_h : ndarray of shape (N,)
        Fast-rate input.
    y_l : ndarray of shape (M,)
        Slow-rate output, ``N = F M``.
    downsampling_factor : int
        ``F``.
    output_layout : str
        ``"slow"`` (a column of ``M`` values) or ``"fast"`` (values at rows
        ``m F`` of a fast-rate column).
    sha256 : str
        SHA-256 of the file's bytes.
    checks : tuple of str
        The data checks performed, in words, for reports.
    """

    path: Path
    file_format: str
    input_column: str
    output_column: str
    u_h: np.ndarray
    y_l: np.ndarray
    downsampling_factor: int
    output_layout: str
    sha256: str
    checks: tuple[str, ...] = field(default_factory=tuple)

    @property
    def n_samples(self) -> int:
        """``N``, fast samples."""
        return int(self.u_h.size)

    @property
    def n_slow(self) -> int:
        """``M``, slow samples."""
        return int(self.y_l.size)


def read_measurement(
    path,
    *,
    F: int,
    input_column: str = "u",
    output_column: str = "y",
    max_samples: int = DEFAULT_MAX_SAMPLES,
) -> Measurement:
    """Read and check a fast input and a slow output from a CSV, NPZ or MAT file.

    Parameters
    ----------
    path : str or Path
        ``.csv``/``.txt``, ``.npz`` or ``.mat`` file (see the module notes).
    F : int
        Downsampling factor: the output is sampled every ``F`` input samples.
    input_column : str, default="u"
        Column (CSV) or variable (NPZ, MAT) holding the fast input.
    output_column : str, default="y"
        Column or variable holding the slow output, either ``M = N/F`` values
        or a fast-rate column with values at rows ``m F`` only.
    max_samples : int, default=DEFAULT_MAX_SAMPLES
        Refuse files with more rows or array elements than this.

    Returns
    -------
    Measurement

    Raises
    ------
    DataFileError
        Missing or unreadable file, unknown format, missing column, empty or
        NaN values, non-numeric cells, lengths that do not match ``F``.

    Examples
    --------
    >>> from importlib.resources import files
    >>> from lrmfrf.io import read_measurement
    >>> data = read_measurement(
    ...     files("lrmfrf") / "data" / "wafer_stage_example.csv", F=3)
    >>> data.u_h.shape, data.y_l.shape
    ((1200,), (400,))
    """
    F = check_downsampling_factor(F)
    path = Path(path)
    if input_column == output_column:
        raise ValueError(
            f"input_column and output_column are both {input_column!r}. Name two "
            "different columns."
        )
    file_format = _check_readable(path)
    if file_format == "csv":
        u_raw, y_raw, where, checks = _read_csv(
            path, input_column, output_column, max_samples
        )
    elif file_format == "npz":
        u_raw, y_raw, where, checks = _read_npz(
            path, input_column, output_column, max_samples
        )
    else:
        u_raw, y_raw, where, checks = _read_mat(
            path, input_column, output_column, max_samples
        )
    u_h = _check_input(path, u_raw, input_column, where, checks)
    y_l, layout = _slow_output(path, y_raw, u_h.size, F, output_column, where, checks)
    checks.append(  # RMS through dot products: no N-sized temporaries
        f"input RMS {np.sqrt(np.dot(u_h, u_h) / u_h.size):.4g}, output RMS "
        f"{np.sqrt(np.dot(y_l, y_l) / y_l.size):.4g}"
    )
    digest = file_sha256(path)
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
    )


def file_sha256(path, *, block_size: int = 2**20) -> str:
    """SHA-256 hex digest of a file, read in blocks (bounded memory)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(block_size), b""):
            digest.update(block)
    return digest.hexdigest()


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------


def check_output_path(path, *, overwrite: bool = False, protect: Iterable = ()) -> Path:
    """Check that ``path`` may be written; return it as a ``Path``.

    Parameters
    ----------
    path : str or Path
        Target file.
    overwrite : bool, default=False
        Allow replacing an existing file.
    protect : iterable of str or Path
        Files that must never be replaced (the inputs), even with
        ``overwrite=True``.

    Raises
    ------
    ValueError
        ``path`` is one of the protected files, or an existing folder.
    FileExistsError
        ``path`` exists and ``overwrite`` is False.
    """
    path = Path(path)
    if not path.exists():
        return path
    for other in protect:
        with suppress(OSError):
            if os.path.samefile(path, other):
                raise ValueError(
                    f"{path}: the output would replace the input file {other}. "
                    "Choose another output folder (--out); inputs are never "
                    "overwritten."
                )
    if path.is_dir():
        raise ValueError(
            f"{path}: an output file name is taken by a folder. Remove the folder "
            "or choose another output folder (--out)."
        )
    if not overwrite:
        raise FileExistsError(
            f"{path}: the output file exists already. Pass --force "
            "(overwrite=True) to replace it, or choose another output folder "
            "(--out)."
        )
    return path


@contextmanager
def atomic_open(
    path, *, overwrite: bool = False, protect: Iterable = ()
) -> Iterator[BinaryIO]:
    """Open ``path`` for binary writing through a temporary file, atomically.

    The data go to a temporary file in the same folder, which is flushed,
    synced and moved onto ``path`` with ``os.replace`` when the ``with`` block
    ends without error; on error it is deleted and ``path`` is untouched.

    Parameters
    ----------
    path : str or Path
        Target file; its folder must exist.
    overwrite : bool, default=False
        Allow replacing an existing file (checked before and after writing).
    protect : iterable of str or Path
        Files never to replace (see :func:`check_output_path`).

    Yields
    ------
    file object
        Binary file open for writing.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from lrmfrf.io import atomic_open
    >>> target = pathlib.Path(tempfile.mkdtemp()) / "hello.txt"
    >>> with atomic_open(target) as fh:
    ...     _ = fh.write(b"hello")
    >>> target.read_bytes()
    b'hello'
    """
    protect = tuple(protect)
    path = check_output_path(path, overwrite=overwrite, protect=protect)
    fd, tmp_name = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"
    )
    try:
        with os.fdopen(fd, "wb") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp_name, 0o666 & ~_umask())
        check_output_path(path, overwrite=overwrite, protect=protect)
        os.replace(tmp_name, path)
    except BaseException:
        with suppress(OSError):
            os.unlink(tmp_name)
        raise


def frf_table(estimator) -> dict[str, np.ndarray]:
    """The columns of the FRF table of a fitted estimator.

    Parameters
    ----------
    estimator : fitted estimator
        With ``frequencies_`` (Hz), ``frf_``, ``frf_std_`` and ``valid_``.

    Returns
    -------
    dict of str to ndarray of shape (n_freq,)
        Keys :data:`FRF_COLUMNS`: frequency in Hz, real and imaginary parts,
        magnitude in dB, phase in degrees (wrapped to (-180, 180]), standard
        deviation of the complex estimate, and validity (bool).
    """
    frf = np.asarray(estimator.frf_, dtype=complex)
    magnitude = np.abs(frf)
    with np.errstate(divide="ignore", invalid="ignore"):
        magnitude_db = 20.0 * np.log10(magnitude)
    return {
        "frequency_hz": np.asarray(estimator.frequencies_, dtype=float),
        "real": frf.real.copy(),
        "imag": frf.imag.copy(),
        "magnitude_db": magnitude_db,
        "phase_deg": np.angle(frf, deg=True),
        "std": np.asarray(estimator.frf_std_, dtype=float),
        "valid": np.asarray(estimator.valid_, dtype=bool),
    }


def write_frf_csv(
    path, table: dict, *, overwrite: bool = False, protect: Iterable = ()
) -> Path:
    """Write an FRF table (see :func:`frf_table`) as CSV, atomically.

    One header row with :data:`FRF_COLUMNS`, then one row per frequency;
    numbers with 10 significant digits, ``valid`` as 0/1, NaN as ``nan``.

    Returns
    -------
    Path
    """
    columns = [np.asarray(table[name]) for name in FRF_COLUMNS]
    n_rows = columns[0].size
    with atomic_open(path, overwrite=overwrite, protect=protect) as fh:
        text = io.TextIOWrapper(fh, encoding="utf-8", newline="")
        text.write(",".join(FRF_COLUMNS) + "\n")
        for start in range(0, n_rows, CSV_CHUNK_ROWS):
            stop = min(start + CSV_CHUNK_ROWS, n_rows)
            block = np.column_stack(
                [col[start:stop].astype(float) for col in columns]
            )
            np.savetxt(
                text, block, delimiter=",", fmt=["%.10g"] * 6 + ["%d"]
            )
        text.flush()
        text.detach()
    return Path(path)


def write_frf_npz(
    path,
    table: dict,
    *,
    metadata: dict | None = None,
    overwrite: bool = False,
    protect: Iterable = (),
) -> Path:
    """Write an FRF table as ``.npz`` (no pickles), atomically.

    Holds the :data:`FRF_COLUMNS` arrays, the complex ``frf``, and each
    ``metadata`` item as a 0-d array (numbers or strings only), so it loads
    with ``np.load(path, allow_pickle=False)``.

    Returns
    -------
    Path
    """
    arrays = {name: np.asarray(table[name]) for name in FRF_COLUMNS}
    arrays["frf"] = arrays["real"] + 1j * arrays["imag"]
    for key, value in (metadata or {}).items():
        if key in arrays:
            raise ValueError(f"metadata key {key!r} clashes with an FRF column.")
        arrays[key] = np.asarray(value if value is not None else "")
        if arrays[key].dtype == object:
            raise TypeError(
                f"metadata[{key!r}] must be a number or a string. Got "
                f"{type(value).__name__}."
            )
    with atomic_open(path, overwrite=overwrite, protect=protect) as fh:
        np.savez(fh, **arrays)
    return Path(path)


# --------------------------------------------------------------------------
# Private helpers: checks shared by the readers
# --------------------------------------------------------------------------


def _umask() -> int:
    current = os.umask(0)
    os.umask(current)
    return current


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
    missing = np.isnan(y_raw)
    fast_layout = F > 1 and y_raw.size == n_fast and n_fast > 1 and missing[1]
    if fast_layout:
        if n_fast % F:
            raise DataFileError(
                path,
                f"the input has N={n_fast} samples, not a multiple of F={F}",
                f"Check --F, or trim the record to {n_fast - n_fast % F} samples",
            )
        on_grid = np.zeros(n_fast, dtype=bool)
        on_grid[::F] = True
        off_values = ~missing & ~on_grid
        if off_values.any():
            first = int(np.flatnonzero(off_values)[0])
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
    present = np.flatnonzero(~missing)
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


def _read_csv(path: Path, input_column: str, output_column: str, max_samples: int):
    checks: list[str] = []
    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            header, delimiter, header_line = _csv_header(path, fh)
            indices = [
                _column_index(path, header, name, option)
                for name, option in (
                    (input_column, "--input-column"),
                    (output_column, "--output-column"),
                )
            ]
            reader = csv.reader(fh, delimiter=delimiter)
            columns = _csv_columns(
                path, reader, indices, header, header_line, max_samples,
                capacity=_count_lines(path),
            )
    except UnicodeDecodeError as exc:
        raise DataFileError(
            path,
            f"is not a UTF-8 text file (undecodable byte at position {exc.start})",
            "Export the data as a UTF-8 CSV, or save them as .npz or .mat",
        ) from exc
    except csv.Error as exc:
        raise DataFileError(
            path, f"is not a valid CSV file ({exc})", "Check the quoting in the file"
        ) from exc
    u_raw, y_raw = columns
    shown = ", ".join(repr(h) for h in header)
    checks.append(
        f"format: CSV, delimiter {delimiter!r}, header line {header_line} with "
        f"columns {shown}"
    )
    checks.append(f"read {u_raw.size} data rows, all cells numeric or empty")

    def where(index: int) -> str:
        return f"line {header_line + 1 + index}"

    return u_raw, y_raw, where, checks


def _csv_header(path: Path, fh) -> tuple[list[str], str, int]:
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


def _count_lines(path: Path, block_size: int = 2**20) -> int:
    """Number of line breaks + 1: an upper bound on the rows (bounded memory)."""
    count = 1
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(block_size), b""):
            count += block.count(b"\n")
    return count


def _csv_columns(path, reader, indices, header, header_line, max_samples, *,
                 capacity: int):
    """Parse the chosen columns, chunk by chunk, into preallocated arrays."""
    size = max(min(capacity, max_samples + 1), 1)
    columns = [np.empty(size) for _ in indices]
    n_rows = 0
    while True:
        rows = list(itertools.islice(reader, CSV_CHUNK_ROWS))
        if not rows:
            break
        if n_rows + len(rows) > max_samples:
            raise DataFileError(
                path,
                f"has more than {max_samples} data rows, the reader's limit "
                "(about 16 bytes of memory per row)",
                "Raise the limit with --max-samples (max_samples=) if memory "
                "allows, or split the record",
            )
        if n_rows + len(rows) > size:  # the file grew while being read
            size = min(2 * (n_rows + len(rows)), max_samples + 1)
            columns = [np.concatenate([c[:n_rows], np.empty(size - n_rows)])
                       for c in columns]
        for column, index in zip(columns, indices, strict=True):
            cells = [row[index] if len(row) > index else "" for row in rows]
            first_line = header_line + 1 + n_rows
            column[n_rows:n_rows + len(rows)] = _parse_cells(
                path, cells, header[index], first_line
            )
        n_rows += len(rows)
    if n_rows == 0:
        raise DataFileError(
            path, "has a header but no data rows", "Write the data below the header"
        )
    columns = [c[:n_rows] for c in columns]
    # Blank lines at the end of the file are not data.
    blank = np.isnan(columns[0]) & np.isnan(columns[1])
    keep = blank.size - int(np.argmax(~blank[::-1])) if (~blank).any() else 0
    return [col[:keep] for col in columns]


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
            f"Store one record per file as a 1-D vector named {name!r}",
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


def _read_npz(path: Path, input_column: str, output_column: str, max_samples: int):
    try:
        with zipfile.ZipFile(path) as archive:
            members = set(archive.namelist())
            names = sorted(m[:-4] for m in members if m.endswith(".npy"))
            for name, option in (
                (input_column, "--input-column"),
                (output_column, "--output-column"),
            ):
                if f"{name}.npy" not in members:
                    raise DataFileError(
                        path,
                        f"no array named {name!r} (the file has "
                        f"{', '.join(map(repr, names)) or 'no arrays'})",
                        f"Pass the right name with {option}, or save the array "
                        f"under that name",
                    )
                with archive.open(f"{name}.npy") as member:
                    shape, dtype = _npy_header(member)
                numeric = (not dtype.hasobject) and (
                    np.issubdtype(dtype, np.number) or dtype.kind == "b"
                )
                _check_array_meta(
                    path, name, shape, str(dtype), numeric, max_samples, "array"
                )
        with np.load(path, allow_pickle=False) as data:
            u_raw = _real_vector(path, data[input_column], input_column, "array")
            y_raw = _real_vector(path, data[output_column], output_column, "array")
    except DataFileError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
        raise DataFileError(
            path,
            f"is not a readable .npz archive ({type(exc).__name__}: {exc})",
            "Save the data with numpy.savez(path, u=u, y=y)",
        ) from exc
    checks = [
        f"format: NumPy .npz loaded with allow_pickle=False, arrays "
        f"{input_column!r} and {output_column!r} numeric, real, 1-D"
    ]
    return u_raw, y_raw, _index_where, checks


def _npy_header(member) -> tuple[tuple[int, ...], np.dtype]:
    version = np.lib.format.read_magic(member)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(member)
    else:
        shape, _, dtype = np.lib.format.read_array_header_2_0(member)
    return tuple(shape), np.dtype(dtype)


def _read_mat(path: Path, input_column: str, output_column: str, max_samples: int):
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
    for name, option in (
        (input_column, "--input-column"),
        (output_column, "--output-column"),
    ):
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
    try:
        data = scipy.io.loadmat(
            path, variable_names=[input_column, output_column], squeeze_me=False
        )
    except Exception as exc:  # pragma: no cover - whosmat read it already
        raise DataFileError(
            path,
            f"could not be loaded ({type(exc).__name__}: {exc})",
            "Save it in MATLAB with save(..., '-v7'), or export CSV or .npz",
        ) from exc
    u_raw = _real_vector(path, data[input_column], input_column, "variable")
    y_raw = _real_vector(path, data[output_column], output_column, "variable")
    checks = [
        f"format: MATLAB .mat, variables {input_column!r} and {output_column!r} "
        "checked (numeric class, real, vector) before use"
    ]
    return u_raw, y_raw, _index_where, checks
