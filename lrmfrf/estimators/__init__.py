"""FRF estimators: LRM and LPM beyond Nyquist, and the spectral-analysis baseline."""

from .local import LPMBeyondNyquist, LRMBeyondNyquist
from .spectral import SpectralAnalysis

__all__ = ["LRMBeyondNyquist", "LPMBeyondNyquist", "SpectralAnalysis"]
