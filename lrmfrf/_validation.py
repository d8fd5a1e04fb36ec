"""Signal and parameter checks, in one place.

Every check raises a ``ValueError`` or ``TypeError`` whose message names the
problem, what was received and what to do. Inputs are never modified: each
check returns a new array (``np.array(..., copy=True)``) when it converts.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "check_downsampling_factor",
    "check_signal",
    "check_records",
    "parse_record_set",
    "format_like_input",
    "Records",
    "check_record_stack",
    "check_local_degrees",
    "check_nonnegative_int",
    "check_nonnegative_int_or_none",
    "check_positive_float",
    "check_bool",
    "check_siso_system",
    "check_sample_time",
]


def check_nonnegative_int(value, name: str, *, minimum: int = 0) -> int:
    """Return ``value`` as an int, or raise if it is not an integer >= minimum.

    Whole floats (``3.0``) are accepted; ``2.5``, ``True`` and strings are not.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        if isinstance(value, numbers.Real) and float(value).is_integer():
            value = int(value)
        else:
            raise TypeError(
                f"`{name}` must be an integer >= {minimum}. Got {value!r} of type "
                f"{type(value).__name__} instead. Pass a whole number, e.g. "
                f"{name}={max(minimum, 2)}."
            )
    value = int(value)
    if value < minimum:
        raise ValueError(
            f"`{name}` must be an integer >= {minimum}. Got {value} instead. "
            f"Use a value of at least {minimum}."
        )
    return value


def check_nonnegative_int_or_none(value, name: str, *, minimum: int = 0):
    """``None``, or ``value`` checked by :func:`check_nonnegative_int`."""
    if value is None:
        return None
    return check_nonnegative_int(value, name, minimum=minimum)


def check_bool(value, name: str) -> bool:
    """Return ``value`` as a bool; accepts ``True``/``False`` and ``0``/``1``."""
    if isinstance(value, (bool, np.bool_)) or (
        isinstance(value, numbers.Integral) and value in (0, 1)
    ):
        return bool(value)
    raise TypeError(
        f"`{name}` must be True or False. Got {value!r} of type "
        f"{type(value).__name__} instead. Pass {name}=True or {name}=False."
    )


def check_downsampling_factor(F) -> int:
    """Return the downsampling factor as a positive int.

    The one rule for the API and the command line: a number with an integral
    value is accepted (``3``, ``3.0``, ``np.int64(3)``, ``np.float64(3.0)``
    all give ``3``); a non-integral number (``3.5``, NaN, inf), a value below
    1, a bool (``True``) and text (``"3"``) are refused with a message saying
    what to pass.

    Parameters
    ----------
    F : int or float
        The ratio of the slow to the fast sample time.

    Returns
    -------
    int
    """
    if isinstance(F, (bool, np.bool_)) or not isinstance(F, numbers.Real):
        kind = "text" if isinstance(F, (str, bytes)) else type(F).__name__
        raise TypeError(
            f"The downsampling factor F must be a positive integer. Got {F!r} "
            f"({kind}) instead. Pass a number, the ratio of the slow to the fast "
            "sample time, e.g. F=3."
        )
    if not float(F).is_integer() or F < 1:
        raise ValueError(
            f"The downsampling factor F must be a positive integer. Got {F!r} "
            "instead. Pass the integer ratio of the slow to the fast sample time, "
            "e.g. F=3."
        )
    return int(F)


