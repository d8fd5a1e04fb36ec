"""Model-vs-measurement workflow: what is missing from my model?

:func:`diagnose` compares a plant model (python-control) with a measured,
beyond-Nyquist FRF, tests where they disagree beyond the calibrated noise,
names the missing effects from an open catalogue (:mod:`.effects`), adds them
to the model and reports the gap before and after (:class:`DiagnosisReport`).
"""

from .detect import Calibration, calibrate
from .effects import (
    Delay,
    Effect,
    EffectContext,
    Gain,
    InputDelay,
    InputGain,
    InputLowPass,
    LowPass,
    MissingMode,
    ModelError,
    ModeShift,
    OutputGain,
    default_effects,
)
from .report import DiagnosisReport, Finding
from .workflow import diagnose

__all__ = [
    "diagnose",
    "DiagnosisReport",
    "Finding",
    "Calibration",
    "calibrate",
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
