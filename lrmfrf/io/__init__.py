"""Reading measured records and writing results safely.

- :mod:`lrmfrf.io.readers`: :func:`read_measurement` (CSV through pandas'
  C parser, ``.npz``, ``.mat``), its checks and :class:`DataFileError`.
- :mod:`lrmfrf.io.writers`: :func:`atomic_open`, :func:`atomic_group` (several
  files all or nothing), the output-path checks and the FRF table writers.

Every public name of both modules is importable from ``lrmfrf.io``.
"""

from .readers import (
    CSV_CHUNK_ROWS,
    DEFAULT_MAX_SAMPLES,
    SAMPLE_TIME_RTOL,
    SUPPORTED_FORMATS,
    TIME_COLUMNS,
    DataFileError,
    Measurement,
    file_sha256,
    read_measurement,
)
from .writers import (
    FRF_COLUMNS,
    AtomicGroup,
    OutputExistsError,
    atomic_group,
    atomic_open,
    check_output_folder,
    check_output_path,
    frf_table,
    write_frf_csv,
    write_frf_npz,
)

__all__ = [
    "CSV_CHUNK_ROWS",
    "DEFAULT_MAX_SAMPLES",
    "FRF_COLUMNS",
    "SAMPLE_TIME_RTOL",
    "SUPPORTED_FORMATS",
    "TIME_COLUMNS",
    "AtomicGroup",
    "DataFileError",
    "Measurement",
    "OutputExistsError",
    "atomic_group",
    "atomic_open",
    "check_output_folder",
    "check_output_path",
    "file_sha256",
    "frf_table",
    "read_measurement",
    "write_frf_csv",
    "write_frf_npz",
]
