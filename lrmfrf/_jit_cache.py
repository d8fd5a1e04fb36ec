"""Numba's on-disk cache for kernels that call kernels of another file.

numba keys a cached kernel on the stamp (modification time and size) of the
file that defines it, and only that file: a kernel of
:mod:`lrmfrf._compiled_uncertainty` that calls (and inlines) the step
functions of :mod:`lrmfrf._compiled`, or reads its ``LANES``, keeps loading
the old machine code after ``_compiled.py`` alone has changed, e.g. after a
``git pull`` in an editable install (numba's known limitation, numba PR
#8396). The stale code silently computes other results, or writes past its
scratch arrays when ``LANES`` grew.

:func:`key_caches_on` closes that gap: it adds a digest of the other files,
read when the module is imported, to the stamp numba writes into and checks
against each kernel's cache index. A process saves its kernels under the
digest of the code it imported and loads only kernels saved under that same
digest, so processes that imported different versions (one started before a
``git pull``, one after) never load each other's machine code, whichever
compiles first; each compiles its own instead.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

__all__ = ["key_caches_on", "source_digest"]


def source_digest(paths) -> str:
    """SHA-256 of the contents of ``paths``, in the given order."""
    digest = hashlib.sha256()
    for path in paths:
        digest.update(Path(path).read_bytes())
    return digest.hexdigest()


def key_caches_on(namespace: dict, dependencies) -> int:
    """Key the on-disk caches of a module's kernels on ``dependencies`` too.

    Parameters
    ----------
    namespace : dict
        A module's ``globals()``; the numba dispatchers with an on-disk cache
        that the module itself defines are keyed (call before any of them
        runs: numba loads a kernel from its cache at the first call).
    dependencies : iterable of str
        The source files whose kernels the module's kernels call.

    Returns
    -------
    int
        The number of kernels keyed (0 without numba's caching, e.g. with
        ``NUMBA_DISABLE_JIT=1``).

    Notes
    -----
    numba checks the stamp of a kernel's file when it loads the kernel's index
    (an index with another stamp counts as empty) and writes it when it saves
    a kernel; the stamp becomes ``(numba's stamp, digest)``. Nothing is
    written at import, so a read-only cache directory changes nothing. An
    index saved by an older lrmfrf (numba's stamp alone) is compiled again
    once.
    """
    dependencies = list(dependencies)
    digest = None
    keyed = 0
    for value in namespace.values():
        py_func = getattr(value, "py_func", None)
        cache_file = getattr(getattr(value, "_cache", None), "_cache_file", None)
        if (py_func is None or cache_file is None
                or py_func.__module__ != namespace.get("__name__")):
            continue  # not a cached kernel of this module
        if digest is None:
            digest = source_digest(dependencies)
        stamp = cache_file._source_stamp
        if not (isinstance(stamp, tuple) and stamp[:1] == ("lrmfrf-deps",)):
            cache_file._source_stamp = ("lrmfrf-deps", stamp, digest)
        keyed += 1
    return keyed