def check_signal(x, name: str, *, purpose: str = "fitting") -> np.ndarray:
    """Return a real, finite, non-empty 1-D float copy of ``x``.

    Parameters
    ----------
    x : array-like of shape (n_samples,)
        The signal.
    name : str
        How the messages call it.
    purpose : str, default="fitting"
        What the signal is for, in the non-finite message ("remove them before
        ``purpose``").

    Returns
    -------
    ndarray of shape (n_samples,), float
    """
    _refuse_masked(x, name)
    try:
        arr = np.array(x, copy=True)
    except Exception as exc:  # pragma: no cover - numpy raises many types
        raise TypeError(f"`{name}` could not be converted to an array: {exc}") from exc
    if arr.dtype.kind in "mM":
        raise TypeError(
            f"`{name}` must hold signal values. Got dtype {arr.dtype} (times or "
            "durations) instead. Pass the measured values; give the sample time "
            "separately (`sample_time`)."
        )
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.number) or arr.dtype == bool
    ):
        raise TypeError(
            f"`{name}` must be a numeric array. Got dtype {arr.dtype} instead. "
            "Convert the signal to floats (check for text cells in the data)."
        )
    if np.iscomplexobj(arr):
        raise TypeError(
            f"`{name}` must be a real time-domain signal. Got a complex array "
            "instead. "
            "Pass the measured time samples, not their DFT."
        )
    if arr.ndim != 1:
        raise ValueError(
            f"`{name}` must be 1-D with shape (n_samples,). Got shape {arr.shape} "
            "instead. "
            "Pass a 1-D record; " + SEVERAL_EXPERIMENTS_HINT
        )
    if arr.size == 0:
        raise ValueError(f"`{name}` is empty. Pass a record with samples.")
    arr = arr.astype(float, copy=False)
    bad = ~np.isfinite(arr)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"`{name}` contains {int(bad.sum())} non-finite value(s) (NaN or inf), "
            f"the first at index {first}. Remove or interpolate them before "
            f"{purpose}."
        )
    return arr


def _refuse_masked(x, name: str) -> None:
    """Masked arrays carry a mask the estimators cannot honour: refuse them."""
    if np.ma.isMaskedArray(x):
        raise TypeError(
            f"`{name}` is a masked array. The estimators need every sample of a "
            "record (a DFT has no notion of missing samples), so a mask cannot be "
            "honoured. Fill or interpolate the masked samples and pass a plain "
            "array, e.g. x.filled(...) or np.ma.getdata(x) if the mask is empty."
        )


def _column_vector_error(name: str, shape) -> ValueError:
    return ValueError(
        f"`{name}` has shape {tuple(shape)}: a column vector, which would be read "
        f"as one record of {shape[0]} channels of one sample each. Pass one record "
        f"as a 1-D array ({name}.ravel()) or channels first, (n_channels, "
        "n_samples), i.e. transpose a (n_samples, n_channels) array; several "
        "experiments go in a list or a 3-D array (n_experiments, n_channels, "
        "n_samples)."
    )


#: Appended to messages about a 2-D record whose shape does not fit.
SEVERAL_EXPERIMENTS_HINT = (
    "A 2-D array is ONE record with channels first, (n_channels, n_samples); "
    "several experiments go in a list of records or a 3-D array "
    "(n_experiments, n_channels, n_samples)."
)

#: The forms in which records can be given (see :class:`Records`).
RECORD_FORMS = ("1d", "2d", "3d", "list")


def _parse_one(x, name: str, purpose: str):
    """One record, 1-D or channels-first 2-D, as a (n_channels, n) float copy."""
    _refuse_masked(x, name)
    try:
        arr = np.array(x, copy=True)
    except Exception as exc:  # pragma: no cover - numpy raises many types
        raise TypeError(f"`{name}` could not be converted to an array: {exc}") from exc
    if arr.ndim == 2:
        if arr.shape[1] == 1 and arr.shape[0] > 1:
            raise _column_vector_error(name, arr.shape)
        several = arr.shape[0] > 1
        rows = [
            check_signal(row, f"{name}[{c}]" if several else name, purpose=purpose)
            for c, row in enumerate(arr)
        ]
        if not rows:
            raise ValueError(f"`{name}` is empty. Pass a record with samples.")
        return np.vstack(rows)
    if arr.ndim != 1:
        raise ValueError(
            f"`{name}` must be one record, 1-D (n_samples,) or 2-D channels first "
            f"(n_channels, n_samples). Got shape {arr.shape} instead. "
            + SEVERAL_EXPERIMENTS_HINT
        )
    return check_signal(arr, name, purpose=purpose)[None, :]


