"""Numba's on-disk cache for kernels that call kernels of another file.

numba keys a cached kernel on the stamp (modification time and size) of the
file that defines it, and only that file: a kernel of
:mod:`lrmfrf._compiled_uncertainty` that calls (and inlines) the step
functions of :mod:`lrmfrf._compiled`, or reads its ``LANES``, keeps loading
the old machine code after ``_compiled.py`` alone has changed, e.g. after a
``git pull`` in an editable install (numba's known limitation, numba PR
#8396). The stale code silently computes other results, or writes past its
scratch arrays when ``LANES`` grew.

:func:`drop_stale_caches` closes that gap: a module whose kernels call
another file's kernels records a digest of those files next to its cache and
empties its kernels' cache indexes (numba then compiles and caches them
again) whenever the digest changes.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

logger = logging.getLogger(__name__)

__all__ = ["drop_stale_caches", "source_digest"]


def source_digest(paths) -> str:
    """SHA-256 of the contents of ``paths``, in the given order."""
    digest = hashlib.sha256()
    for path in paths:
        digest.update(Path(path).read_bytes())
    return digest.hexdigest()


def drop_stale_caches(namespace: dict, module_file: str, dependencies) -> bool:
    """Empty the cache indexes of the cached kernels in ``namespace`` when
    the files in ``dependencies`` changed since they were cached.

    Parameters
    ----------
    namespace : dict
        A module's ``globals()``; its numba dispatchers with an on-disk cache
        are checked (call before any of them runs: numba loads a kernel from
        its cache at the first call).
    module_file : str
        The module's ``__file__`` (names the digest file).
    dependencies : iterable of str
        The source files whose kernels the module's kernels call.

    Returns
    -------
    bool
        Whether the caches were emptied (a changed or missing digest).
    """
    caches = [d._cache for d in namespace.values()
              if getattr(d, "py_func", None) is not None
              and hasattr(getattr(d, "_cache", None), "cache_path")]
    if not caches:
        return False
    digest = source_digest(dependencies)
    stamp = Path(caches[0].cache_path) / f"{Path(module_file).stem}.deps.sha256"
    try:
        if stamp.is_file() and stamp.read_text().strip() == digest:
            return False
        for cache in caches:
            cache.flush()  # an empty index: compiled and saved again
        stamp.write_text(digest + "\n")
    except OSError as error:  # a read-only cache directory: nothing cached
        logger.debug("numba cache of %s not checked: %s", module_file, error)
        return False
    logger.debug("numba caches of %s emptied: %s changed", module_file,
                 ", ".join(str(path) for path in dependencies))
    return True
