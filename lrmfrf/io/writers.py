"""Writing results safely: atomic files, output-path checks, the FRF table.

Every file goes to a temporary file in the target folder, is flushed and
synced, then moved onto its name with ``os.replace``: a reader never sees a
half-written file. An existing file is kept unless ``overwrite=True``, and a
file listed in ``protect`` (the inputs) is never replaced.

:func:`atomic_group` extends this to several files: they are all written to
temporary files first and moved onto their names only when every one of them
was written, so a failure leaves none of the new files behind.
"""

from __future__ import annotations

import io
import os
import tempfile
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import BinaryIO

import numpy as np

from .readers import CSV_CHUNK_ROWS

__all__ = [
    "FRF_COLUMNS",
    "AtomicGroup",
    "OutputExistsError",
    "atomic_group",
    "atomic_open",
    "check_output_folder",
    "check_output_path",
    "frf_table",
    "write_frf_csv",
    "write_frf_npz",
]

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
        raise OutputExistsError(path)
    return path


class OutputExistsError(FileExistsError):
    """An output file exists and ``overwrite`` is False.

    Parameters
    ----------
    path : Path
        The existing file.
    """

    def __init__(self, path):
        self.path = Path(path)
        super().__init__(
            f"{path}: the output file exists already. Pass --force "
            "(overwrite=True) to replace it, or choose another output folder "
            "(--out)."
        )


def check_output_folder(folder) -> Path:
    """Check that ``folder`` is, or can be created as, a folder; return it.

    Parameters
    ----------
    folder : str or Path
        Output folder; it and its missing parents are created by the writer.

    Raises
    ------
    ValueError
        ``folder`` or one of its parents is an existing file, or ``folder`` is
        the empty string.
    """
    if str(folder) == "":
        raise ValueError(
            "the output folder is the empty string. Name a folder, e.g. "
            "--out results (or '.' for the current folder)."
        )
    folder = Path(folder)
    for candidate in (folder, *folder.parents):
        if candidate.exists():
            if not candidate.is_dir():
                what = ("--out is" if candidate == folder
                        else f"its parent {candidate} is")
                raise ValueError(
                    f"{folder}: {what} a file, not a folder. Choose a folder name "
                    "(--out)."
                )
            break
    return folder


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
        Fitted without ``sample_time``, ``frequencies_`` (and so the column
        ``frequency_hz``) are in cycles per sample: pass ``sample_time``.

    Returns
    -------
    dict of str to ndarray of shape (n_freq,)
        Keys :data:`FRF_COLUMNS`: frequency in Hz, real and imaginary parts,
        magnitude in dB, phase in degrees (wrapped to (-180, 180]), standard
        deviation of the complex estimate, and validity (bool); new arrays,
        not views of the estimator's attributes. For a MIMO
        estimate every column but ``frequency_hz`` has shape ``(n_y, n_u,
        n_freq)``, entry ``[o, i]`` from input ``i`` to output ``o``.
    """
    frf = np.asarray(estimator.frf_, dtype=complex)
    magnitude = np.abs(frf)
    with np.errstate(divide="ignore", invalid="ignore"):
        magnitude_db = 20.0 * np.log10(magnitude)
    # new arrays throughout: a table edited (e.g. masked or converted to
    # other units) must not edit the fitted estimator
    return {
        "frequency_hz": np.array(estimator.frequencies_, dtype=float),
        "real": frf.real.copy(),
        "imag": frf.imag.copy(),
        "magnitude_db": magnitude_db,
        "phase_deg": np.angle(frf, deg=True),
        "std": np.array(estimator.frf_std_, dtype=float),
        "valid": np.array(estimator.valid_, dtype=bool),
    }


def write_frf_csv(
    path,
    table: dict,
    *,
    overwrite: bool = False,
    protect: Iterable = (),
    group: AtomicGroup | None = None,
) -> Path:
    """Write an FRF table (see :func:`frf_table`) as CSV, atomically.

    One header row with :data:`FRF_COLUMNS`, then one row per frequency;
    numbers with 10 significant digits, ``valid`` as 0/1, NaN as ``nan``. A
    MIMO table is written in long form: two more leading columns ``output``
    and ``input`` (0-based channel indices), then the rows of entry ``[0,
    0]``, ``[0, 1]``, ... in that order, each over all frequencies.

    Parameters
    ----------
    path : str or Path
        Target file.
    table : dict
        From :func:`frf_table`.
    overwrite, protect
        See :func:`atomic_open`; ignored when ``group`` is given (the group's
        own apply).
    group : AtomicGroup, optional
        Write as part of an :func:`atomic_group` (the file appears when the
        group commits).

    Returns
    -------
    Path
    """
    return _write(path, _frf_csv, (table,), overwrite, protect, group)


def write_frf_npz(
    path,
    table: dict,
    *,
    metadata: dict | None = None,
    overwrite: bool = False,
    protect: Iterable = (),
    group: AtomicGroup | None = None,
) -> Path:
    """Write an FRF table as ``.npz`` (no pickles), atomically.

    Holds the :data:`FRF_COLUMNS` arrays (``(n_y, n_u, n_freq)`` each but
    ``frequency_hz`` for a MIMO table), the complex ``frf``, and each
    ``metadata`` item as a 0-d array (numbers or strings only), so it loads
    with ``np.load(path, allow_pickle=False)``. Parameters as
    :func:`write_frf_csv`.

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
    return _write(path, _savez, (arrays,), overwrite, protect, group)


