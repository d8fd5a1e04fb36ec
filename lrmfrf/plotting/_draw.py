"""Drawing: Bode plots with uncertainty bands and FRF error plots (matplotlib).

The inputs are normalised to :class:`~lrmfrf.plotting._curves.FRFCurve` by
:mod:`lrmfrf.plotting._curves`; this module lays out the axes, draws curves,
bands and the slow Nyquist frequency, and keeps the phase continuous.
matplotlib is imported only when a plot is drawn.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from ._curves import (
    FRFCurve,
    _estimate_curve,
    _resolve_slow_nyquist,
    _true_curve,
    _truth_on_grid,
    frf_collection,
    frf_curve,
)
from ._grid import is_mimo, plot_frf_grid

__all__ = ["plot_frf", "plot_error"]

logger = logging.getLogger(__name__)

_INSTALL_HINT = 'plotting needs matplotlib: pip install "lrmfrf[plot]"'


def plot_frf(
    *frfs,
    true=None,
    ax=None,
    std_band: float = 2.0,
    labels: Sequence[str] | None = None,
    slow_nyquist: float | bool | None = None,
    xscale: str = "log",
    max_points: int | None = None,
    title: str | None = None,
    phase: str = "unwrap",
    legend: str = "outside",
    freq_range: tuple[float, float] | None = None,
    units: str | None = None,
):
    """Bode plot (magnitude in dB, phase in degrees) with uncertainty bands.

    A MIMO FRF (an estimator or result whose ``frf_`` has shape ``(n_y, n_u,
    K)``, or a MIMO ``control.FrequencyResponseData``) is drawn as an ``n_y x
    n_u`` grid of Bode magnitudes with their std bands, one panel per channel
    titled ``input -> output`` (labels from the FRD's or the estimator's
    ``output_labels_``/``input_labels_`` when present, else ``y0..``/
    ``u0..``); the phase is not drawn there (``phase`` is ignored: plot one
    channel for it). ``true`` is then a MIMO system, FRD or ``(n_y, n_u, K)``
    array, and ``ax`` an array of Axes of shape ``(n_y, n_u)``.

    Parameters
    ----------
    *frfs : fitted estimators, control.FrequencyResponseData or tuples
        FRFs to draw (see :func:`frf_curve`), as separate arguments, as one
        list, or as one mapping ``{label: frf}`` (its keys are the labels);
        invalid bins leave gaps. The first is drawn on top, with the most
        opaque band.
    true : control LTI system, FRD, tuple or complex ndarray, optional
        Reference drawn as a black dashed line. A python-control system is
        evaluated on a dense grid (at ``z = exp(j 2 pi f Ts)`` if discrete); an
        array must lie on the first FRF's grid.
    ax : sequence of two matplotlib Axes, optional
        ``(magnitude_axes, phase_axes)`` to draw into; default a new figure.
    std_band : float, default=2.0
        Shade ``|G| +/- std_band * std`` (in dB; a lower edge at or below zero
        is drawn down to the bottom of the axes) and the matching phase band
        ``+/- arcsin(std_band * std / |G|)``. ``0`` draws no band.
    labels : sequence of str, optional
        Legend labels, one per FRF; default the class names (with a mapping,
        its keys).
    slow_nyquist : float, bool or None, default=None
        Frequency in Hz of the dotted vertical line marking the slow Nyquist
        frequency ``1/(2 F Ts)``; the band above it is lightly shaded.
        ``None`` takes it from the first FRF that knows it; ``False`` draws
        no line.
    xscale : {"log", "linear"}, default="log"
        Frequency axis scale; ``"log"`` leaves out 0 Hz.
    max_points : int, optional
        Draw at most about this many points per curve (log-spaced bins), for
        very long records.
    title : str, optional
        Figure title.
    phase : {"unwrap", "wrap"}, default="unwrap"
        ``"unwrap"``: a continuous phase. The reference (``true`` if given,
        else the first FRF) is unwrapped along frequency and every other
        curve is drawn within +/-180 degrees of it, so estimates and truth are
        compared without 360-degree jumps. ``"wrap"``: each phase in
        (-180, 180], breaks where it wraps.
    legend : {"outside", "inside", "none"}, default="outside"
        ``"outside"`` puts the legend to the right of the magnitude axes,
        where it cannot cover data; ``"inside"`` lets matplotlib choose a
        place in the axes.
    freq_range : (float, float), optional
        Draw only this band of frequencies in Hz (a zoom, e.g. on one
        resonance); the axis limits then fit the data in the band.
    units : str, optional
        Units of ``G`` (e.g. ``"m/N"``): the magnitude axis then reads
        "Magnitude [dB re 1 m/N]".

    Returns
    -------
    fig : matplotlib.figure.Figure
    axes : ndarray of shape (2,) or (n_y, n_u) of matplotlib Axes
        Magnitude and phase axes; for a MIMO FRF the grid of magnitude axes.

    Examples
    --------
    >>> import numpy as np
    >>> from lrmfrf.plotting import plot_frf
    >>> f = np.linspace(1, 100, 50)
    >>> fig, axes = plot_frf((f, 1 / (1 + 1j * f / 10), 0.01 * np.ones(50)),
    ...                      slow_nyquist=40.0)
    >>> [a.get_ylabel() for a in axes]
    ['Magnitude [dB]', 'Phase [deg]']
    """
    if not frfs:
        raise ValueError("plot_frf needs at least one FRF to draw. Pass an estimator.")
    frfs, labels = frf_collection(frfs, labels, what="FRF")
    if any(is_mimo(obj) for obj in frfs):
        return plot_frf_grid(
            frfs, labels, true=true, ax=ax, std_band=_check_std_band(std_band),
            slow_nyquist=slow_nyquist, xscale=_check_xscale(xscale),
            max_points=max_points, title=title, legend=_check_legend(legend),
            window=_check_freq_range(freq_range), units=units)
    curves = [frf_curve(obj) for obj in frfs]
    std_band = _check_std_band(std_band)
    if xscale not in ("log", "linear"):
        raise ValueError(f"xscale must be 'log' or 'linear'. Got {xscale!r}.")
    if phase not in ("unwrap", "wrap"):
        raise ValueError(f"phase must be 'unwrap' or 'wrap'. Got {phase!r}.")
    if legend not in ("outside", "inside", "none"):
        raise ValueError(
            f"legend must be 'outside', 'inside' or 'none'. Got {legend!r}."
        )
    window = _check_freq_range(freq_range)
    fig, axes = _bode_axes(ax)
    mag_ax, phase_ax = axes
    reference = None if true is None else _true_curve(true, curves[0], window)
    reference_phase = None
    if phase == "unwrap":
        basis = reference if reference is not None else curves[0]
        # Unwrapped over all frequencies, so a zoom shows the same phase values.
        reference_phase = _reference_phase(basis, xscale)
    floors, phases = [], []
    n_curves = len(curves)
    for index, (curve, label) in enumerate(zip(curves, labels, strict=True)):
        keep = _plot_indices(curve.frequencies, xscale, max_points, window)
        floor, shown = _draw_curve(
            axes, curve, keep, label, f"C{index}", std_band,
            reference_phase=reference_phase,
            zorder=2.0 + (n_curves - index) / (n_curves + 1),
            band_alpha=0.3 if index == 0 else 0.15,
        )
        floors.append(floor)
        phases.append(shown)
    if reference is not None:
        keep = _plot_indices(reference.frequencies, xscale, None, window)
        _, shown = _draw_curve(axes, reference, keep, "true", "k", 0.0,
                               linestyle="--", reference_phase=reference_phase,
                               zorder=3.5)
        phases.append(shown)
    low, high = _frequency_span(curves, reference, xscale)
    if window is not None:
        low, high = window
    nyquist = _resolve_slow_nyquist(slow_nyquist, curves)
    if nyquist is not None:
        for axis in axes:
            if high > nyquist:
                axis.axvspan(nyquist, high, color="0.5", alpha=0.08, linewidth=0,
                             zorder=0)
            axis.axvline(nyquist, color="0.3", linestyle=":", linewidth=1.2,
                         label=f"slow Nyquist {nyquist:.4g} Hz"
                         if axis is mag_ax else None)
    if std_band > 0 and any(c.std is not None for c in curves):
        from matplotlib.patches import Patch

        band_key = Patch(color="0.5", alpha=0.35, linewidth=0,
                         label=f"±{std_band:g} std (shaded)")
    else:
        band_key = None
    finite_floors = [f for f in floors if np.isfinite(f)]
    if finite_floors:
        mag_ax.set_ylim(bottom=min(finite_floors))
    for axis in axes:
        axis.set_xscale(xscale)
        axis.grid(True, which="major", alpha=0.4)
        axis.grid(True, which="minor", alpha=0.15)
    if high > low:
        phase_ax.set_xlim(low, high)  # axes share x when created here
        mag_ax.set_xlim(low, high)
    _phase_limits(phase_ax, phases, reference_phase, window,
                  wrapped=phase == "wrap")
    mag_ax.set_ylabel(f"Magnitude [dB re 1 {units}]" if units else "Magnitude [dB]")
    phase_ax.set_ylabel("Phase [deg]")
    phase_ax.set_xlabel("Frequency [Hz]")
    if legend != "none":
        handles, names = mag_ax.get_legend_handles_labels()
        if band_key is not None:
            handles.append(band_key)
            names.append(band_key.get_label())
        if legend == "outside":
            mag_ax.legend(handles, names, loc="upper left",
                          bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0,
                          fontsize="small")
        else:
            mag_ax.legend(handles, names, loc="best", fontsize="small")
    if title:
        mag_ax.set_title(title)
    return fig, axes


def plot_error(
    G_true,
    *estimates,
    frequencies=None,
    kind: str = "cumulative",
    labels: Sequence[str] | None = None,
    ax=None,
    slow_nyquist: float | bool | None = None,
    xscale: str = "log",
    yscale: str | None = None,
    units: str | None = None,
):
    """Plot the cumulative or relative error of FRF estimates.

    Parameters
    ----------
    G_true : complex ndarray of shape (n_freq,) or control LTI system
        True FRF on the estimates' grid, or a system evaluated on each
        estimate's own grid (needed when the grids differ, e.g. spectral
        analysis on its segment grid).
    *estimates : fitted estimators or complex ndarrays of shape (n_freq,)
        Estimates, as separate arguments, one list, or one mapping
        ``{label: estimate}``; arrays need ``frequencies``.
    frequencies : ndarray of shape (n_freq,), optional
        Frequencies in Hz of array estimates (and of an array ``G_true``).
    kind : {"cumulative", "relative"}, default="cumulative"
        ``"cumulative"``: the paper's eq. (CPSD),
        ``(1/N) sum_{k<=n} |G - Ghat|`` against frequency (see
        :func:`lrmfrf.metrics.cumulative_error`; ``N`` is the estimator's
        record length on the fast DFT grid, else ``2 (n_freq - 1)``; invalid
        bins add nothing). ``"relative"``: ``|G - Ghat| / |G|`` on a log axis
        (see :func:`lrmfrf.metrics.relative_error`).
    labels : sequence of str, optional
        Legend labels, one per estimate; default the class names (with a
        mapping, its keys).
    ax : matplotlib Axes, optional
        Axes to draw into; default a new figure.
    slow_nyquist : float, bool or None, default=None
        As in :func:`plot_frf`.
    xscale : {"log", "linear"}, default="log"
    yscale : {"linear", "log"}, optional
        Error axis scale; default linear for ``"cumulative"`` (as in the
        paper) and log for ``"relative"``.
    units : str, optional
        Units of ``G`` for the cumulative-error axis label, e.g. ``"m/N"``;
        default "units of G".

    Returns
    -------
    fig : matplotlib.figure.Figure
    ax : matplotlib Axes
        The error axes (one Axes, as ``plt.subplots()`` returns).

    Examples
    --------
    >>> import numpy as np
    >>> from lrmfrf.plotting import plot_error
    >>> f = np.linspace(0, 100, 11)
    >>> G = np.full(11, 2.0 + 0j)
    >>> fig, ax = plot_error(G, {"10 % high": 1.1 * G, "exact": G},
    ...                      frequencies=f, kind="relative", slow_nyquist=False)
    >>> [line.get_label() for line in ax.get_lines()]
    ['10 % high', 'exact']
    """
    if kind not in ("cumulative", "relative"):
        raise ValueError(
            f"kind must be 'cumulative' or 'relative'. Got {kind!r}."
        )
    if not estimates:
        raise ValueError("plot_error needs at least one estimate. Pass an estimator.")
    if xscale not in ("log", "linear"):
        raise ValueError(f"xscale must be 'log' or 'linear'. Got {xscale!r}.")
    if yscale is None:
        yscale = "log" if kind == "relative" else "linear"
    if yscale not in ("log", "linear"):
        raise ValueError(f"yscale must be 'log' or 'linear'. Got {yscale!r}.")
    from .. import metrics

    estimates, labels = frf_collection(estimates, labels, what="estimate")
    curves = [_estimate_curve(est, frequencies) for est in estimates]
    if ax is None:
        plt = _pyplot()
        fig, ax = plt.subplots(figsize=(8, 4), layout="constrained")
    else:
        fig = ax.figure
    for index, (curve, label) in enumerate(zip(curves, labels, strict=True)):
        truth = _truth_on_grid(G_true, curve, frequencies)
        if kind == "cumulative":
            error = metrics.cumulative_error(
                truth, curve.frf, curve.n_samples,
                valid=np.isfinite(curve.frf) & np.isfinite(truth),
            )
        else:
            error = metrics.relative_error(truth, curve.frf)
        keep = _plot_indices(curve.frequencies, xscale, None)
        ax.plot(curve.frequencies[keep], np.asarray(error)[keep], color=f"C{index}",
                label=label)
    nyquist = _resolve_slow_nyquist(slow_nyquist, curves)
    if nyquist is not None:
        ax.axvline(nyquist, color="0.3", linestyle=":", linewidth=1.2,
                   label=f"slow Nyquist {nyquist:.4g} Hz")
    ax.set_xscale(xscale)
    ax.set_yscale(yscale)
    if kind == "relative":
        ax.set_ylabel("Relative error |G - Ĝ| / |G| [-]")
    else:
        ax.set_ylabel(f"Cumulative error (1/N) Σ |G - Ĝ| [{units or 'units of G'}]")
    ax.set_xlabel("Frequency [Hz]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="best", fontsize="small")
    return fig, ax


# --------------------------------------------------------------------------
# Private helpers
# --------------------------------------------------------------------------


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise ImportError(_INSTALL_HINT) from exc
    return plt


def _bode_axes(ax):
    return axes_column(ax, ("magnitude", "phase"), figsize=(9.5, 6))


def axes_column(ax, panels: tuple[str, ...], *, figsize) -> tuple:
    """``(fig, axes)``: the user's ``ax`` (one Axes per panel, checked) or a new
    column of ``len(panels)`` Axes sharing the frequency axis."""
    count = len(panels)
    if ax is None:
        plt = _pyplot()
        fig, axes = plt.subplots(count, 1, sharex=True, figsize=figsize,
                                 layout="constrained")
        return fig, np.atleast_1d(np.asarray(axes))
    try:
        axes = np.asarray(list(ax), dtype=object)
    except TypeError:
        axes = np.asarray([ax], dtype=object)
    if axes.size != count:
        raise ValueError(
            f"`ax` must be {count} Axes ({', '.join(panels)}). Got {axes.size}. "
            f"Create them with fig.subplots({count}, 1, sharex=True)."
        )
    return axes[0].figure, axes


def _check_xscale(xscale: str) -> str:
    if xscale not in ("log", "linear"):
        raise ValueError(f"xscale must be 'log' or 'linear'. Got {xscale!r}.")
    return xscale


def _check_legend(legend: str) -> str:
    if legend not in ("outside", "inside", "none"):
        raise ValueError(
            f"legend must be 'outside', 'inside' or 'none'. Got {legend!r}."
        )
    return legend


def _check_std_band(std_band) -> float:
    try:
        value = float(std_band)
    except (TypeError, ValueError):
        value = np.nan
    if not np.isfinite(value) or value < 0:
        raise ValueError(
            f"std_band must be a non-negative number of standard deviations. Got "
            f"{std_band!r}. Use e.g. 2 (0 draws no band)."
        )
    return value


def _plot_indices(frequencies, xscale: str, max_points, window=None) -> np.ndarray:
    index = np.arange(frequencies.size)
    if xscale == "log":
        index = index[frequencies > 0]
    if window is not None:
        index = index[(frequencies[index] >= window[0])
                      & (frequencies[index] <= window[1])]
    if max_points is not None and index.size > max_points:
        if xscale == "log":
            picks = np.geomspace(1, index.size, int(max_points)) - 1
        else:
            picks = np.linspace(0, index.size - 1, int(max_points))
        index = index[np.unique(np.round(picks).astype(int))]
    return index


def _check_freq_range(freq_range):
    if freq_range is None:
        return None
    try:
        low, high = (float(v) for v in freq_range)
    except (TypeError, ValueError):
        low = high = np.nan
    if not (np.isfinite(low) and np.isfinite(high) and 0 <= low < high):
        raise ValueError(
            f"freq_range must be two frequencies in Hz, 0 <= low < high. Got "
            f"{freq_range!r}."
        )
    return low, high


def _draw_curve(axes, curve: FRFCurve, keep, label, color, std_band,
                linestyle="-", reference_phase=None, zorder=2.0, band_alpha=0.25):
    """Draw one curve and its bands.

    Returns a floor for the magnitude axis and the phase as drawn (degrees).
    """
    mag_ax, phase_ax = axes
    freq = curve.frequencies[keep]
    frf = curve.frf[keep]
    phase = np.angle(frf, deg=True)
    if reference_phase is not None:
        phase = _phase_near(freq, phase, *reference_phase)
    phase[~np.isfinite(frf)] = np.nan
    floor, band, ratio = _draw_magnitude(
        mag_ax, curve, keep, label, color, std_band, linestyle=linestyle,
        zorder=zorder, band_alpha=band_alpha)
    phase_ax.plot(*_break_wraps(freq, phase), color=color, linestyle=linestyle,
                  linewidth=1.0, zorder=zorder)
    if band is None:
        return floor, phase
    with np.errstate(invalid="ignore"):
        half_width = np.where(ratio < 1, np.degrees(np.arcsin(ratio)), 180.0)
    phase_band = band.copy()
    phase_band[np.flatnonzero(np.abs(np.diff(phase)) > 180.0) + 1] = False
    phase_ax.fill_between(freq, phase - half_width, phase + half_width,
                          where=phase_band, color=color, alpha=band_alpha,
                          linewidth=0, zorder=zorder - 1.5)
    return floor, phase


def _draw_magnitude(mag_ax, curve: FRFCurve, keep, label, color, std_band,
                    linestyle="-", zorder=2.0, band_alpha=0.25):
    """Draw one magnitude curve (dB) and its band ``|G| +/- std_band std``.

    Returns a floor for the axis, where the band is drawn (``None`` if no band
    or no finite point) and ``std_band std / |G|`` clipped to [0, 1].
    """
    freq = curve.frequencies[keep]
    magnitude = np.abs(curve.frf[keep])
    with np.errstate(divide="ignore", invalid="ignore"):
        mag_db = 20 * np.log10(magnitude)
    mag_ax.plot(freq, mag_db, color=color, linestyle=linestyle, linewidth=1.0,
                label=label, zorder=zorder)
    finite = mag_db[np.isfinite(mag_db)]
    if finite.size == 0:
        return np.nan, None, None
    floor = float(finite.min()) - 10.0
    if curve.std is None or std_band == 0:
        return floor, None, None
    spread = std_band * curve.std[keep]
    with np.errstate(divide="ignore", invalid="ignore"):
        upper = 20 * np.log10(magnitude + spread)
        lower = np.where(
            magnitude > spread, 20 * np.log10(magnitude - spread), floor - 10.0
        )
        ratio = np.clip(spread / magnitude, 0.0, 1.0)
    band = np.isfinite(upper) & np.isfinite(spread)
    mag_ax.fill_between(freq, lower, upper, where=band, color=color,
                        alpha=band_alpha, linewidth=0, zorder=zorder - 1.5)
    return floor, band, ratio


def _reference_phase(curve: FRFCurve, xscale: str):
    """Unwrapped phase (degrees) of ``curve`` on its reliable bins.

    Reliable: finite, and (when a std is known) ``std < 0.3 |G|``, a phase
    uncertainty below about 17 degrees. Unwrapping only across reliable bins
    keeps noise from adding spurious multiples of 360 degrees. Returns
    ``(frequencies, phase)``, possibly empty.
    """
    keep = _plot_indices(curve.frequencies, xscale, None)
    frf = curve.frf[keep]
    reliable = np.isfinite(frf) & (np.abs(frf) > 0)
    if curve.std is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            reliable &= curve.std[keep] < 0.3 * np.abs(frf)
    if not reliable.any():  # nothing trustworthy: unwrap what there is
        reliable = np.isfinite(frf)
    freq = curve.frequencies[keep][reliable]
    unwrapped = np.degrees(np.unwrap(np.angle(frf[reliable])))
    return freq, unwrapped


def _phase_near(freq, phase, ref_freq, ref_phase):
    """Shift each phase by a multiple of 360 deg to within 180 deg of a reference.

    The reference (unwrapped, on ``ref_freq``) is interpolated linearly at
    ``freq``; on the reference's own bins the result is the reference itself.
    """
    if ref_freq.size == 0:
        return phase
    target = np.interp(freq, ref_freq, ref_phase)
    return target + (phase - target + 180.0) % 360.0 - 180.0


def _phase_limits(phase_ax, phases, reference_phase, window, *,
                  wrapped: bool) -> None:
    """Phase axis limits and ticks (multiples of 90 degrees).

    Unwrapped: the reference's range plus 45 degrees on each side (estimates
    further away than that are clipped: they are far off anyway); without a
    reference, the range of the drawn curves.
    """
    from matplotlib.ticker import MultipleLocator

    if wrapped:
        phase_ax.set_ylim(-200, 200)
        phase_ax.yaxis.set_major_locator(MultipleLocator(90))
        return
    if reference_phase is not None and reference_phase[1].size:
        ref_freq, values = reference_phase
        if window is not None:
            inside = (ref_freq >= window[0]) & (ref_freq <= window[1])
            values = values[inside] if inside.any() else np.interp(
                np.asarray(window), ref_freq, values)
        margin = 45.0
    else:
        values = np.concatenate([np.ravel(p) for p in phases]) if phases else []
        margin = 0.0
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    if values.size == 0:
        phase_ax.set_ylim(-200, 200)
        return
    low = 90.0 * np.floor((values.min() - margin) / 90.0) - 10.0
    high = 90.0 * np.ceil((values.max() + margin) / 90.0) + 10.0
    phase_ax.set_ylim(low, high)
    step = 90.0 if high - low <= 760 else 180.0 * np.ceil((high - low) / 1440.0)
    phase_ax.yaxis.set_major_locator(MultipleLocator(step))


def _frequency_span(curves, reference, xscale: str) -> tuple[float, float]:
    """Smallest and largest drawn frequency (positive ones on a log axis)."""
    grids = [c.frequencies for c in curves]
    if reference is not None:
        grids.append(reference.frequencies)
    values = np.concatenate([np.asarray(g, dtype=float) for g in grids])
    values = values[np.isfinite(values)]
    if xscale == "log":
        values = values[values > 0]
    if values.size == 0:
        return 0.0, 0.0
    return float(values.min()), float(values.max())


def _break_wraps(freq: np.ndarray, phase: np.ndarray):
    """Insert NaN where the phase jumps by more than 180 degrees."""
    jumps = np.flatnonzero(np.abs(np.diff(phase)) > 180.0) + 1
    return np.insert(freq, jumps, np.nan), np.insert(phase, jumps, np.nan)
