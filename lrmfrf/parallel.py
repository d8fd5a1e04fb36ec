"""Fit one estimator to many independent data sets, in parallel.

:func:`fit_many` fits a clone of an estimator to each of many independent
records (experiments, stage positions, realisations) with joblib. The joblib
backend decides where the work runs:

- ``n_jobs=1`` (or ``None`` outside any joblib context): serially, in-process;
- ``n_jobs=2``, ``-1``: local worker processes (joblib's default "loky");
- a Dask cluster: start a ``distributed.Client`` and select joblib's "dask"
  backend around the call. The same pattern scales out
  ``sklearn.model_selection.GridSearchCV`` and the ``n_jobs`` of
  :class:`~lrmfrf.estimators.selection.LRMBeyondNyquistCV`::

      import dask
      import joblib
      from distributed import Client, LocalCluster

      # Keep glibc's adaptive mmap threshold in the workers (see below).
      unset = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}
      with dask.config.set(unset), LocalCluster(
          n_workers=2, threads_per_worker=1, dashboard_address=None
      ) as cluster, Client(cluster):
          with joblib.parallel_config(backend="dask"):
              fitted = fit_many(LRMBeyondNyquist(), U_records, Y_records, F=3,
                                n_jobs=-1)
              search = GridSearchCV(LRMBeyondNyquist(), grid, cv=KFold(4),
                                    n_jobs=-1).fit(U_list, Y_list, F=3)

  For a remote cluster pass its scheduler address to ``Client(...)`` instead
  of a ``LocalCluster``; the workers need ``lrmfrf`` installed. Dask is an
  optional dependency (``pip install lrmfrf[dask]``).

  **Worker memory setting.** ``distributed`` starts every worker with
  ``MALLOC_TRIM_THRESHOLD_=65536`` (its ``distributed.nanny.pre-spawn-environ``
  configuration). Setting it disables glibc's adaptive mmap threshold, so each
  large temporary array of a fit is a fresh ``mmap`` whose pages fault in
  again; a fit then costs about 2.3x the CPU time (measured at N = 6000:
  0.12 s instead of 0.05 s). Setting the key to ``None`` as above (for
  workers started with ``dask worker``: ``MALLOC_TRIM_THRESHOLD_: null`` under
  ``distributed.nanny.pre-spawn-environ`` in their Dask configuration)
  restores the speed, at the price of workers returning freed memory to the
  operating system less eagerly. ``benchmarks/scaleout.py`` times both.

Each task sends one record pair and returns one fitted estimator (its FRF
arrays are ``O(N)``), so the traffic per task is small compared with the
``O(N p^2)`` work of a fit.
"""

from __future__ import annotations

import numbers
import warnings
from collections.abc import Sequence

import numpy as np
from joblib import Parallel, delayed
from sklearn.base import BaseEstimator, clone

from ._validation import check_bool
from .progress import progress

__all__ = ["fit_many"]


def _fit_one(estimator, u_h, y_l, F, fit_params):
    return estimator.fit(u_h, y_l, F, **fit_params)