def _write(path, writer, args, overwrite, protect, group) -> Path:
    if group is not None:
        return group.write_with(path, writer, *args)
    with atomic_open(path, overwrite=overwrite, protect=protect) as fh:
        writer(fh, *args)
    return Path(path)


def _savez(fh, arrays: dict) -> None:
    np.savez(fh, **arrays)


def _frf_csv(fh, table: dict) -> None:
    frequency = np.asarray(table["frequency_hz"])
    values = [np.asarray(table[name]) for name in FRF_COLUMNS[1:]]
    text = io.TextIOWrapper(fh, encoding="utf-8", newline="")
    mimo = values[0].ndim == 3
    if mimo:
        text.write(",".join(("output", "input", *FRF_COLUMNS)) + "\n")
        entries = list(np.ndindex(values[0].shape[:2]))
    else:
        text.write(",".join(FRF_COLUMNS) + "\n")
        entries = [()]
    n_rows = frequency.size
    for entry in entries:
        for start in range(0, n_rows, CSV_CHUNK_ROWS):
            stop = min(start + CSV_CHUNK_ROWS, n_rows)
            block = [frequency[start:stop].astype(float)]
            block += [col[entry][start:stop].astype(float) for col in values]
            fmt = ["%.10g"] * 6 + ["%d"]
            if mimo:
                block = [np.full(stop - start, e, dtype=float) for e in entry] + block
                fmt = ["%d", "%d"] + fmt
            np.savetxt(text, np.column_stack(block), delimiter=",", fmt=fmt)
    text.flush()
    text.detach()


