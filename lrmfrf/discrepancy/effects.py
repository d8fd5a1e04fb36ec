"""The catalogue of model effects the discrepancy workflow can name.

An effect is a small class: it names its parameters, proposes initial guesses
from the current discrepancy, declares bounds, applies itself to a continuous
plant model (:class:`~lrmfrf.discrepancy._models.ContinuousPlant`) and
describes itself in words. The frequency response used in the fit is that of
the exact zero-order-hold discretisation of the modified model, so the fitted
response and the returned ``updated_plant`` are the same system.

Add your own effect by subclassing :class:`Effect` and passing an instance in
``diagnose(..., effects=[*default_effects(), MyEffect()])``.

Parameter conventions (the ``parameters`` dict of a finding):

==============  ===========================  ====================================
effect          parameters                    model change
==============  ===========================  ====================================
gain            gain                          ``P -> gain * P``
delay           delay (s)                     ``P -> exp(-s delay) P`` (input)
low_pass        cutoff (Hz)                   ``P -> P / (1 + s / (2 pi cutoff))``
missing_mode    frequency (Hz), damping       ``P -> P + r / (s^2 + 2 z w s + w^2)``
mode_shift      frequency (Hz), damping       a model mode moved, numerator kept
model_error     zero_frequency, zero_damping, ``P -> H P``, ``H`` a unit-DC-gain
                pole_frequency, pole_damping  second-order filter (unnamed)
==============  ===========================  ====================================

``missing_mode`` also fits the modal residue ``r`` (a nuisance parameter,
reported with the finding's evidence, not in ``parameters``).

Per-channel effects (MIMO only; they expand to nothing on a SISO plant and
on the side with a single channel, where they would be ``gain``,
``low_pass`` or ``delay`` again). Each is one candidate per channel
(:meth:`Effect.expand`, as ``mode_shift`` is one per mode); the channel is
chosen, not fitted, and is
reported as an integer parameter (``input=j`` or ``output=i``, 0-based, the
``u0, u1, ...`` and ``y0, y1, ...`` of :meth:`DiagnosisReport.plot_grid`):

==============  ===========================  ====================================
effect          parameters                    model change
==============  ===========================  ====================================
input_gain      input (j), gain               column ``j`` of ``P`` times ``gain``
                                              (one actuator's constant)
output_gain     output (i), gain              row ``i`` of ``P`` times ``gain``
                                              (one sensor's scale)
input_low_pass  input (j), cutoff (Hz)        input ``j`` through
                                              ``1 / (1 + s / (2 pi cutoff))``
input_delay     input (j), delay (s)          input ``j`` delayed by ``delay``
                                              (one actuator's delay; the
                                              model's delay is then one per
                                              input)
==============  ===========================  ====================================

A per-channel effect names the all-channel effect it refines
(:attr:`Effect.parent`: ``gain``, ``low_pass`` or ``delay``); the search
prefers the parent unless the per-channel candidate is better by the
``ic_margin`` of :func:`lrmfrf.diagnose` (a refinement has to earn its
channel).

MIMO plants (``n_y`` outputs, ``n_u`` inputs). ``gain``, ``delay``,
``low_pass`` and ``model_error`` act on every input channel alike (one
parameter set: an actuator-chain error common to all channels; one channel's
gain, bandwidth or delay is the per-channel effects' above; ``delay`` adds
to each input's own delay). ``missing_mode`` adds
a mode with the rank-one real residue ``c b^T`` (a mode shape: ``c`` over the
outputs, ``b`` over the inputs), ``P -> P + c b^T / (s^2 + 2 z w s + w^2)``;
its nuisance parameters are ``residue_0 .. residue_{n_y-1}`` (``c``) and the
angles ``input_angle_1 .. input_angle_{n_u-1}`` of the unit vector ``b``
(hyperspherical coordinates, so ``c b^T`` has no scale ambiguity), started
from the rank-one part of a weighted least-squares residue. ``mode_shift``
moves a model mode of the whole plant: the mode's block ``A_m`` becomes
``alpha A_m + beta I`` (the new pole pair, same modal directions) and its
input matrix is divided by ``alpha``, which keeps the numerator ``s b1 + b0``
exactly when ``b1 = C_m B_m = 0`` (force to position) and approximately
otherwise. SISO keeps its exact numerator-preserving surgery.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from ._models import ContinuousPlant, Resonance, discrete_response

__all__ = [
    "Effect",
    "EffectContext",
    "Gain",
    "Delay",
    "LowPass",
    "MissingMode",
    "ModeShift",
    "ModelError",
    "InputGain",
    "OutputGain",
    "InputDelay",
    "InputLowPass",
    "default_effects",
]

TWO_PI = 2.0 * math.pi


@dataclass
class EffectContext:
    """What an effect may look at to propose initial guesses.

    Attributes
    ----------
    plant : ContinuousPlant
        Current plant model (the effects accepted so far applied).
    frequencies : ndarray of shape (K,)
        Frequencies of the compared bins in Hz.
    sample_time : float
        Fast sample time in s.
    plant_ratio : ndarray of shape (K,), complex
        Measured over modelled plant response ``P_meas / P_model``.
    plant_weight : ndarray of shape (K,)
        Inverse variance of ``plant_ratio`` (0 where unusable).
    discrepancy : ndarray of shape (K,)
        Smoothed whitened squared residual (the discrepancy spectrum).
    resonances : list of Resonance
        Lightly damped modes of ``plant``.
    sensitivity : ndarray of shape (K,), complex, or pair of ndarrays
        ``dG/dP`` of the measured system at the model (1 without controller).
        MIMO: the pair ``(S_o, S_i)`` of shapes (n_y, n_y, K) and
        (n_u, n_u, K) with ``dG = S_o dP S_i`` (identities in open loop).
    residual : ndarray of shape (K,) or (n_y, n_u, K), complex
        ``G_meas - G_model``.
    std : ndarray of the shape of ``residual``
        Calibrated standard deviation of ``G_meas``.
    modal_resonances : list of Resonance or None
        Lightly damped modes of the plant the modal effects (``order`` 0,
        mode shifts) act on: the nominal plant with the accepted mode shifts,
        without the modes accepted missing modes added (those are applied
        after the shifts, so a shift cannot move them). None: ``resonances``.

    For MIMO, ``plant_ratio`` and ``plant_weight`` are per entry,
    ``(n_y, n_u, K)``; ``discrepancy`` is the bin power's moving mean, (K,).
    """

    plant: ContinuousPlant
    frequencies: np.ndarray
    sample_time: float
    plant_ratio: np.ndarray
    plant_weight: np.ndarray
    discrepancy: np.ndarray
    resonances: list = field(default_factory=list)
    sensitivity: np.ndarray | None = None
    residual: np.ndarray | None = None
    std: np.ndarray | None = None
    modal_resonances: list | None = None

    @property
    def nyquist(self) -> float:
        """Fast Nyquist frequency in Hz."""
        return 0.5 / self.sample_time


class Effect:
    """Base class of a nameable model effect.

    Subclasses set the class attributes and implement :meth:`apply`,
    :meth:`initial_guesses` and :meth:`bounds`.

    Attributes
    ----------
    name : str
        Effect name reported in findings.
    parameter_names : tuple of str
        Reported parameters (the keys of ``Finding.parameters``).
    nuisance_names : tuple of str
        Further fitted parameters, reported with the evidence only.
    order : int
        Application order: modal changes (0, 1) before series effects (2), so a
        delay or low-pass acts on the whole plant, added modes included.
    named : bool
        False for the unnamed model-error fallback.
    repeatable : bool
        Whether the effect may be accepted more than once (several missing
        modes); a second gain or delay is never useful.
    parent : str or None
        Name of the simpler effect this one refines (a per-channel gain:
        ``"gain"``); the search names the parent unless this candidate is
        better by ``ic_margin``.
    """

    name: str = "effect"
    parameter_names: tuple[str, ...] = ()
    nuisance_names: tuple[str, ...] = ()
    order: int = 2
    named: bool = True
    repeatable: bool = False
    parent: str | None = None

    @property
    def all_names(self) -> tuple[str, ...]:
        return self.parameter_names + self.nuisance_names

    def expand(self, context: EffectContext) -> list[Effect]:
        """Concrete candidates for this context (one per model mode for shifts)."""
        return [self]

    def initial_guesses(self, context: EffectContext) -> list[dict]:
        """Starting points for the fit, each a dict over :attr:`all_names`."""
        raise NotImplementedError

    def bounds(self, context: EffectContext) -> dict:
        """``{name: (lower, upper)}`` for every name in :attr:`all_names`."""
        raise NotImplementedError

    def apply(self, plant: ContinuousPlant, params: dict) -> ContinuousPlant:
        """The plant with this effect added."""
        raise NotImplementedError

    def describe(self, params: dict) -> str:
        """One line of plain text."""
        values = ", ".join(f"{k}={v:.4g}" for k, v in params.items())
        return f"{self.name}({values})"

    def label(self) -> str:
        """Name of this candidate instance (e.g. which mode is shifted)."""
        return self.name

    def fixed_parameters(self) -> dict:
        """Reported parameters chosen by :meth:`expand`, not fitted (a channel).

        They come first in ``Finding.parameters``; empty by default.
        """
        return {}

    def response(
        self,
        plant: ContinuousPlant,
        params: dict,
        frequencies: np.ndarray,
        sample_time: float,
    ) -> np.ndarray:
        """ZOH frequency response of the plant with this effect, shape (K,)."""
        return discrete_response(self.apply(plant, params), frequencies, sample_time)

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


# ---------------------------------------------------------------------------
# The catalogue
# ---------------------------------------------------------------------------


class Gain(Effect):
    """Static gain error: ``P -> gain * P`` (actuator constant, sensor scale)."""

    name = "gain"
    parameter_names = ("gain",)

    def initial_guesses(self, context):
        ratio, weight = context.plant_ratio, context.plant_weight
        guesses = [0.7, 0.9, 1.1, 1.4]
        if weight.sum() > 0:
            estimate = float(np.sum(weight * np.abs(ratio)) / np.sum(weight))
            if np.isfinite(estimate) and 0.1 < estimate < 10:
                guesses.insert(0, estimate)
        return [{"gain": g} for g in guesses]

    def bounds(self, context):
        return {"gain": (0.05, 20.0)}

    def apply(self, plant, params):
        g = params["gain"]
        return plant.with_(C=plant.C * g, D=plant.D * g)

    def describe(self, params):
        return f"gain error: the plant gain is {params['gain']:.4g} times the model's"


class Delay(Effect):
    """Input time delay (fractional samples allowed): ``P -> exp(-s delay) P``."""

    name = "delay"
    parameter_names = ("delay",)

    def initial_guesses(self, context):
        T = context.sample_time
        grid = np.concatenate([np.arange(0.1, 1.0, 0.2), np.arange(1.0, 8.01, 0.5)])
        return [{"delay": float(d * T)} for d in grid]

    def bounds(self, context):
        return {"delay": (0.0, 20.0 * context.sample_time)}

    def apply(self, plant, params):
        extra = max(params["delay"], 0.0)
        if np.ndim(plant.delay) == 0:
            return plant.with_(delay=plant.delay + extra)
        return plant.with_(delay=tuple(float(d) + extra for d in plant.input_delays))

    def describe(self, params):
        return f"missing input delay of {params['delay'] * 1e3:.4g} ms"


class LowPass(Effect):
    """First-order actuator or sensor bandwidth: ``P -> P / (1 + s / w_c)``."""

    name = "low_pass"
    parameter_names = ("cutoff",)

    def initial_guesses(self, context):
        nyq = context.nyquist
        return [{"cutoff": float(c)} for c in nyq * np.geomspace(0.1, 8.0, 9)]

    def bounds(self, context):
        return {"cutoff": (0.01 * context.nyquist, 100.0 * context.nyquist)}

    def apply(self, plant, params):
        wc = TWO_PI * params["cutoff"]
        eye = np.eye(plant.n_inputs)  # one filter per input channel, alike
        return series_input(plant, -wc * eye, wc * eye, eye, 0.0 * eye)

    def describe(self, params):
        return (
            f"first-order low-pass (actuator or sensor bandwidth) at "
            f"{params['cutoff']:.4g} Hz"
        )


class MissingMode(Effect):
    """A lightly damped mode absent from the model, added in parallel.

    Parameters
    ----------
    n_starts : int, default=4
        Discrepancy-spectrum peaks tried as starting frequencies.
    max_damping : float, default=0.1
        Upper bound of the damping ratio (a lightly damped mode).
    """

    name = "missing_mode"
    parameter_names = ("frequency", "damping")
    nuisance_names = ("residue",)
    order = 1
    repeatable = True

    def __init__(self, *, n_starts: int = 4, max_damping: float = 0.1,
                 shape: tuple | None = None):
        self.n_starts = n_starts
        self.max_damping = max_damping
        self.shape = None if shape is None or tuple(shape) == (1, 1) else tuple(shape)
        if self.shape is not None:
            n_y, n_u = self.shape
            self.nuisance_names = (
                tuple(f"residue_{i}" for i in range(n_y))
                + tuple(f"input_angle_{j}" for j in range(1, n_u))
            )

    def expand(self, context):
        plant = context.plant
        if plant.is_siso or self.shape is not None:
            return [self]
        return [MissingMode(n_starts=self.n_starts, max_damping=self.max_damping,
                            shape=(plant.n_outputs, plant.n_inputs))]

    def initial_guesses(self, context):
        lowest = self.lowest_frequency(context)
        usable = np.where(context.frequencies >= lowest, context.discrepancy, 0.0)
        peaks = _spectrum_peaks(usable, self.n_starts)
        guesses = []
        for index in peaks:
            f0 = max(float(context.frequencies[index]), lowest)
            for zeta in (0.005, 0.015, 0.04):
                guesses.append({"frequency": f0, "damping": zeta,
                                **self._residue_guess(context, f0, zeta)})
        return guesses

    def _residue_guess(self, context, frequency, damping) -> dict:
        if self.shape is None:
            return {"residue": _mode_residue(context, frequency, damping)}
        c, b = _mode_shape_guess(context, frequency, damping)
        angles = _unit_vector_angles(b)
        guess = {f"residue_{i}": float(v) for i, v in enumerate(c)}
        guess.update({f"input_angle_{j + 1}": float(a) for j, a in enumerate(angles)})
        return guess

    def bounds(self, context):
        out = {
            "frequency": (self.lowest_frequency(context), 0.999 * context.nyquist),
            "damping": (1e-4, self.max_damping),
        }
        out.update({name: (-np.inf, np.inf) for name in self.nuisance_names})
        return out

    @staticmethod
    def lowest_frequency(context) -> float:
        """Ten bins above the lower edge of the compared band.

        A mode below the band acts there like a mass (gain) change; it must
        show its resonance to be named a mode.
        """
        f = np.sort(context.frequencies)
        spacing = float(np.median(np.diff(f))) if f.size > 1 else float(f[0])
        return float(f[0] + 10 * spacing)

    def apply(self, plant, params):
        if self.shape is None:
            return add_mode(plant, params["frequency"], params["damping"],
                            params["residue"], 0.0)
        n_y, n_u = self.shape
        c = np.array([params[f"residue_{i}"] for i in range(n_y)])
        angles = [params[f"input_angle_{j}"] for j in range(1, n_u)]
        return add_mode(plant, params["frequency"], params["damping"], c, 0.0,
                        input_vector=_unit_vector(angles))

    def __repr__(self):
        return "MissingMode()" if self.shape is None else (
            f"MissingMode(shape={self.shape})")

    def describe(self, params):
        return (
            f"missing mode at {params['frequency']:.4g} Hz with "
            f"{100 * params['damping']:.3g} % damping"
        )


class ModeShift(Effect):
    """A model mode at the wrong frequency or damping (its numerator kept).

    The catalogue entry expands into one candidate per lightly damped mode of
    the model (:meth:`expand`).
    """

    name = "mode_shift"
    parameter_names = ("frequency", "damping")
    order = 0

    def __init__(self, *, target: Resonance | None = None, max_shift: float = 0.3):
        self.target = target
        self.max_shift = max_shift

    def expand(self, context):
        if self.target is not None:
            return [self]
        modes = (context.resonances if context.modal_resonances is None
                 else context.modal_resonances)
        return [
            ModeShift(target=mode, max_shift=self.max_shift)
            for mode in modes
            if mode.frequency < context.nyquist and not _repeated(mode, modes)
        ]

    def label(self):
        if self.target is None:
            return self.name
        return f"{self.name}[{self.target.frequency:.4g} Hz]"

    def initial_guesses(self, context):
        f0, z0 = self.target.frequency, self.target.damping
        starts = [f0 * s for s in (1.0, 0.97, 1.03, 0.93, 1.07, 0.85, 1.15)]
        # a moved mode leaves a discrepancy peak at its new frequency
        for index in _spectrum_peaks(context.discrepancy, 6):
            f = float(context.frequencies[index])
            if abs(f / f0 - 1) < self.max_shift:
                starts.append(f)
        return [{"frequency": f, "damping": z0} for f in starts]

    def bounds(self, context):
        f0 = self.target.frequency
        return {
            "frequency": (f0 * (1 - self.max_shift), f0 * (1 + self.max_shift)),
            "damping": (1e-4, 0.5),
        }

    def apply(self, plant, params):
        if not plant.is_siso:
            return shift_mode(plant, self.target.frequency, self.target.damping,
                              params["frequency"], params["damping"])
        rest, b1, b0 = split_mode(plant, self.target.frequency, self.target.damping)
        return add_mode(rest, params["frequency"], params["damping"], b0, b1)

    def describe(self, params):
        f0 = self.target.frequency
        change = 100 * (params["frequency"] / f0 - 1)
        return (
            f"model mode at {f0:.4g} Hz is at {params['frequency']:.4g} Hz "
            f"({change:+.3g} %) with {100 * params['damping']:.3g} % damping "
            f"(model: {100 * self.target.damping:.3g} %)"
        )

    def __repr__(self):
        return f"ModeShift(target={self.target!r})"


class ModelError(Effect):
    """Unnamed low-order model error: a unit-DC-gain second-order filter.

    ``H(s) = (s^2/wz^2 + 2 zz s/wz + 1) / (s^2/wp^2 + 2 zp s/wp + 1)`` in series
    with the plant. Used when no catalogue effect explains the gap; it says
    where and how much the model is wrong, not why.
    """

    name = "model_error"
    parameter_names = ("zero_frequency", "zero_damping", "pole_frequency",
                       "pole_damping")
    named = False

    def initial_guesses(self, context):
        peaks = _spectrum_peaks(context.discrepancy, 3)
        guesses = []
        for index in peaks:
            f0 = float(context.frequencies[index])
            for ratio in (0.9, 1.1):
                guesses.append({"zero_frequency": f0 * ratio, "zero_damping": 0.3,
                                "pole_frequency": f0, "pole_damping": 0.3})
        return guesses

    def bounds(self, context):
        fmin = max(float(context.frequencies.min()), 1e-3)
        fmax = 10 * context.nyquist
        return {
            "zero_frequency": (fmin, fmax), "zero_damping": (1e-3, 2.0),
            "pole_frequency": (fmin, fmax), "pole_damping": (1e-3, 2.0),
        }

    def apply(self, plant, params):
        wz = TWO_PI * params["zero_frequency"]
        wp = TWO_PI * params["pole_frequency"]
        zz, zp = params["zero_damping"], params["pole_damping"]
        dc = wp**2 / wz**2
        # H = dc * (s^2 + 2 zz wz s + wz^2) / (s^2 + 2 zp wp s + wp^2)
        Af = np.array([[0.0, wp], [-wp, -2 * zp * wp]])
        Bf = np.array([[0.0], [1.0]])
        c1 = dc * (2 * zz * wz - 2 * zp * wp)
        c0 = dc * (wz**2 - wp**2)
        Cf = np.array([[c0 / wp, c1]])
        eye = np.eye(plant.n_inputs)  # the same filter on every input channel
        return series_input(plant, np.kron(Af, eye), np.kron(Bf, eye),
                            np.kron(Cf, eye), np.kron(np.array([[dc]]), eye))

    def describe(self, params):
        return (
            "unexplained model error (no catalogue effect fits): second-order "
            f"zeros at {params['zero_frequency']:.4g} Hz, poles at "
            f"{params['pole_frequency']:.4g} Hz"
        )


class _ChannelEffect(Effect):
    """An effect on one input or output channel of a MIMO plant.

    The catalogue entry (``channel=None``) expands into one candidate per
    channel; none for a single channel (SISO included), where the all-channel
    effect is the same model.
    """

    side: str = "input"  # or "output"

    def __init__(self, *, channel: int | None = None):
        self.channel = None if channel is None else int(channel)

    def _count(self, plant: ContinuousPlant) -> int:
        return plant.n_inputs if self.side == "input" else plant.n_outputs

    def check_channel(self, n_outputs: int, n_inputs: int) -> None:
        """Raise ``ValueError`` unless ``channel`` (if given) is one of the
        plant's ``n_inputs`` inputs (``n_outputs`` outputs for a sensor)."""
        count = n_inputs if self.side == "input" else n_outputs
        if self.channel is not None and not 0 <= self.channel < count:
            noun = self.side + ("" if count == 1 else "s")
            raise ValueError(
                f"{self!r}: the plant has {count} {noun}, and `channel` is "
                f"a 0-based index from 0 to {count - 1}. Pass an existing "
                f"channel, or {type(self).__name__}() for one candidate "
                "per channel.")

    def expand(self, context):
        count = self._count(context.plant)
        if self.channel is not None:
            self.check_channel(context.plant.n_outputs, context.plant.n_inputs)
            return [self]
        if count < 2:
            return []
        return [type(self)(channel=j) for j in range(count)]

    @property
    def channel_name(self) -> str:
        return f"{'u' if self.side == 'input' else 'y'}{self.channel}"

    def label(self):
        if self.channel is None:
            return self.name
        return f"{self.name}[{self.channel_name}]"

    def fixed_parameters(self):
        return {} if self.channel is None else {self.side: self.channel}

    def _entries(self, array: np.ndarray) -> np.ndarray:
        """The entries of a ``(n_y, n_u, K)`` array this channel touches."""
        return array[:, self.channel] if self.side == "input" else array[self.channel]

    def __repr__(self):
        return (f"{type(self).__name__}()" if self.channel is None
                else f"{type(self).__name__}(channel={self.channel})")


