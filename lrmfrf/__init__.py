"""lrmfrf: fast-rate FRF identification beyond the Nyquist frequency.

Local rational modelling over the ``F`` aliased frequency bands of a slow-rate
output (van Haren et al., 2024), with the local polynomial and spectral
analysis baselines, an OAT-like wafer-stage simulator and a model-discrepancy
workflow.

Public names are imported lazily (PEP 562), so the command line starts fast.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_PUBLIC = {
    "LRMBeyondNyquist": "lrmfrf.estimators",
    "LPMBeyondNyquist": "lrmfrf.estimators",
    "SpectralAnalysis": "lrmfrf.estimators",
    "LRMBeyondNyquistCV": "lrmfrf.estimators",
    "LPMBeyondNyquistCV": "lrmfrf.estimators",
    "fit_many": "lrmfrf.parallel",
    "diagnose": "lrmfrf.discrepancy",
    "IdentifiabilityWarning": "lrmfrf.exceptions",
    "multisine": "lrmfrf.signals",
    "plant_from_closed_loop": "lrmfrf.closed_loop",
    "wafer_stage": "lrmfrf.plants",
}

__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'lrmfrf' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