def parse_record_set(x, name: str, *, purpose: str = "fitting"):
    """Parse a record or a set of experiments into one 3-D array.

    The one record convention of the package (python-control's, channels
    first, time last): 1-D ``(n,)`` is one SISO record; 2-D ``(n_ch, n)`` is
    ONE record with channels first; 3-D ``(P, n_ch, n)`` holds ``P``
    experiments; a list holds experiments, each 1-D or 2-D.

    Parameters
    ----------
    x : array-like or list
    name : str
        How the messages call it.
    purpose : str, default="fitting"
        Passed to :func:`check_signal`.

    Returns
    -------
    data : ndarray of shape (P, n_channels, n_samples), float
        A new array (the input is never modified).
    form : {"1d", "2d", "3d", "list"}
        How ``x`` was given.
    item_ndim : tuple of int
        ``ndim`` of each experiment as given (1 or 2), for returning results
        in the same form.
    """
    _refuse_masked(x, name)
    if isinstance(x, (list, tuple)) and len(x) > 0 and all(
        isinstance(item, (Sequence, np.ndarray)) and not isinstance(item, (str, bytes))
        for item in x
    ) and not all(np.ndim(item) == 0 for item in x):
        items = [
            _parse_one(item, f"{name}[{p}]" if len(x) > 1 else name, purpose)
            for p, item in enumerate(x)
        ]
        if len(items) > 1 and all(item.shape[1] == 1 for item in items):
            raise _column_vector_error(name, (len(items), 1))
        channels = sorted({item.shape[0] for item in items})
        if len(channels) > 1:
            raise ValueError(
                f"All experiments of `{name}` must have the same number of "
                f"channels. Got {channels}. Pass the same channels in every "
                "experiment."
            )
        lengths = sorted({item.shape[1] for item in items})
        if len(lengths) > 1:
            raise ValueError(
                f"All records of `{name}` must have equal length. Got lengths "
                f"{lengths}. Trim the records to a common length."
            )
        item_ndim = tuple(int(np.ndim(item)) for item in x)
        return np.stack(items), "list", item_ndim
    if isinstance(x, np.ndarray) and x.ndim == 3:
        if x.shape[0] == 0:
            raise ValueError(f"`{name}` is empty. Pass a record with samples.")
        items = [
            _parse_one(x[p], f"{name}[{p}]" if x.shape[0] > 1 else name, purpose)
            for p in range(x.shape[0])
        ]
        return np.stack(items), "3d", (2,) * x.shape[0]
    if not isinstance(x, np.ndarray):
        try:
            arr = np.asarray(x)
        except Exception:  # pragma: no cover - numpy raises many types
            arr = None
        if arr is not None and arr.ndim == 3:
            return parse_record_set(arr, name, purpose=purpose)
    data = _parse_one(x, name, purpose)
    form = "2d" if np.ndim(x) == 2 else "1d"
    return data[None], form, (2 if form == "2d" else 1,)