class InputGain(_ChannelEffect):
    """One actuator's gain: column ``input`` of ``P`` times ``gain`` (MIMO)."""

    name = "input_gain"
    parameter_names = ("gain",)
    parent = "gain"
    side = "input"

    def initial_guesses(self, context):
        guesses = [0.7, 0.9, 1.1, 1.4]
        ratio, weight = context.plant_ratio, context.plant_weight
        if ratio is not None and np.ndim(ratio) == 3:
            r, w = self._entries(ratio), self._entries(weight)
            if w.sum() > 0:
                estimate = float(np.sum(w * np.abs(r)) / np.sum(w))
                if np.isfinite(estimate) and 0.1 < estimate < 10:
                    guesses.insert(0, estimate)
        return [{"gain": g} for g in guesses]

    def bounds(self, context):
        return {"gain": (0.05, 20.0)}

    def apply(self, plant, params):
        scale = np.ones(plant.n_inputs)
        scale[self.channel] = params["gain"]
        return plant.with_(B=plant.B * scale, D=plant.D * scale)

    def describe(self, params):
        return (f"input {self.channel_name} (actuator) gain is "
                f"{params['gain']:.4g} times the model's")


class OutputGain(InputGain):
    """One sensor's scale: row ``output`` of ``P`` times ``gain`` (MIMO)."""

    name = "output_gain"
    side = "output"

    def apply(self, plant, params):
        scale = np.ones((plant.n_outputs, 1))
        scale[self.channel] = params["gain"]
        return plant.with_(C=plant.C * scale, D=plant.D * scale)

    def describe(self, params):
        return (f"output {self.channel_name} (sensor) gain is "
                f"{params['gain']:.4g} times the model's")