def fit_many(
    estimator: BaseEstimator,
    U_records: Sequence,
    Y_records: Sequence,
    F: int,
    *,
    n_jobs: int | None = None,
    backend: str | None = None,
    verbose: bool = False,
    **fit_params,
) -> list:
    """Fit a clone of ``estimator`` to each of many independent data sets.

    Parameters
    ----------
    estimator : estimator
        Unfitted (or fitted: it is cloned) FRF estimator, e.g.
        ``LRMBeyondNyquist(half_window=18)`` or ``LRMBeyondNyquistCV()``.
    U_records : sequence of length R
        Fast inputs. Item ``i`` is anything the estimator's ``fit`` accepts as
        ``u_h``: one record of shape (N_i,) or (n_u, N_i) (channels first),
        or ``P_i`` experiments fitted together (shared system, own
        transients) as a (P_i, n_u, N_i) array or a list of records.
    Y_records : sequence of length R
        Slow outputs matching ``U_records`` item by item.
    F : int
        Downsampling factor (the same for all data sets).
    n_jobs : int or None, default=None
        Parallel jobs (joblib semantics: ``None`` defers to the active
        ``joblib.parallel_config``, else 1; ``-1`` all workers/cores).
    backend : str or None, default=None
        joblib backend ("loky", "threading", "dask", ...). ``None`` uses the
        active ``joblib.parallel_config`` (or loky).
    verbose : bool, default=False
        Show a progress bar over the data sets as their fits finish (as the
        estimators' ``verbose``; see :mod:`lrmfrf.progress`, needs tqdm).
        Integers, joblib's verbosity in earlier releases, are deprecated: ``0``
        means ``False`` and ``> 0`` means ``True``, with a ``FutureWarning``.
    **fit_params
        Passed to each ``fit``, e.g. ``sample_time=0.5e-3``.

    Returns
    -------
    list of length R
        Fitted clones, in the order of the records.

    Examples
    --------
    >>> from scipy.signal import lfilter
    >>> from lrmfrf import LRMBeyondNyquist
    >>> from lrmfrf.parallel import fit_many
    >>> from lrmfrf.signals import multisine
    >>> U = [multisine(600, rng=seed) for seed in range(3)]
    >>> Y = [lfilter([0.2, 0.1], [1.0, -0.5], u)[::3] for u in U]
    >>> fits = fit_many(LRMBeyondNyquist(half_window=9, num_degree=1,
    ...                 transient_degree=1, den_degree=2), U, Y, F=3)
    >>> len(fits), fits[0].frf_.shape
    (3, (301,))
    """
    verbose = _check_verbose(verbose)
    if not hasattr(estimator, "fit") or not hasattr(estimator, "get_params"):
        raise TypeError(
            "`estimator` must be a scikit-learn style estimator with fit and "
            f"get_params, e.g. LRMBeyondNyquist(). Got {type(estimator).__name__}."
        )
    U_records = _as_sequence(U_records, "U_records")
    Y_records = _as_sequence(Y_records, "Y_records")
    if len(U_records) != len(Y_records):
        raise ValueError(
            f"U_records holds {len(U_records)} data set(s) but Y_records holds "
            f"{len(Y_records)}. Pass one output item per input item."
        )
    if len(U_records) == 0:
        raise ValueError(
            "U_records and Y_records are empty. Pass at least one data set."
        )
    tasks = (
        delayed(_fit_one)(clone(estimator), u, y, F, fit_params)
        for u, y in zip(U_records, Y_records, strict=True)
    )
    if not verbose:
        return list(Parallel(n_jobs=n_jobs, backend=backend)(tasks))
    # Results in order as they become available, so the bar advances.
    fits = Parallel(n_jobs=n_jobs, backend=backend, return_as="generator")(tasks)
    return list(progress(fits, enabled=True, total=len(U_records), desc="fits"))


def _check_verbose(verbose) -> bool:
    """``verbose`` as a bool; joblib-style integers are deprecated."""
    if isinstance(verbose, (bool, np.bool_)):
        return bool(verbose)
    if isinstance(verbose, numbers.Integral):
        warnings.warn(
            f"fit_many(verbose={verbose!r}): an integer verbosity (joblib's) is "
            "deprecated and will be refused in the next release; `verbose` is a "
            f"bool that shows a progress bar. Pass verbose={bool(verbose > 0)}.",
            FutureWarning,
            stacklevel=3,
        )
        return bool(verbose > 0)
    return check_bool(verbose, "verbose")  # raises: the common message


def _as_sequence(records, name: str):
    if isinstance(records, (str, bytes)) or not hasattr(records, "__len__"):
        raise TypeError(
            f"`{name}` must be a sequence of records (a list, or an array whose "
            f"first axis indexes the data sets). Got {type(records).__name__}."
        )
    return records
