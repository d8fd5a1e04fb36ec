"""FRF curves: every plottable object normalised to frequencies in Hz, FRF, std.

The plotting functions (:mod:`lrmfrf.plotting`) accept fitted estimators,
``control.FrequencyResponseData`` objects, ``(frequencies_hz, frf[, std])``
tuples, and collections of these (several arguments, one list, or one
mapping ``{label: estimate}``); this module turns each into an
:class:`FRFCurve` and evaluates a reference system on a curve's grid. It does
not import matplotlib.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["FRFCurve", "frf_curve"]


@dataclass(frozen=True)
class FRFCurve:
    """One FRF on its frequency grid, as the plots use it.

    Attributes
    ----------
    frequencies : ndarray of shape (n_freq,)
        Frequencies in Hz.
    frf : ndarray of shape (n_freq,), complex
        Invalid bins hold NaN.
    std : ndarray of shape (n_freq,) or None
        Standard deviation of the complex estimate.
    slow_nyquist : float or None
        ``1 / (2 F Ts)`` in Hz when known.
    sample_time : float or None
        Fast sample time in seconds when known.
    n_samples : int or None
        Record length ``N`` when the grid is the fast DFT grid ``k = 0..N//2``.
    """

    frequencies: np.ndarray
    frf: np.ndarray
    std: np.ndarray | None
    slow_nyquist: float | None
    sample_time: float | None
    n_samples: int | None = None


def frf_curve(obj) -> FRFCurve:
    """Convert an estimator, an FRD or a tuple to an :class:`FRFCurve`.

    Parameters
    ----------
    obj : fitted estimator, control.FrequencyResponseData or tuple
        A tuple is ``(frequencies_hz, frf)`` or ``(frequencies_hz, frf, std)``.

    Returns
    -------
    FRFCurve

    Raises
    ------
    TypeError
        For other objects.
    ValueError
        For an unfitted estimator, a MIMO FRD or arrays of different lengths.
    """
    if hasattr(obj, "get_params") and not hasattr(obj, "frf_"):
        raise ValueError(
            f"This {type(obj).__name__} is not fitted. Call fit(u_h, y_l, F) "
            "before plotting it."
        )
    if hasattr(obj, "frf_") and hasattr(obj, "frequencies_"):
        return _estimator_curve(obj)
    if hasattr(obj, "omega") and (hasattr(obj, "frdata") or hasattr(obj, "fresp")):
        return _frd_curve(obj)
    if isinstance(obj, tuple) and len(obj) in (2, 3):
        return _tuple_curve(obj)
    raise TypeError(
        f"Cannot plot an object of type {type(obj).__name__}. Pass a fitted "
        "estimator, a control.FrequencyResponseData or a (frequencies_hz, frf"
        "[, std]) tuple."
    )


def frf_collection(objs: tuple, labels, *, what: str) -> tuple[list, list[str]]:
    """The FRFs to draw and their labels, from a plot function's arguments.

    Parameters
    ----------
    objs : tuple
        The positional FRF arguments: several FRFs, or one list (or tuple) of
        estimators, or one mapping ``{label: FRF}``.
    labels : sequence of str or None
        ``labels=`` of the plot function (not with a mapping, whose keys are
        the labels).
    what : str
        Name of the arguments in messages (``"FRF"``, ``"estimate"``).

    Returns
    -------
    frfs : list
    labels : list of str
        One per FRF; default the class names.

    Raises
    ------
    TypeError
        For a collection passed together with other positional FRFs.
    ValueError
        For no FRF, a mapping together with ``labels``, or a wrong number of
        labels.
    """
    collections = [obj for obj in objs if _is_collection(obj)]
    if collections and len(objs) > 1:
        raise TypeError(
            f"Got a {type(collections[0]).__name__} of {what}s and {len(objs) - 1} "
            f"more positional argument(s). Pass the {what}s either as separate "
            "arguments or as one list or mapping {label: " + what + "}, not both."
        )
    if collections and isinstance(objs[0], Mapping):
        if labels is not None:
            raise ValueError(
                f"A mapping of {what}s takes its labels from its keys; labels= "
                "was given too. Pass either the mapping or labels=, not both."
            )
        labels = [str(key) for key in objs[0]]
        objs = tuple(objs[0].values())
    elif collections:
        objs = tuple(objs[0])
    if not objs:
        raise ValueError(f"Nothing to draw: pass at least one {what}, e.g. a fitted "
                         "estimator.")
    return list(objs), _check_labels(labels, objs)


def _is_frf_object(obj) -> bool:
    """A single FRF that is an object (estimator, FRD), not numbers."""
    return hasattr(obj, "get_params") or hasattr(obj, "frf_") or hasattr(obj, "omega")


def _is_collection(obj) -> bool:
    """A mapping, a list holding FRFs, or a tuple of estimators/FRDs.

    A tuple of arrays is one ``(frequencies, frf[, std])`` curve and a list of
    numbers one array estimate, so neither is a collection; an empty list or
    mapping is one (and refused: nothing to draw).
    """
    if isinstance(obj, Mapping):
        return True
    if isinstance(obj, tuple):
        return len(obj) > 0 and all(_is_frf_object(item) for item in obj)
    if isinstance(obj, list):
        return not obj or any(
            _is_frf_object(item) or isinstance(item, (tuple, np.ndarray))
            for item in obj
        )
    return False


# --------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------


def _check_labels(labels, objs) -> list[str]:
    if labels is None:
        return [_default_label(obj) for obj in objs]
    labels = list(labels)
    if len(labels) != len(objs):
        raise ValueError(
            f"Got {len(labels)} labels for {len(objs)} FRFs. Pass one label per FRF."
        )
    return [str(label) for label in labels]


def _default_label(obj) -> str:
    if isinstance(obj, (tuple, np.ndarray)):
        return "estimate"
    return type(obj).__name__


def _estimator_curve(est) -> FRFCurve:
    frf = np.array(est.frf_, dtype=complex)
    valid = np.asarray(getattr(est, "valid_", np.ones(frf.shape, bool)), dtype=bool)
    frf[~valid] = np.nan
    std = getattr(est, "frf_std_", None)
    std = None if std is None else np.where(valid, np.asarray(std, dtype=float), np.nan)
    F = getattr(est, "downsampling_factor_", None)
    Ts = getattr(est, "sample_time_", None)
    nyquist = 1.0 / (2.0 * F * Ts) if F and Ts else None
    N = getattr(est, "n_samples_", None)
    N = N if N is not None and frf.size == N // 2 + 1 else None
    return FRFCurve(np.asarray(est.frequencies_, float), frf, std, nyquist, Ts, N)


def _frd_curve(frd) -> FRFCurve:
    data = getattr(frd, "frdata", None)
    if data is None:
        data = frd.fresp
    data = np.asarray(data)
    if data.ndim == 3:
        if data.shape[:2] != (1, 1):
            raise ValueError(
                f"Only SISO FRDs can be plotted. Got {data.shape[0]} outputs and "
                f"{data.shape[1]} inputs. Plot one channel, e.g. frd[0, 0]."
            )
        data = data[0, 0]
    dt = getattr(frd, "dt", None)
    numeric = isinstance(dt, (int, float)) and not isinstance(dt, bool)
    Ts = float(dt) if numeric and dt else None
    freq = np.asarray(frd.omega, dtype=float) / (2 * np.pi)
    return FRFCurve(freq, data.astype(complex), None, None, Ts)


def _tuple_curve(obj) -> FRFCurve:
    freq = np.asarray(obj[0], dtype=float)
    frf = np.asarray(obj[1], dtype=complex)
    std = np.asarray(obj[2], dtype=float) if len(obj) == 3 else None
    shapes = {a.shape for a in (freq, frf) + (() if std is None else (std,))}
    if len(shapes) != 1 or freq.ndim != 1:
        raise ValueError(
            f"The (frequencies, frf[, std]) arrays must be 1-D of equal length. Got "
            f"shapes {[np.shape(a) for a in obj]}. Pass matching arrays."
        )
    return FRFCurve(freq, frf, std, None, None)


def _estimate_curve(est, frequencies) -> FRFCurve:
    if isinstance(est, np.ndarray) or (
        isinstance(est, Sequence) and not isinstance(est, tuple)
    ):
        if frequencies is None:
            raise ValueError(
                "Array estimates need their frequencies. Pass frequencies= (Hz) "
                "or the fitted estimators themselves."
            )
        return _tuple_curve((frequencies, est))
    return frf_curve(est)


def _is_lti(obj) -> bool:
    return hasattr(obj, "dt") and callable(obj) and not hasattr(obj, "omega")


def _evaluate_lti(system, frequencies: np.ndarray, sample_time) -> np.ndarray:
    if getattr(system, "ninputs", 1) != 1 or getattr(system, "noutputs", 1) != 1:
        raise ValueError(
            "The true system must be SISO. Pass one channel, e.g. system[0, 0]."
        )
    dt = system.dt
    if dt is None or dt == 0 or dt is False:
        points = 2j * np.pi * frequencies
    else:
        step = sample_time if dt is True else float(dt)
        if step is None:
            raise ValueError(
                "The true system has an unspecified sample time (dt=True). Give "
                "it dt in seconds."
            )
        points = np.exp(2j * np.pi * frequencies * step)
    return np.asarray(system(points), dtype=complex).reshape(frequencies.shape)


def _true_curve(true, first: FRFCurve, window=None) -> FRFCurve:
    if _is_lti(true):
        grid = first.frequencies
        positive = grid[grid > 0]
        if window is not None:
            grid = np.union1d(grid, np.linspace(window[0], window[1], 2000))
        elif positive.size:
            dense = np.geomspace(positive.min(), grid.max(), 2000)
            grid = np.union1d(grid, dense)
        return FRFCurve(grid, _evaluate_lti(true, grid, first.sample_time), None,
                        None, first.sample_time)
    if isinstance(true, np.ndarray):
        if true.shape != first.frequencies.shape:
            raise ValueError(
                f"An array `true` must lie on the first FRF's grid of "
                f"{first.frequencies.size} frequencies. Got shape {true.shape}. "
                "Pass the true system (python-control) to evaluate it anywhere."
            )
        return FRFCurve(first.frequencies, true.astype(complex), None, None, None)
    return frf_curve(true)


def _truth_on_grid(G_true, curve: FRFCurve, frequencies) -> np.ndarray:
    if _is_lti(G_true):
        return _evaluate_lti(G_true, curve.frequencies, curve.sample_time)
    truth = np.asarray(G_true, dtype=complex)
    if truth.shape != curve.frf.shape:
        raise ValueError(
            f"G_true has shape {truth.shape} but an estimate has "
            f"{curve.frf.shape[0]} frequencies. Pass the true system "
            "(python-control) to evaluate it on each estimate's grid."
        )
    return truth


def _resolve_slow_nyquist(slow_nyquist, curves) -> float | None:
    if slow_nyquist is False:
        return None
    if slow_nyquist is None or slow_nyquist is True:
        known = [c.slow_nyquist for c in curves if c.slow_nyquist is not None]
        return known[0] if known else None
    value = float(slow_nyquist)
    if not np.isfinite(value) or value <= 0:
        raise ValueError(
            f"slow_nyquist must be a positive frequency in Hz, None or False. Got "
            f"{slow_nyquist!r}."
        )
    return value