class InputLowPass(_ChannelEffect):
    """One actuator's bandwidth: input ``input`` through a first-order low-pass."""

    name = "input_low_pass"
    parameter_names = ("cutoff",)
    parent = "low_pass"
    side = "input"

    def initial_guesses(self, context):
        return LowPass().initial_guesses(context)

    def bounds(self, context):
        return LowPass().bounds(context)

    def apply(self, plant, params):
        wc = TWO_PI * params["cutoff"]
        m = plant.n_inputs
        pick = np.zeros((1, m))
        pick[0, self.channel] = 1.0
        return series_input(plant, np.array([[-wc]]), wc * pick, pick.T,
                            np.eye(m) - pick.T @ pick)

    def describe(self, params):
        return (f"first-order low-pass on input {self.channel_name} (actuator "
                f"bandwidth) at {params['cutoff']:.4g} Hz")


class InputDelay(_ChannelEffect):
    """One actuator's delay: input ``input`` delayed by ``delay`` seconds
    (fractional samples allowed), the other inputs as they are (MIMO)."""

    name = "input_delay"
    parameter_names = ("delay",)
    parent = "delay"
    side = "input"

    def initial_guesses(self, context):
        return Delay().initial_guesses(context)

    def bounds(self, context):
        return Delay().bounds(context)

    def apply(self, plant, params):
        delays = np.array(plant.input_delays)
        delays[self.channel] += max(params["delay"], 0.0)
        return plant.with_(delay=tuple(float(d) for d in delays))

    def describe(self, params):
        return (f"missing delay of {params['delay'] * 1e3:.4g} ms on input "
                f"{self.channel_name} (actuator)")