@dataclass(frozen=True)
class Records:
    """Fast inputs and slow outputs of one or several experiments, parsed once.

    Every estimator parses ``u_h``/``y_l`` with :func:`check_records` into
    this object; the layers below work on its 3-D arrays.

    Attributes
    ----------
    u : ndarray of shape (P, n_u, N), float
    y : ndarray of shape (P, n_y, M), float
    F : int
        ``N = F M``.
    u_form, y_form : {"1d", "2d", "3d", "list"}
        How ``u_h`` and ``y_l`` were given.
    u_item_ndim : tuple of int
        ``ndim`` of each input experiment as given (for results in that form).
    """

    u: np.ndarray
    y: np.ndarray
    F: int
    u_form: str = "1d"
    y_form: str = "1d"
    u_item_ndim: tuple = (1,)

    @property
    def n_experiments(self) -> int:
        """``P``."""
        return self.u.shape[0]

    @property
    def n_inputs(self) -> int:
        """``n_u``."""
        return self.u.shape[1]

    @property
    def n_outputs(self) -> int:
        """``n_y``."""
        return self.y.shape[1]

    @property
    def n_samples(self) -> int:
        """``N``."""
        return self.u.shape[2]

    @property
    def n_slow(self) -> int:
        """``M``."""
        return self.y.shape[2]

    @property
    def is_siso(self) -> bool:
        """True when ``n_u == n_y == 1``."""
        return self.n_inputs == 1 and self.n_outputs == 1

    @property
    def two_d_given(self) -> bool:
        """True when ``u_h`` or ``y_l`` was a 2-D array of several channels."""
        return (self.u_form == "2d" and self.n_inputs > 1) or (
            self.y_form == "2d" and self.n_outputs > 1
        )

    def independent_experiments(self, input_spectra=None) -> int:
        """How many experiments have linearly independent inputs.

        An experiment whose input record is a multiple or a linear combination
        of the others' (the same excitation repeated, or scaled) gives, with
        its own transient, no equation on the FRF that the others do not: the
        local problems then have the equations of this many experiments only.
        The records are scaled to unit norm (the amplitudes do not matter) and
        an eigenvalue of their Gram matrix below ``1e-12`` of the largest
        (a singular value below 1e-6) counts as dependence; all-zero records
        count for none. Records of any finite amplitude count alike.

        The FRF's equations at a slow bin ``k`` see an experiment through its
        aliased input vector (``U(k + f M)`` over the ``F`` bands and ``n_u``
        inputs): an experiment whose vector is, at every bin, a combination
        of the others' (with coefficients that may change from bin to bin)
        adds no equation on the FRF either. The same excitation shifted by
        whole slow samples (``F`` fast samples, e.g. one period of a periodic
        excitation cut at another phase) is such a copy: its vector is the
        original's times a phase. When there are at most ``F n_u``
        experiments (more always combine at a bin), the count is therefore
        also the rank of those vectors at a typical bin (the median over up
        to 256 spread bins with input from every experiment and in at least
        ``P`` of the band-input entries, singular values below ``1e-6`` of the bin's largest counting
        as dependence; an input that misses bands is left to the fit's
        per-bin check), computed from one DFT of
        each record (``input_spectra``, the one-sided DFTs of ``u``
        ``(P, n_u, N//2+1)``, if the caller has them: any common scale).
        """
        if self.n_experiments == 1:  # (an all-zero record: rank-deficient bins)
            return 1
        from .local_models import (
            _aliased_rank,
            power_of_two_exponent,
            scale_by_power_of_two,
        )

        rows = self.u.reshape(self.n_experiments, -1)
        # records far from unit amplitude (e.g. 1e-170 or 1e160, which the
        # estimators fit exactly) would under- or overflow in the Gram matrix:
        # those are normalised by a power of two (a copy of those rows only)
        exponents = [power_of_two_exponent(row) for row in rows]
        if any(exponents):
            rows = np.stack([scale_by_power_of_two(row, -e)
                             for row, e in zip(rows, exponents)])
        gram = rows @ rows.T  # no copy of ordinary records
        norms = np.sqrt(np.diag(gram))
        excited = norms > 0
        gram = gram[np.ix_(excited, excited)] / np.outer(norms[excited],
                                                          norms[excited])
        if gram.shape[0] <= 1:
            return gram.shape[0]
        eigenvalues = np.linalg.eigvalsh(gram)
        count = int(np.sum(eigenvalues > 1e-12 * eigenvalues[-1]))
        if gram.shape[0] > self.F * self.n_inputs:
            return count
        N = self.n_samples
        if input_spectra is None:
            def spectrum_of(p):  # one experiment at a time, scaled rows
                return np.fft.rfft(rows[p].reshape(self.n_inputs, N), axis=-1)
        else:
            def spectrum_of(p):
                return input_spectra[p]
        rank = _aliased_rank(spectrum_of, np.flatnonzero(excited), self.n_inputs,
                             N, self.F)
        return count if rank is None else min(count, rank)

    def hint(self) -> str:
        """:data:`SEVERAL_EXPERIMENTS_HINT` when a 2-D array with several rows
        was given (a message about a shape that does not fit adds it), else
        an empty string."""
        return " " + SEVERAL_EXPERIMENTS_HINT if self.two_d_given else ""

    def siso_stacks(self, who: str) -> tuple[np.ndarray, np.ndarray]:
        """The records as (P, N) and (P, M) stacks, for SISO-only code.

        Raises
        ------
        ValueError
            When there is more than one input or output channel.
        """
        if not self.is_siso:
            raise ValueError(
                f"{who} handles one input and one output channel only. Got "
                f"{self.n_inputs} input and {self.n_outputs} output channel(s)."
                + self.hint()
                + " Select one channel of each for a MIMO system."
            )
        return self.u[:, 0, :], self.y[:, 0, :]


def format_like_input(y: np.ndarray, form: str, item_ndim: tuple) -> object:
    """Return per-experiment outputs (P, n_y, M) in the form of the input.

    A 1-D input with one output gives 1-D; a 2-D input (or a 1-D input with
    several outputs) gives (n_y, M); 3-D gives (P, n_y, M); a list gives a
    list of such records.
    """
    def one(record, ndim):
        return record[0] if (ndim == 1 and record.shape[0] == 1) else record

    if form == "list":
        return [one(y[p], item_ndim[p]) for p in range(y.shape[0])]
    if form == "3d":
        return y
    return one(y[0], 1 if form == "1d" else 2)