class AtomicGroup:
    """Several files written all or nothing (see :func:`atomic_group`).

    Parameters
    ----------
    overwrite : bool
        Allow replacing existing files.
    protect : tuple of Path
        Files never to replace.
    """

    def __init__(self, *, overwrite: bool = False, protect: Iterable = ()):
        self.overwrite = overwrite
        self.protect = tuple(protect)
        self._pending: list[tuple[str, Path]] = []
        self._folders: list[Path] = []

    @contextmanager
    def open(self, path) -> Iterator[BinaryIO]:
        """Open ``path`` for binary writing; it appears only at the commit.

        Missing folders on the way are created (and removed again when the
        group fails and they are empty).
        """
        path = check_output_path(path, overwrite=self.overwrite,
                                 protect=self.protect)
        self._make_folder(path.parent)
        fd, tmp_name = tempfile.mkstemp(
            dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"
        )
        self._pending.append((tmp_name, path))
        with os.fdopen(fd, "wb") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp_name, 0o666 & ~_umask())

    def write_bytes(self, path, data: bytes) -> Path:
        """Write ``data`` to ``path`` (at the commit)."""
        with self.open(path) as fh:
            fh.write(data)
        return Path(path)

    def write_with(self, path, writer: Callable, *args, **kwargs) -> Path:
        """Call ``writer(fh, *args, **kwargs)`` on a binary file for ``path``."""
        with self.open(path) as fh:
            writer(fh, *args, **kwargs)
        return Path(path)

    @property
    def paths(self) -> list[Path]:
        """The target paths, in the order they were opened."""
        return [path for _, path in self._pending]

    def commit(self) -> None:
        """Move every temporary file onto its target; undo all on a failure."""
        for _, path in self._pending:
            check_output_path(path, overwrite=self.overwrite, protect=self.protect)
        done: list[tuple[Path, str | None]] = []
        try:
            for tmp_name, path in self._pending:
                backup = _backup(path)
                try:
                    os.replace(tmp_name, path)
                except BaseException:
                    if backup is not None:  # the old file is still in place
                        with suppress(OSError):
                            os.unlink(backup)
                    raise
                done.append((path, backup))
        except BaseException:
            for path, backup in reversed(done):
                with suppress(OSError):
                    if backup is None:
                        os.unlink(path)
                    else:
                        os.replace(backup, path)
            raise
        finally:
            self.discard()
        for _, backup in done:
            if backup is not None:
                with suppress(OSError):
                    os.unlink(backup)

    def discard(self) -> None:
        """Delete the temporary files not moved yet and the folders made."""
        for tmp_name, _ in self._pending:
            with suppress(OSError):
                os.unlink(tmp_name)
        self._pending = [(t, p) for t, p in self._pending if os.path.exists(t)]

    def _remove_folders(self) -> None:
        for folder in reversed(self._folders):
            with suppress(OSError):
                folder.rmdir()  # only when empty
        self._folders = []

    def _make_folder(self, folder: Path) -> None:
        missing = []
        for candidate in (folder, *folder.parents):
            if candidate.exists():
                break
            missing.append(candidate)
        folder.mkdir(parents=True, exist_ok=True)
        self._folders += reversed(missing)


@contextmanager
def atomic_group(*, overwrite: bool = False, protect: Iterable = ()
                 ) -> Iterator[AtomicGroup]:
    """Write several files all or nothing.

    Files opened with ``group.open(path)`` (or written with
    ``group.write_bytes``) go to temporary files; when the ``with`` block ends
    without error they are moved onto their names. If the block raises, or a
    move fails, no target is created or changed (files moved already are
    removed or restored) and folders the group created are removed again
    when empty.

    Parameters
    ----------
    overwrite : bool, default=False
        Allow replacing existing files.
    protect : iterable of str or Path
        Files never to replace (see :func:`check_output_path`).

    Yields
    ------
    AtomicGroup

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from lrmfrf.io import atomic_group
    >>> folder = pathlib.Path(tempfile.mkdtemp()) / "out"
    >>> with atomic_group() as group:
    ...     _ = group.write_bytes(folder / "a.txt", b"a")
    ...     _ = group.write_bytes(folder / "b.txt", b"b")
    >>> sorted(p.name for p in folder.iterdir())
    ['a.txt', 'b.txt']
    """
    group = AtomicGroup(overwrite=overwrite, protect=protect)
    try:
        yield group
        group.commit()
    except BaseException:
        group.discard()
        group._remove_folders()
        raise


# --------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------


def _umask() -> int:
    current = os.umask(0)
    os.umask(current)
    return current


def _backup(path: Path) -> str | None:
    """A hard link (or copy) of an existing ``path`` to restore it; else None."""
    if not path.exists():
        return None
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.",
                                suffix=".bak")
    os.close(fd)
    os.unlink(name)
    try:
        os.link(path, name)
    except OSError:
        import shutil

        shutil.copy2(path, name)
    return name