def default_effects() -> list[Effect]:
    """The default catalogue: gain, delay, low_pass, missing_mode, mode_shift,
    and per channel input_gain, output_gain, input_low_pass, input_delay
    (MIMO only: they expand to no candidate on a SISO plant)."""
    return [Gain(), Delay(), LowPass(), MissingMode(), ModeShift(), InputGain(),
            OutputGain(), InputLowPass(), InputDelay()]


# ---------------------------------------------------------------------------
# Model surgery (private helpers, also used by the hidden-effect generator)
# ---------------------------------------------------------------------------


def series_input(plant: ContinuousPlant, Af, Bf, Cf, Df) -> ContinuousPlant:
    """``plant`` preceded by the filter ``(Af, Bf, Cf, Df)`` at its input."""
    n, m = plant.n_states, Af.shape[0]
    A = np.block([[plant.A, plant.B @ Cf], [np.zeros((m, n)), Af]])
    B = np.vstack([plant.B @ Df, Bf])
    C = np.hstack([plant.C, plant.D @ Cf])
    D = plant.D @ Df
    return plant.with_(A=A, B=B, C=C, D=D)


def add_mode(plant: ContinuousPlant, frequency: float, damping: float,
             b0, b1, *, input_vector=None) -> ContinuousPlant:
    """``plant + (b1 s + b0) b^T / (s^2 + 2 damping w s + w^2)``, ``w = 2 pi f``.

    The mode is realised with states ``[w q, dq/dt]`` (well scaled). For a
    MIMO plant ``b0`` and ``b1`` may be vectors over the outputs and
    ``input_vector`` is ``b`` over the inputs (default: ones, SISO: 1).
    """
    w = TWO_PI * frequency
    m, n_y = plant.n_inputs, plant.n_outputs
    direction = (np.ones((1, m)) if input_vector is None
                 else np.asarray(input_vector, dtype=float).reshape(1, m))
    A = scipy.linalg.block_diag(plant.A, np.array([[0.0, w], [-w, -2 * damping * w]]))
    B = np.vstack([plant.B, np.zeros((1, m)), direction])
    b0 = np.broadcast_to(np.asarray(b0, dtype=float).reshape(-1), (n_y,))
    b1 = np.broadcast_to(np.asarray(b1, dtype=float).reshape(-1), (n_y,))
    C = np.hstack([plant.C, np.column_stack([b0 / w, b1])])
    return plant.with_(A=A, B=B, C=C)


