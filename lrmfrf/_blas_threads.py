"""One BLAS thread around the normal-equation solves, shared by all threads.

The many small matrix products of the normal equations are memory-bound, and
threading them on a busy machine costs several times more than it gains, so
the fits run them with BLAS limited to one thread (:func:`single_threaded_blas`).

OpenBLAS on pthreads (the numpy and scipy wheels), MKL and BLIS keep one thread
count for the whole process. A threadpoolctl context per fit saves the count it
finds and puts it back on exit, so two Python threads fitting at once (dask's
threaded scheduler, joblib's threading backend, a ``ThreadPoolExecutor``)
restore each other's values out of order: A limits 2 -> 1, B saves 1, A
restores 2 while B still solves, B restores 1, and BLAS stays on one thread for
the rest of the process. Here the sections are counted process-wide under a
lock instead: the first one in limits BLAS and keeps the original counts, later
ones only count, the last one out restores them, whichever threads these are.

threadpoolctl >= 3.8 lets only one Python thread at a time set a process-wide
OpenBLAS's count (the first to set it, until it clears the claim; other
threads' calls do nothing). The thread that restores may not be the one that
limited, so each limit and restore here gives up the claim it took.

OpenBLAS on its OpenMP layer keeps a count per calling thread: such libraries
are limited and restored by each thread for itself, as threadpoolctl's own
contexts do.

A process forked while other threads are inside keeps only the forking
thread's sections: the others' threads do not exist in the child and would
never leave (its sections would only count, and BLAS would stay on the one
thread or on whatever count the child sets). The child keeps the counts it
inherits (one thread if a section was open) and limits and restores afresh.
"""

from __future__ import annotations

import functools
import os
import threading

__all__ = ["blas_controller", "single_threaded_blas"]

_lock = threading.Lock()
_open_sections: dict = {}  # the sections inside (a token each) -> entering thread
_shared_limiter = None  # the first section's limiter: holds the original counts


def _after_fork_in_child():
    """Drop the sections of the threads a forked child does not have."""
    global _shared_limiter
    try:
        me = threading.get_ident()
        for token in [t for t, ident in _open_sections.items() if ident != me]:
            del _open_sections[token]
        if not _open_sections:
            _shared_limiter = None  # BLAS keeps the counts it has at the fork
    finally:
        _lock.release()


if hasattr(os, "register_at_fork"):  # a fork never copies the lock while held
    os.register_at_fork(before=_lock.acquire, after_in_parent=_lock.release,
                        after_in_child=_after_fork_in_child)


def single_threaded_blas():
    """A context that runs BLAS on one thread, safe to overlap and to nest.

    Entering counts a section; the first section in (over all threads) limits
    the process-wide BLAS libraries to one thread and the last one out restores
    their original counts, also when the block raises. Libraries with a count
    per thread are limited and restored by the entering thread itself.

    Returns
    -------
    context manager

    Examples
    --------
    >>> import numpy as np
    >>> with single_threaded_blas():
    ...     gram = np.ones((3, 2)).T @ np.ones((3, 2))
    """
    return _SingleThreadedBlas()


class _SingleThreadedBlas:
    """The context of :func:`single_threaded_blas` (one per ``with``)."""

    __slots__ = ("_own_limiter", "_token")

    def __enter__(self):
        shared, per_thread = _blas_libraries()
        self._token = _enter_shared(shared)
        try:
            self._own_limiter = (
                per_thread.limit(limits=1, user_api="blas")
                if per_thread.lib_controllers else None
            )
        except BaseException:
            _leave_shared(self._token)
            raise
        return self

    def __exit__(self, exc_type, exc, traceback):
        try:
            if self._own_limiter is not None:
                self._own_limiter.restore_original_limits()
        finally:
            _leave_shared(self._token)
        return False


@functools.lru_cache(maxsize=1)
def blas_controller():
    """The process's :class:`threadpoolctl.ThreadpoolController`, made once:
    ``threadpool_limits`` scans the loaded libraries on every entry, about
    2 ms (threadpoolctl 3.8, 2-core machine), and a fit of N = 1200 enters
    twice: about 4 ms, a tenth of the fit. The BLAS that numpy and scipy use
    are loaded by the time lrmfrf fits anything."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@functools.lru_cache(maxsize=1)
def _blas_libraries():
    """The BLAS controllers split into (process-wide count, count per thread)."""
    blas = blas_controller().select(user_api="blas")
    per_thread = [lib.filepath for lib in blas.lib_controllers
                  if _count_per_thread(lib)]
    shared = [lib.filepath for lib in blas.lib_controllers
              if lib.filepath not in per_thread]
    return blas.select(filepath=shared), blas.select(filepath=per_thread)


def _count_per_thread(lib_controller):
    """Whether a library's thread count belongs to the calling thread: OpenBLAS
    on OpenMP (whose count is each thread's OpenMP setting); the others
    threadpoolctl controls (OpenBLAS on pthreads, MKL, BLIS) share one count."""
    return (lib_controller.internal_api == "openblas"
            and getattr(lib_controller, "threading_layer", None) == "openmp")


def _enter_shared(shared):
    """Count a section in (limiting BLAS if it is the first); returns its token."""
    global _shared_limiter
    token = object()
    with _lock:
        if not _open_sections and shared.lib_controllers:
            limiter = shared.limit(limits=1, user_api="blas")
            try:
                _give_up_openblas_claim()
            except BaseException:
                # no section is counted in: put the counts back now, or BLAS
                # would stay on one thread and the next section would keep
                # that one thread as the "original" count
                limiter.restore_original_limits()
                raise
            _shared_limiter = limiter
        _open_sections[token] = threading.get_ident()
    return token


def _leave_shared(token):
    """Count a section out (restoring BLAS if it is the last); a section a
    forked child dropped (entered by a thread it does not have) counts nothing."""
    global _shared_limiter
    with _lock:
        if _open_sections.pop(token, None) is None:
            return
        if not _open_sections and _shared_limiter is not None:
            limiter, _shared_limiter = _shared_limiter, None
            try:
                limiter.restore_original_limits()
            finally:
                _give_up_openblas_claim()


def _give_up_openblas_claim():
    """Clear the calling thread's claim on OpenBLAS's count (threadpoolctl >= 3.8;
    nothing to do before), so that the thread leaving last can restore it."""
    from threadpoolctl import OpenBLASController

    clear = getattr(OpenBLASController, "clear_controlling_thread", None)
    if clear is not None:
        clear()  # only if this thread holds the claim