def check_record_stack(x, name: str, *, purpose: str = "fitting") -> np.ndarray:
    """Validate the record(s) of one channel and return them as (P, n).

    Parameters
    ----------
    x : array-like or list
        A 1-D record, a (1, n) record, a list of 1-D records or a (P, 1, n)
        array (see :func:`parse_record_set`).
    name : str
        How the messages call it.
    purpose : str, default="fitting"
        Passed to :func:`check_signal`.

    Returns
    -------
    ndarray of shape (n_experiments, n_samples)
    """
    data, form, _ = parse_record_set(x, name, purpose=purpose)
    if data.shape[1] != 1:
        extra = " " + SEVERAL_EXPERIMENTS_HINT if form == "2d" else ""
        raise ValueError(
            f"`{name}` must hold one channel. Got {data.shape[1]} channels."
            + extra
        )
    return data[:, 0, :]


def check_records(u_h, y_l, F, *, purpose: str = "fitting") -> Records:
    """Validate one or several experiments into a :class:`Records`.

    Parameters
    ----------
    u_h : array-like or list
        Fast-rate input record(s): ``(N,)``, ``(n_u, N)``, ``(P, n_u, N)`` or
        a list of ``P`` records (see :func:`parse_record_set`).
    y_l : array-like or list
        Slow-rate output record(s), likewise with ``n_y`` channels and
        ``n_samples == F * n_slow``.
    F : int
        Downsampling factor.
    purpose : str, default="fitting"
        Passed to :func:`check_signal` (e.g. ``"scoring"``).

    Returns
    -------
    Records
    """
    F = check_downsampling_factor(F)
    u, u_form, u_ndim = parse_record_set(u_h, "u_h", purpose=purpose)
    y, y_form, _ = parse_record_set(y_l, "y_l", purpose=purpose)
    records = Records(u, y, F, u_form, y_form, u_ndim)
    if u.shape[0] != y.shape[0]:
        raise ValueError(
            f"u_h holds {u.shape[0]} experiment(s) but y_l holds {y.shape[0]}. "
            "Pass one slow output record per input record." + records.hint()
        )
    N, M = u.shape[2], y.shape[2]
    if N != F * M:
        raise ValueError(
            f"The fast input has N={N} samples and the slow output M={M}, but "
            f"N must equal F*M = {F}*{M} = {F * M}. Check F or trim u_h to "
            f"{F * M} samples (y_l(m) must be y_h(m*F))." + records.hint()
        )
    return records


#: Names of the local-model degrees as LRMBeyondNyquist calls them.
LRM_PARAMETER_NAMES = {
    "half_window": "half_window",
    "num_degree": "num_degree",
    "transient_degree": "transient_degree",
    "den_degree": "den_degree",
}