def split_mode(plant: ContinuousPlant, frequency: float, damping: float):
    """Separate the pole pair nearest ``(frequency, damping)`` from ``plant``.

    Returns
    -------
    rest : ContinuousPlant
        The plant without the mode.
    b1, b0 : float
        The mode's numerator: it is ``(b1 s + b0) / (s^2 + 2 z w s + w^2)``.
    """
    rest, A11, B1, C1 = _separate_mode(plant, frequency, damping)
    b1 = float((C1 @ B1)[0, 0])
    b0 = float((C1 @ (A11 - np.trace(A11) * np.eye(2)) @ B1)[0, 0])
    return rest, b1, b0


def shift_mode(plant: ContinuousPlant, frequency: float, damping: float,
               new_frequency: float, new_damping: float) -> ContinuousPlant:
    """Move the mode nearest ``(frequency, damping)`` (any plant dimensions).

    The mode's 2x2 block ``A_m`` (isolated by :func:`_separate_mode`) becomes
    ``alpha A_m + beta I`` with the new pole pair (``alpha = Im p' / Im p``,
    ``beta = Re p' - alpha Re p``: same modal directions), and its input
    matrix ``B_m`` is divided by ``alpha``. The numerator ``s b1 + b0`` (matrices
    for MIMO) becomes ``s b1 / alpha + b0 - (beta / alpha) b1``: exactly kept
    when ``b1 = C_m B_m = 0`` (force to position).
    """
    rest, A11, B1, C1 = _separate_mode(plant, frequency, damping)
    pole = np.linalg.eigvals(A11)
    pole = pole[np.argmax(pole.imag)]
    w = TWO_PI * new_frequency
    zeta = min(max(new_damping, 0.0), 0.999999)
    new_pole = complex(-zeta * w, w * math.sqrt(1 - zeta**2))
    alpha = new_pole.imag / pole.imag
    beta = new_pole.real - alpha * pole.real
    A = scipy.linalg.block_diag(rest.A, alpha * A11 + beta * np.eye(2))
    B = np.vstack([rest.B, B1 / alpha])
    C = np.hstack([rest.C, C1])
    return plant.with_(A=A, B=B, C=C)


