"""Optional progress bars for long loops (tqdm, if installed).

Library functions keep progress bars off by default (``verbose=False``); the
command line turns them on when its standard error is a terminal. Without
tqdm (``pip install "lrmfrf[progress]"``) the loop runs unchanged.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterable, Iterator
from typing import TypeVar

__all__ = ["progress", "progress_enabled"]

logger = logging.getLogger(__name__)

T = TypeVar("T")


def progress_enabled(enabled: bool | None = None, *, stream=None) -> bool:
    """Resolve an ``enabled`` setting: ``None`` means "if ``stream`` is a terminal".

    Parameters
    ----------
    enabled : bool or None, default=None
        ``True``/``False`` are returned unchanged; ``None`` asks the stream.
    stream : file-like, optional
        Stream the bar would write to; default ``sys.stderr``.

    Returns
    -------
    bool
    """
    if enabled is not None:
        return bool(enabled)
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty()) if callable(isatty) else False
    except (ValueError, OSError):  # closed or detached stream
        return False


def progress(
    iterable: Iterable[T],
    *,
    enabled: bool | None,
    total: int | None = None,
    desc: str | None = None,
    **tqdm_kwargs,
) -> Iterable[T] | Iterator[T]:
    """Wrap ``iterable`` in a tqdm progress bar when enabled and available.

    Parameters
    ----------
    iterable : iterable
        The loop to report on; it is iterated exactly once, unchanged.
    enabled : bool or None
        ``False`` returns ``iterable`` itself; ``True`` shows a bar on
        standard error; ``None`` shows one only if standard error is a
        terminal.
    total : int, optional
        Number of items, for iterables without ``len``.
    desc : str, optional
        Label in front of the bar.
    **tqdm_kwargs
        Passed to ``tqdm.tqdm`` (e.g. ``leave=False``, ``unit="file"``).

    Returns
    -------
    iterable
        A ``tqdm`` iterator, or ``iterable`` itself when the bar is disabled or
        tqdm is not installed.

    Examples
    --------
    >>> from lrmfrf.progress import progress
    >>> sum(progress(range(4), enabled=False))
    6
    """
    if not progress_enabled(enabled):
        return iterable
    try:
        from tqdm import tqdm
    except ImportError:
        logger.debug("tqdm is not installed; running without a progress bar")
        return iterable
    return tqdm(iterable, total=total, desc=desc, **tqdm_kwargs)
