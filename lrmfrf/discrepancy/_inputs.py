"""Input checks and preparation of :func:`lrmfrf.diagnose`.

Everything that turns the user's arguments into the comparison the search
works on: the settings, the sample time (given or a discrete model's ``dt``),
the plant and controller (and the stability of their loop), the estimator fit
and the bins it can compare (:class:`~lrmfrf.discrepancy.fit.FitProblem`).
The search itself is in :mod:`._search`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import control
import numpy as np
from sklearn.base import clone

from .._validation import (
    check_nonnegative_float,
    check_nonnegative_int,
    check_probability,
    check_sample_time,
    check_siso_system,
)
from ._models import (
    ContinuousPlant,
    as_continuous_plant,
    frequency_response,
    to_discrete_ss,
)
from .detect import Calibration
from .effects import Effect, default_effects
from .fit import FitProblem

#: Fewest compared bins for a meaningful diagnosis.
MIN_BINS = 20

#: Fewest residual degrees of freedom of the default estimator's local fits
#: (issue 15: at F = 5 the default half window leaves none with one experiment).
MIN_DEFAULT_DOF = 10


@dataclass(frozen=True)
class SearchSettings:
    """The checked settings of the search (see :func:`lrmfrf.diagnose`)."""

    alpha: float
    effect_alpha: float
    ic_margin: float
    max_effects: int
    calibration_runs: int
    smoothing_bins: int
    debias_rounds: int


def check_settings(*, alpha, effect_alpha, ic_margin, max_effects,
                   calibration_runs, smoothing_bins, debias_rounds) -> SearchSettings:
    """Check the numeric settings of :func:`lrmfrf.diagnose`."""
    settings = SearchSettings(
        alpha=check_probability(alpha, "alpha"),
        effect_alpha=check_probability(effect_alpha, "effect_alpha"),
        ic_margin=check_nonnegative_float(ic_margin, "ic_margin"),
        max_effects=check_nonnegative_int(max_effects, "max_effects"),
        calibration_runs=check_nonnegative_int(calibration_runs, "calibration_runs"),
        smoothing_bins=check_nonnegative_int(smoothing_bins, "smoothing_bins",
                                             minimum=1),
        debias_rounds=check_nonnegative_int(debias_rounds, "debias_rounds"),
    )
    if settings.calibration_runs == 1:
        raise ValueError(
            "`calibration_runs` must be 0 (no calibration) or >= 2 (the spread of "
            "the runs is needed). Got 1. Use e.g. calibration_runs=10."
        )
    return settings


def check_catalogue(effects, shape: tuple = (1, 1)) -> list[Effect]:
    """The effect catalogue as a list (default: :func:`default_effects`).

    ``shape`` is the data's ``(n_y, n_u)``: a per-channel effect's explicit
    channel must be one of them (checked here, not first when the search
    expands the catalogue, which it does not when nothing is significant).
    """
    catalogue = list(default_effects() if effects is None else effects)
    for entry in catalogue:
        if not isinstance(entry, Effect):
            raise TypeError(
                f"`effects` must hold Effect instances. Got {type(entry).__name__}. "
                "Subclass lrmfrf.discrepancy.Effect."
            )
        check_channel = getattr(entry, "check_channel", None)
        if check_channel is not None:
            check_channel(*shape)
    return catalogue


def check_models(plant, controller, sample_time: float, source: str,
                 shape: tuple = (1, 1)):
    """The plant as a :class:`ContinuousPlant` and the controller as state space.

    ``shape`` is the data's ``(n_y, n_u)``: the plant must have it, the
    controller the transposed one. Raises if the closed loop of the given
    plant and controller is unstable (it cannot then be the measured system).
    """
    nominal = as_continuous_plant(plant, sample_time, shape=shape)
    controller = check_controller(controller, sample_time, source, shape)
    measured_system(nominal, controller, sample_time)  # stability check
    return nominal, controller


def comparison_problem(fitted, band, controller, sample_time: float,
                       entry_shape: tuple = ()):
    """The :class:`FitProblem` on the usable bins, and those bins.

    ``entry_shape`` is ``()`` for SISO, ``(n_y, n_u)`` for MIMO.
    """
    bins = usable_bins(fitted, band, entry_shape)
    frequencies = np.asarray(fitted.frequencies_, dtype=float)[bins]
    controller_frf = (
        None if controller is None
        else frequency_response(controller, frequencies, sample_time)
    )
    shape = tuple(entry_shape) + (bins.size,)
    problem = FitProblem(
        frequencies=frequencies,
        measured=np.asarray(fitted.frf_)[..., bins],
        std=np.asarray(fitted.frf_std_)[..., bins],
        sample_time=sample_time,
        controller=controller_frf,
        bias=np.zeros(shape, complex),
        scale=np.ones(shape),
        inflation=1.0,
    )
    return problem, bins


def closed_loop(plant: ContinuousPlant, controller, sample_time: float):
    """Discrete closed loop ``P (I + C P)^-1`` and its largest pole magnitude."""
    discrete = to_discrete_ss(plant, sample_time)
    loop = control.feedback(discrete, control.ss(controller), sign=-1)
    radius = float(np.max(np.abs(np.linalg.eigvals(loop.A)))) if loop.nstates else 0.0
    return loop, radius


def measured_system(plant: ContinuousPlant, controller, sample_time: float):
    """Discrete model of the measured system; raise if the loop is unstable."""
    if controller is None:
        return to_discrete_ss(plant, sample_time)
    loop, radius = closed_loop(plant, controller, sample_time)
    if radius >= 1.0:
        raise ValueError(
            "the closed loop of `plant` and `controller` is unstable (largest pole "
            f"magnitude {radius:.6g} >= 1), so it cannot be the measured system. "
            "Check the controller sign convention (u = u_h - C y) and the plant."
        )
    return loop


def fit_estimator(estimator, u, y, F, sample_time):
    """The fitted estimator (fitted here unless it already is) and a template.

    ``u`` (P, N) or (P, n_u, N), ``y`` (P, M) or (P, n_y, M). The template is
    an unfitted clone, refitted by the calibration runs.
    """
    n_inputs = u.shape[1] if u.ndim == 3 else 1
    if estimator is None:
        estimator = default_estimator(F, u.shape[0], u.shape[-1] // F, n_inputs)
    if not hasattr(estimator, "fit"):
        raise TypeError(
            "`estimator` must be an FRF estimator with fit(u_h, y_l, F, *, "
            f"sample_time). Got {type(estimator).__name__}."
        )
    template = clone(estimator)
    if hasattr(estimator, "frf_"):
        N = u.shape[-1]
        if getattr(estimator, "n_samples_", N) != N or getattr(
            estimator, "downsampling_factor_", F
        ) != F:
            raise ValueError(
                "the fitted `estimator` does not match the data: it was fitted to "
                f"N={getattr(estimator, 'n_samples_', None)}, "
                f"F={getattr(estimator, 'downsampling_factor_', None)}; the data "
                f"have N={N}, F={F}. Pass an unfitted estimator to fit it here."
            )
        stime = getattr(estimator, "sample_time_", sample_time)
        if not math.isclose(stime, sample_time, rel_tol=1e-9):
            raise ValueError(
                f"the fitted `estimator` used sample_time={stime!r} s, the call "
                f"sample_time={sample_time!r} s. Use one sample time."
            )
        return estimator, template
    fitted = clone(estimator)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fitted.fit(list(u), list(y), F, sample_time=sample_time)
    except ValueError as exc:
        raise ValueError(
            f"the estimator could not be fitted to the data ({exc}). Record more "
            "samples or use a smaller half_window."
        ) from exc
    return fitted, template


def default_estimator(F: int, n_experiments: int, n_slow: int, n_inputs: int = 1):
    """``LRMBeyondNyquist()`` with a half window that leaves enough dof.

    The default half window (18) leaves ``P (2n + 1) - n_params`` residual
    degrees of freedom: 10 at ``F = 3`` with one experiment, 5 at ``F = 4`` and
    none at ``F = 5`` (then ``frf_std_`` is NaN and nothing can be tested).
    The half window is raised, one slow bin at a time, until the local fits
    keep :data:`MIN_DEFAULT_DOF` degrees of freedom or the window spans the
    record; where the default already does, it is used unchanged.
    """
    from ..estimators import LRMBeyondNyquist
    from ..windows import LocalModelLayout

    estimator = LRMBeyondNyquist()
    params = estimator.get_params()
    half_window = int(params["half_window"])

    def dof(n):
        return LocalModelLayout(
            F=F, half_window=n, num_degree=params["num_degree"],
            transient_degree=params["transient_degree"],
            den_degree=params["den_degree"], n_experiments=n_experiments,
            n_inputs=n_inputs,
        ).dof

    while dof(half_window) < MIN_DEFAULT_DOF and 2 * (half_window + 1) + 1 <= n_slow:
        half_window += 1
    return estimator.set_params(half_window=half_window)


def usable_bins(fitted, band, entry_shape: tuple = ()) -> np.ndarray:
    """Indices of the bins in ``band`` with a valid, finite FRF and std > 0.

    ``entry_shape`` is ``(n_y, n_u)`` for a MIMO measurement (``frf_`` of
    shape ``(n_y, n_u, K)``): a bin is used when every entry is usable.
    """
    frf = np.asarray(fitted.frf_)
    std = np.asarray(fitted.frf_std_)
    freqs = np.asarray(fitted.frequencies_, dtype=float)
    valid = np.asarray(getattr(fitted, "valid_", np.ones(frf.shape, bool)), bool)
    expected = tuple(entry_shape) + freqs.shape
    if freqs.ndim != 1 or frf.shape != expected or std.shape != expected:
        what = "1-D arrays of one length" if not entry_shape else (
            f"of shape {expected} (frequencies_ of shape {freqs.shape})")
        raise ValueError(
            f"the estimator's frequencies_, frf_ and frf_std_ must be {what}. "
            f"Got shapes {freqs.shape}, {frf.shape} and {std.shape}."
        )
    inside = (freqs > 0) & (freqs >= band[0]) & (freqs <= band[1])
    good = valid & np.isfinite(frf) & np.isfinite(std) & (std > 0)
    good = inside & good.reshape(-1, freqs.size).all(axis=0)
    n_inside = int(np.count_nonzero(inside))
    n_bad = n_inside - int(np.count_nonzero(good))
    if n_bad:
        warnings.warn(
            f"{n_bad} of {n_inside} bins have a non-finite FRF or a std that is "
            "zero, negative or NaN; they are left out of the comparison.",
            UserWarning, stacklevel=4,
        )
    bins = np.flatnonzero(good)
    needed = max(MIN_BINS, n_inside // 2)
    if bins.size < needed:
        raise ValueError(
            f"only {bins.size} of {n_inside} bins have a finite FRF and a "
            f"positive finite std; at least {needed} are needed. Check the "
            "estimator's frf_std_ (zero or NaN std), the input excitation and "
            "`band`."
        )
    return bins


def check_band(band) -> tuple:
    """``band`` as ``(low, high)`` in Hz; ``None`` means every bin."""
    if band is None:
        return (0.0, math.inf)
    try:
        low, high = (float(v) for v in band)
    except (TypeError, ValueError) as exc:
        raise TypeError(
            f"`band` must be a pair (low, high) in Hz or None. Got {band!r}."
        ) from exc
    if not (low >= 0 and high > low):
        raise ValueError(
            f"`band` must satisfy 0 <= low < high (Hz). Got {band!r}."
        )
    return (low, high)


def resolve_sample_time(sample_time, plant, controller) -> tuple[float, str]:
    """The fast sample time and where it came from (for messages).

    Given: checked. Not given: the ``dt`` of a discrete ``plant``, else of a
    discrete ``controller``; else an error asking for it.
    """
    if sample_time is not None:
        value = check_sample_time(sample_time)
        return value, f"sample_time={value!r} s"
    if not isinstance(plant, control.LTI):
        check_siso_system(plant, "`plant`", discrete=False,
                          hint="stage.plant[0, 0] for y4")  # the type message
    for model, name in ((plant, "`plant`"), (controller, "`controller`")):
        if model is None or not isinstance(model, control.LTI):
            continue
        dt = model.dt
        if control.isdtime(model, strict=True) and not isinstance(dt, bool):
            value = check_sample_time(dt)
            return value, f"sample_time={value!r} s (the dt of {name})"
    raise ValueError(
        "`sample_time` was not given and neither `plant` nor `controller` is a "
        "discrete model with a known dt to take it from. Pass the fast sample "
        "time in seconds, e.g. sample_time=0.5e-3."
    )


def check_controller(controller, sample_time, source, shape=(1, 1)):
    """The controller as discrete state space at ``sample_time`` (or None).

    ``source`` says where the sample time came from, for the message;
    ``shape`` is the plant's ``(n_y, n_u)`` (the controller maps the ``n_y``
    outputs to the ``n_u`` inputs).
    """
    if controller is None:
        return None
    if tuple(shape) == (1, 1):
        check_siso_system(controller, "`controller`", discrete=False)
    else:
        _check_controller_shape(controller, shape)
    if not control.isdtime(controller, strict=True):
        raise ValueError(
            "`controller` must be discrete with dt == sample_time. Got "
            f"dt={controller.dt!r}. Discretise it, e.g. "
            "control.sample_system(C, sample_time, 'tustin')."
        )
    if not math.isclose(float(controller.dt), sample_time, rel_tol=1e-9):
        raise ValueError(
            f"`controller` has dt={float(controller.dt)!r} s but {source}. Pass "
            "the controller at the fast sample time."
        )
    return control.ss(controller)


def _check_controller_shape(controller, shape):
    """A MIMO controller must have ``n_y`` inputs and ``n_u`` outputs."""
    if not isinstance(controller, (control.StateSpace, control.TransferFunction)):
        raise TypeError(
            "`controller` must be a control.StateSpace or TransferFunction "
            f"(python-control StateSpace); got {type(controller).__name__}."
        )
    n_y, n_u = shape
    if (controller.noutputs, controller.ninputs) != (n_u, n_y):
        raise ValueError(
            f"`controller` has {controller.noutputs} output(s) and "
            f"{controller.ninputs} input(s); with {n_y} plant output(s) and "
            f"{n_u} input(s) it must have {n_u} outputs and {n_y} inputs "
            "(u = r - C y)."
        )


def check_calibration(cal, n_bins, entry_shape: tuple = ()):
    """Check a reused calibration against the compared bins (and entries)."""
    if not isinstance(cal, Calibration):
        raise TypeError(
            "`calibration` must be a Calibration from an earlier report "
            f"(report.calibration). Got {type(cal).__name__}."
        )
    if cal.bias.shape[-1:] != (n_bins,):
        raise ValueError(
            f"`calibration` was made for {cal.bias.shape[-1]} bins, these data have "
            f"{n_bins}. Reuse a calibration only with the same inputs and estimator."
        )
    if cal.bias.shape[:-1] != tuple(entry_shape):
        raise ValueError(
            f"`calibration` was made for FRF entries of shape {cal.bias.shape[:-1]}, "
            f"these data have {tuple(entry_shape)}. Reuse a calibration only with "
            "the same inputs, outputs and estimator."
        )