def _separate_mode(plant: ContinuousPlant, frequency: float, damping: float):
    """``(rest, A_m, B_m, C_m)``: the plant without the mode, and the mode."""
    w = TWO_PI * frequency
    target = complex(-damping * w, w * math.sqrt(max(1 - damping**2, 0.0)))
    poles = np.linalg.eigvals(plant.A)
    upper = poles[poles.imag > 0]
    if upper.size == 0:
        raise ValueError("the model has no complex pole pair to shift.")
    chosen = upper[np.argmin(np.abs(upper - target))]
    tol = 1e-6 * abs(chosen)

    def select(re, im):
        return np.abs(re + 1j * np.abs(im) - chosen) < tol

    T, Z, sdim = scipy.linalg.schur(plant.A, output="real", sort=select)
    if sdim != 2:
        raise ValueError(
            f"could not isolate the mode at {frequency:.4g} Hz (repeated pole)."
        )
    A11, A12, A22 = T[:2, :2], T[:2, 2:], T[2:, 2:]
    X = scipy.linalg.solve_sylvester(A11, -A22, -A12)
    n = plant.n_states
    Tm = np.eye(n)
    Tm[:2, 2:] = X
    Tinv = np.eye(n)
    Tinv[:2, 2:] = -X
    B = Tinv @ Z.T @ plant.B
    C = plant.C @ Z @ Tm
    B1, C1 = B[:2], C[:, :2]
    rest = plant.with_(A=A22, B=B[2:], C=C[:, 2:])
    return rest, A11, B1, C1


