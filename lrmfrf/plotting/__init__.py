"""Bode plots with uncertainty bands, and FRF error plots (matplotlib).

matplotlib is an optional dependency (``pip install "lrmfrf[plot]"``); it is
imported when a plot is drawn, so ``import lrmfrf.plotting`` always works.

Every plotting function follows one convention:

- it accepts fitted estimators (``frequencies_`` in Hz, ``frf_``,
  ``frf_std_``, ``valid_``, ``downsampling_factor_``, ``sample_time_``),
  ``control.FrequencyResponseData`` objects (``omega`` in rad/s) or
  ``(frequencies_hz, frf)`` / ``(frequencies_hz, frf, std)`` tuples, passed
  as separate arguments, as one list, or as one mapping ``{label: estimate}``
  (the keys become the legend labels);
- it returns what it drew as matplotlib does: ``(fig, axes)``
  (:func:`plot_frf`: an array of the magnitude and phase Axes;
  :func:`plot_error`: one Axes).

Layout: :mod:`lrmfrf.plotting._curves` normalises the inputs to
:class:`FRFCurve` (no matplotlib), :mod:`lrmfrf.plotting._draw` draws them.
"""

from ._curves import FRFCurve, frf_curve
from ._draw import plot_error, plot_frf

__all__ = ["plot_frf", "plot_error", "frf_curve", "FRFCurve"]