def check_local_degrees(
    *,
    half_window: int,
    num_degree: int,
    transient_degree: int,
    den_degree: int,
    F: int,
    n_slow: int,
    n_experiments: int = 1,
    parameter_names: dict | None = None,
    n_inputs: int = 1,
    hint: str = "",
    n_independent: int | None = None,
) -> dict:
    """Check that the local problems are well posed and return the degrees.

    The conditions are eq. (uniqueConditions) of the paper, generalised to
    ``P`` experiments that share the system parameters and each have their own
    transient, and to ``n_u`` inputs (the local models of all inputs over all
    ``F`` bands in one problem per output row):
    ``P (2n+1) >= (R_g+1) F n_u + P (R_t+1) + R_e`` and ``2n+1 <= M``.

    Parameters
    ----------
    half_window, num_degree, transient_degree, den_degree : int
        ``n``, ``R_g``, ``R_t``, ``R_e``.
    F : int
        Downsampling factor.
    n_slow : int
        ``M``, samples of the slow record.
    n_experiments : int, default=1
        ``P``.
    parameter_names : dict, optional
        How the caller's estimator names each of the four settings, for the
        messages (e.g. LPM calls ``num_degree`` ``degree``); a name of ``None``
        marks a setting the user cannot change (LPM's ``den_degree = 0``).
        Default: :data:`LRM_PARAMETER_NAMES`.
    n_inputs : int, default=1
        ``n_u``.
    hint : str, default=""
        Appended to the messages (e.g. :meth:`Records.hint`).
    n_independent : int, optional
        Experiments with linearly independent inputs
        (:meth:`Records.independent_experiments`); default ``P``. Dependent
        experiments add no equations on the FRF, so the count must also hold
        with ``P`` replaced by this number.

    Returns
    -------
    dict
        The four settings as ints, keyed like the arguments.
    """
    names = {**LRM_PARAMETER_NAMES, **(parameter_names or {})}
    n = check_nonnegative_int(half_window, names["half_window"], minimum=1)
    Rg = check_nonnegative_int(num_degree, names["num_degree"] or "num_degree")
    Rt = check_nonnegative_int(
        transient_degree, names["transient_degree"] or "transient_degree"
    )
    Re = check_nonnegative_int(den_degree, names["den_degree"] or "den_degree")
    window = 2 * n + 1
    max_half_window = (n_slow - 1) // 2
    if window > n_slow:
        raise ValueError(
            f"The window 2*{names['half_window']}+1 = {window} slow bins is wider "
            f"than the slow record (M={n_slow} bins). Reduce "
            f"{names['half_window']} to at most {max_half_window} or measure a "
            "longer record." + hint
        )
    P = n_experiments
    # the dependent experiments first: their count is the stricter one, and
    # the P-experiment advice (a window, more experiments) would not suffice
    independent = P if n_independent is None else n_independent
    if independent < P:
        n_params = (Rg + 1) * F * n_inputs + independent * (Rt + 1) + Re
        n_equations = independent * window
        if independent == 0 or n_equations < n_params:
            raise ValueError(
                f"The inputs of the {P} experiments are linearly dependent: only "
                f"{independent} of them {'is' if independent == 1 else 'are'} "
                "independent (an experiment repeats, scales or combines the "
                "others' input, or shifts it by whole slow samples, or its "
                "input is zero), and a dependent "
                "experiment, with its own transient, adds no equation on the "
                "FRF. "
                + (_too_few_equations_message(
                    names, n, Rg, Rt, Re, F, independent, n_params, n_equations,
                    max_half_window, n_inputs,
                ) if independent else "Excite the system: every input record "
                   "is zero.")
                + hint
            )
    n_params = (Rg + 1) * F * n_inputs + P * (Rt + 1) + Re
    n_equations = P * window
    if n_equations < n_params:
        raise ValueError(
            _too_few_equations_message(
                names, n, Rg, Rt, Re, F, P, n_params, n_equations, max_half_window,
                n_inputs,
            ) + hint
        )
    return {
        "half_window": n,
        "num_degree": Rg,
        "transient_degree": Rt,
        "den_degree": Re,
    }


def _too_few_equations_message(
    names, n, Rg, Rt, Re, F, P, n_params, n_equations, max_half_window, n_inputs=1
) -> str:
    """Say how many equations and parameters there are, and what to change."""
    num, tr, den = names["num_degree"], names["transient_degree"], names["den_degree"]
    times_p = f"{P}*" if P > 1 else ""
    times_u = "*n_u" if n_inputs > 1 else ""
    formula = f"({num}+1)*F{times_u} + {times_p}({tr}+1)"
    values = f"({Rg}+1)*{F}{f'*{n_inputs}' if n_inputs > 1 else ''} + {times_p}({Rt}+1)"
    if den is not None:
        formula += f" + {den}"
        values += f" + {Re}"
    degrees = [name for name in (num, tr, den) if name is not None]
    lower = "lower " + ", ".join(degrees[:-1]) + f" or {degrees[-1]}"
    need_n = int(np.ceil((np.ceil(n_params / P) - 1) / 2))
    if need_n <= max_half_window:
        fix = f"Increase {names['half_window']} to at least {need_n}, or {lower}."
    else:
        fix = (
            f"The record allows {names['half_window']} <= {max_half_window} only, "
            f"so {lower} (or measure a longer record)."
        )
    if n_inputs > 1 or P > 1:
        fix += _experiments_needed(n, Rg, Rt, Re, F, n_inputs, P)
    equations = f"{P}*(2*{n}+1)" if P > 1 else f"2*{n}+1"
    return (
        f"Too few equations for the parameters: the window gives {equations} = "
        f"{n_equations} equations but the local model has {formula} = {values} "
        f"= {n_params} parameters (eq. uniqueConditions needs at least as many "
        f"equations). {fix}"
    )