def _repeated(mode: Resonance, modes: list) -> bool:
    """Another pole pair at the same place (e.g. a symmetric suspension of a
    MIMO stage): the mode cannot be isolated and moved on its own."""
    return any(
        other.index != mode.index
        and abs(other.frequency - mode.frequency) <= 1e-6 * mode.frequency
        and abs(other.damping - mode.damping) <= 1e-6 * max(mode.damping, 1e-12)
        for other in modes
    )


def _spectrum_peaks(spectrum: np.ndarray, count: int) -> list[int]:
    """Indices of the ``count`` largest local maxima of ``spectrum``."""
    s = np.asarray(spectrum, dtype=float)
    if s.size < 3:
        return [int(np.argmax(s))] if s.size else []
    interior = (s[1:-1] >= s[:-2]) & (s[1:-1] >= s[2:])
    candidates = np.flatnonzero(interior) + 1
    if s[0] >= s[1]:
        candidates = np.append(candidates, 0)
    if s[-1] >= s[-2]:
        candidates = np.append(candidates, s.size - 1)
    order = candidates[np.argsort(s[candidates])[::-1]]
    picked: list[int] = []
    for index in order:
        if all(abs(index - p) > 3 for p in picked):
            picked.append(int(index))
        if len(picked) == count:
            break
    return picked


