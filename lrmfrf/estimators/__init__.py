"""FRF estimators: LRM and LPM beyond Nyquist, their closed-form selection, and the
spectral-analysis baseline."""

from .local import LPMBeyondNyquist, LRMBeyondNyquist
from .selection import LPMBeyondNyquistCV, LRMBeyondNyquistCV
from .spectral import SpectralAnalysis

__all__ = [
    "LRMBeyondNyquist",
    "LPMBeyondNyquist",
    "SpectralAnalysis",
    "LRMBeyondNyquistCV",
    "LPMBeyondNyquistCV",
]