def _experiments_needed(n, Rg, Rt, Re, F, n_inputs, P) -> str:
    """The number of experiments that makes the problem square or better."""
    per_experiment = 2 * n - Rt  # equations minus transient parameters
    shared = (Rg + 1) * F * n_inputs + Re
    if per_experiment <= 0:
        return ""
    need_p = int(np.ceil(shared / per_experiment))
    return (
        f" With half_window={n}, at least {need_p} experiments "
        f"(records with different inputs, e.g. lrmfrf.signals."
        f"orthogonal_multisines) give enough equations."
    )


def check_positive_float(value, name: str, *, allow_none: bool):
    """``value`` as a positive finite float (or None when allowed)."""
    if value is None and allow_none:
        return None
    hint = " or None" if allow_none else ""
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise TypeError(
            f"`{name}` must be a positive number{hint}. Got {value!r} of type "
            f"{type(value).__name__} instead. Pass a positive finite number."
        ) from exc
    if not np.isfinite(number) or number <= 0:
        raise ValueError(
            f"`{name}` must be a positive, finite number{hint}. Got {value!r} "
            "instead. Use the default unless you have a reason not to."
        )
    return number


def check_siso_system(
    system,
    name: str,
    *,
    discrete: bool = True,
    state_space_only: bool = False,
    hint: str = "system[0, 0]",
):
    """Check that ``system`` is a SISO python-control model (discrete by default).

    Parameters
    ----------
    system : object
        The model to check.
    name : str
        How the message calls it (e.g. ``"`plant`"``).
    discrete : bool, default=True
        Also require a discrete-time system with a known sample time.
    state_space_only : bool, default=False
        Accept only ``control.StateSpace`` (not ``TransferFunction``).
    hint : str
        Example channel selection for the SISO message.

    Returns
    -------
    The system, unchanged.
    """
    import control

    allowed = (control.StateSpace,) if state_space_only else (
        control.StateSpace, control.TransferFunction)
    if not isinstance(system, allowed):
        kinds = "StateSpace" if state_space_only else "StateSpace or TransferFunction"
        raise TypeError(
            f"{name} must be a control.{kinds} (python-control StateSpace); got "
            f"{type(system).__name__}. Build it with control.ss(...)."
        )
    if system.ninputs != 1 or system.noutputs != 1:
        raise ValueError(
            f"{name} must be SISO; got {system.noutputs} outputs and "
            f"{system.ninputs} inputs. Select one channel, e.g. {hint}."
        )
    if discrete and not control.isdtime(system, strict=True):
        raise ValueError(
            f"{name} must be discrete-time; got dt={system.dt!r}. Discretise it "
            "first, e.g. control.sample_system(sys, Ts, 'zoh')."
        )
    return system


def check_sample_time(sample_time) -> float:
    """Return the fast sample time in seconds as a positive finite float."""
    try:
        value = float(sample_time)
    except (TypeError, ValueError) as exc:
        raise TypeError(
            f"`sample_time` must be a positive number of seconds. Got "
            f"{sample_time!r} of type {type(sample_time).__name__} instead. Pass "
            "the fast sample time, e.g. sample_time=0.5e-3."
        ) from exc
    if not np.isfinite(value) or value <= 0:
        raise ValueError(
            f"`sample_time` must be a positive, finite number of seconds (the fast "
            f"sample time). Got {sample_time!r} instead. Pass the fast sample "
            "time, e.g. sample_time=0.5e-3."
        )
    return value


# ---------------------------------------------------------------------------
# Generic checks first needed by the discrepancy workflow (issue 12, item 9)
# ---------------------------------------------------------------------------

__all__ += [
    "check_nonnegative_float",
    "check_probability",
    "check_rng",
    "renamed_keyword",
]


def check_nonnegative_float(value, name: str) -> float:
    """Return ``value`` as a finite float >= 0, or raise.

    Booleans and strings are refused (``TypeError``); NaN, inf and negative
    numbers are refused (``ValueError``).
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(
            f"`{name}` must be a number >= 0. Got {value!r} of type "
            f"{type(value).__name__} instead. Pass a finite number, e.g. {name}=1.0."
        )
    if not np.isfinite(value) or value < 0:
        raise ValueError(
            f"`{name}` must be a finite number >= 0. Got {value!r} instead. Pass "
            "a finite number, or use the default."
        )
    return float(value)


def check_probability(value, name: str) -> float:
    """Return a significance level (a probability strictly between 0 and 1)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(
            f"`{name}` must be a probability in (0, 1). Got {value!r} of type "
            f"{type(value).__name__} instead. Pass e.g. {name}=0.01."
        )
    if not 0 < value < 1:
        raise ValueError(
            f"`{name}` must be in (0, 1). Got {value!r} instead. Pass e.g. "
            f"{name}=0.01."
        )
    return float(value)