def _mode_residue(context: EffectContext, frequency: float, damping: float) -> float:
    """Weighted least-squares residue of a mode given its frequency and damping."""
    if context.residual is None or context.std is None:
        return 0.0
    unit = ContinuousPlant(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)),
                           np.zeros((1, 1)))
    shape = discrete_response(add_mode(unit, frequency, damping, 1.0, 0.0),
                              context.frequencies, context.sample_time)
    sens = context.sensitivity if context.sensitivity is not None else 1.0
    a = sens * shape / context.std
    b = context.residual / context.std
    denominator = float(np.sum(np.abs(a) ** 2))
    if denominator == 0 or not np.isfinite(denominator):
        return 0.0
    return float(np.real(np.sum(np.conj(a) * b)) / denominator)


def _mode_shape_guess(context: EffectContext, frequency: float, damping: float):
    """MIMO: ``(c, b)`` of the rank-one part of the least-squares residue.

    The real residue matrix ``R`` (n_y, n_u) of a mode with this frequency and
    damping is fitted to the whitened residual through the sensitivities
    (``dG = S_o m R S_i``, ``m`` the unit mode's response), then ``R ~ c b^T``
    by its largest singular triplet (``b`` of unit length).
    """
    residual, std = context.residual, context.std
    n_y, n_u, K = residual.shape
    if context.sensitivity is None:
        S_o = np.broadcast_to(np.eye(n_y)[..., None], (n_y, n_y, K))
        S_i = np.broadcast_to(np.eye(n_u)[..., None], (n_u, n_u, K))
    else:
        S_o, S_i = context.sensitivity
    unit = ContinuousPlant(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)),
                           np.zeros((1, 1)))
    shape = discrete_response(add_mode(unit, frequency, damping, 1.0, 0.0),
                              context.frequencies, context.sample_time)
    # design[i, j, k, a, b] = S_o[i, a, k] m(k) S_i[b, j, k] / std[i, j, k]
    design = np.einsum("iak,bjk->ijkab", S_o, S_i) * shape[None, None, :, None, None]
    design = design / std[..., None, None]
    design = design.reshape(-1, n_y * n_u)
    target = (residual / std).reshape(-1)
    a = np.concatenate([design.real, design.imag])
    y = np.concatenate([target.real, target.imag])
    good = np.all(np.isfinite(a), axis=1) & np.isfinite(y)
    if not np.any(good):
        return np.zeros(n_y), _unit_vector(np.zeros(n_u - 1))
    R = np.linalg.lstsq(a[good], y[good], rcond=None)[0].reshape(n_y, n_u)
    left, sv, right = np.linalg.svd(R)
    return sv[0] * left[:, 0], right[0]


def _unit_vector(angles) -> np.ndarray:
    """Unit vector from hyperspherical angles (``n - 1`` angles give ``n``)."""
    angles = np.asarray(angles, dtype=float).reshape(-1)
    vector = np.ones(angles.size + 1)
    for j, angle in enumerate(angles):
        vector[j] *= math.cos(angle)
        vector[j + 1:] *= math.sin(angle)
    return vector


def _unit_vector_angles(vector) -> np.ndarray:
    """The angles of :func:`_unit_vector` for a unit ``vector``."""
    v = np.asarray(vector, dtype=float).reshape(-1)
    v = v / max(float(np.linalg.norm(v)), 1e-300)
    angles = []
    for j in range(v.size - 1):
        tail = float(np.linalg.norm(v[j + 1:]))
        angle = math.atan2(tail, v[j])
        if j == v.size - 2 and v[-1] < 0:
            angle = -angle
        angles.append(angle)
    return np.array(angles)
