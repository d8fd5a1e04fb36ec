"""lrmfrf: fast-rate FRF identification beyond the Nyquist frequency.

Local rational modelling over the ``F`` aliased frequency bands of a slow-rate
output (van Haren et al., 2024), with the local polynomial and spectral
analysis baselines.
"""

from .estimators import LPMBeyondNyquist, LRMBeyondNyquist, SpectralAnalysis
from .exceptions import IdentifiabilityWarning
from .signals import multisine

__version__ = "0.1.0"

__all__ = [
    "LRMBeyondNyquist",
    "LPMBeyondNyquist",
    "SpectralAnalysis",
    "IdentifiabilityWarning",
    "multisine",
]