def check_rng(rng, name: str = "rng") -> np.random.Generator:
    """Return a ``numpy.random.Generator`` from ``None``, an int seed or a Generator.

    A Generator is returned as is (it is drawn from, so the caller's stream
    advances); ``None`` gives fresh entropy.
    """
    valid = rng is None or isinstance(rng, (numbers.Integral, np.random.Generator))
    if not valid or isinstance(rng, bool):
        raise TypeError(
            f"`{name}` must be None, an int seed or a numpy.random.Generator. Got "
            f"{rng!r} of type {type(rng).__name__} instead. Pass e.g. {name}=0 or "
            f"{name}=np.random.default_rng(0)."
        )
    if isinstance(rng, numbers.Integral) and rng < 0:
        raise ValueError(
            f"`{name}` must be a seed >= 0. Got {rng} instead. Pass e.g. {name}=0."
        )
    return np.random.default_rng(rng)


def renamed_keyword(new_value, old_value, *, new: str, old: str, default=None,
                    since: str = "issue 12", stacklevel: int = 3):
    """Resolve a renamed keyword argument that keeps working for one release.

    Parameters
    ----------
    new_value : object
        Value passed under the new name (``default`` when not passed).
    old_value : object
        Value passed under the old name; ``None`` when not passed.
    new, old : str
        The new and the old keyword names.
    default : object, optional
        The new keyword's default, to tell whether it was passed.
    since : str
        Shown in the warning.
    stacklevel : int, default=3
        Points the warning at the caller of the function that calls this.

    Returns
    -------
    object
        ``old_value`` (with a ``FutureWarning``) when only the old name was
        passed, else ``new_value``.

    Raises
    ------
    TypeError
        When both names were passed.
    """
    import warnings

    if old_value is None:
        return new_value
    if new_value is not default and not _equals(new_value, default):
        raise TypeError(
            f"`{old}` was renamed to `{new}` ({since}); pass only `{new}`, not "
            "both."
        )
    warnings.warn(
        f"`{old}` was renamed to `{new}` ({since}) and will be removed in the next "
        f"release. Use {new}=... instead.",
        FutureWarning, stacklevel=stacklevel,
    )
    return old_value


def _equals(value, default) -> bool:
    try:
        return bool(value == default)
    except (TypeError, ValueError):  # arrays and the like: not the default
        return False


def check_feedback_outputs(feedback_outputs, n_outputs: int) -> tuple[int, ...]:
    """Indices of the outputs a controller feeds back: ``None`` means all of them,
    one int means that output; distinct indices in ``0..n_outputs-1``."""
    if feedback_outputs is None:
        return tuple(range(n_outputs))
    if isinstance(feedback_outputs, numbers.Integral):
        feedback_outputs = (feedback_outputs,)
    indices = tuple(feedback_outputs)
    if (
        not indices
        or not all(isinstance(i, numbers.Integral) for i in indices)
        or len(set(indices)) != len(indices)
        or not all(0 <= i < n_outputs for i in indices)
    ):
        raise ValueError(
            f"feedback_outputs must be distinct output indices in [0, "
            f"{n_outputs - 1}]; got {feedback_outputs!r}."
        )
    return tuple(int(i) for i in indices)

__all__ += ["check_feedback_outputs"]


def check_discrete_controller(controller, *, hint: str):
    """A python-control ``StateSpace``/``TransferFunction`` with a known,
    discrete sample time; ``hint`` says how to discretise it."""
    import control

    if not isinstance(controller, (control.StateSpace, control.TransferFunction)):
        raise TypeError(
            "controller must be a control.StateSpace or TransferFunction; got "
            f"{type(controller).__name__}."
        )
    if not control.isdtime(controller, strict=True) or controller.dt is True:
        raise ValueError(
            f"controller must be discrete-time with a known sample time; got "
            f"dt={controller.dt!r}. {hint}"
        )
    return controller


__all__ += ["check_discrete_controller"]
