"""MIMO FRFs: an ``n_y x n_u`` grid of Bode magnitudes with std bands.

:func:`lrmfrf.plotting.plot_frf` draws here when an FRF has several inputs or
outputs (an estimator or result whose ``frf_`` has shape ``(n_y, n_u, K)``, or
a MIMO ``control.FrequencyResponseData``). Each channel is split into the
SISO :class:`~lrmfrf.plotting._curves.FRFCurve` the Bode plot uses; the phase
is not drawn in the grid (plot one channel for it).
"""

from __future__ import annotations

import numpy as np

from ._curves import FRFCurve, _is_lti, _true_curve, frf_curve

__all__ = ["is_mimo", "channel_curves", "plot_frf_grid"]


def is_mimo(obj) -> bool:
    """Whether ``obj`` is a MIMO FRF (3-D ``frf_`` or a MIMO FRD)."""
    if hasattr(obj, "frf_") and hasattr(obj, "frequencies_"):
        return np.ndim(obj.frf_) == 3
    if hasattr(obj, "omega") and (hasattr(obj, "frdata") or hasattr(obj, "fresp")):
        return _frd_data(obj).shape[:2] != (1, 1)
    return False


def channel_curves(obj):
    """Split an FRF into its channels.

    Returns
    -------
    curves : ndarray of FRFCurve, shape (n_y, n_u)
    output_labels, input_labels : list of str
        From ``output_labels``/``input_labels`` of an FRD or an estimator
        (``output_labels_``/``input_labels_``) when present, else ``y0, y1,
        ...`` and ``u0, u1, ...``.
    """
    if hasattr(obj, "frf_") and hasattr(obj, "frequencies_"):
        frf = np.asarray(obj.frf_)
        if frf.ndim == 1:
            frf_all = frf[None, None]
        else:
            frf_all = frf
        shape = frf_all.shape[:2]
        std = getattr(obj, "frf_std_", None)
        valid = getattr(obj, "valid_", None)
        curves = np.empty(shape, dtype=object)
        for o, i in np.ndindex(shape):
            view = _Channel(obj, o, i, frf.ndim == 1, std, valid)
            curves[o, i] = frf_curve(view)
        outputs = getattr(obj, "output_labels_", None)
        inputs = getattr(obj, "input_labels_", None)
    else:
        data = _frd_data(obj)
        shape = data.shape[:2]
        dt = getattr(obj, "dt", None)
        numeric = isinstance(dt, (int, float)) and not isinstance(dt, bool)
        sample_time = float(dt) if numeric and dt else None
        frequencies = np.asarray(obj.omega, dtype=float) / (2 * np.pi)
        curves = np.empty(shape, dtype=object)
        for o, i in np.ndindex(shape):
            curves[o, i] = FRFCurve(frequencies, data[o, i].astype(complex),
                                    None, None, sample_time)
        outputs = getattr(obj, "output_labels", None)
        inputs = getattr(obj, "input_labels", None)
    outputs = _labels(outputs, shape[0], "y")
    inputs = _labels(inputs, shape[1], "u")
    return curves, outputs, inputs


def plot_frf_grid(frfs, labels, *, true, ax, std_band, slow_nyquist, xscale,
                  max_points, title, legend, window, units):
    """Draw the grid; arguments as :func:`lrmfrf.plotting.plot_frf`."""
    from ._draw import (
        _draw_magnitude,
        _frequency_span,
        _plot_indices,
        _pyplot,
        _resolve_slow_nyquist,
    )

    split = [channel_curves(obj) for obj in frfs]
    shape = split[0][0].shape
    for (curves, _, _), label in zip(split, labels, strict=True):
        if curves.shape != shape:
            raise ValueError(
                f"All FRFs in a MIMO plot must have the same n_y x n_u = {shape}; "
                f"{label!r} has {curves.shape}."
            )
    outputs, inputs = split[0][1], split[0][2]
    fig, axes = _grid_axes(ax, shape, _pyplot)
    references = _true_grid(true, split[0][0], window)
    first_curves = [curves[0, 0] for curves, _, _ in split]
    nyquist = _resolve_slow_nyquist(slow_nyquist, first_curves)
    n_curves = len(split)
    for o, i in np.ndindex(shape):
        axis = axes[o, i]
        floors = []
        for index, ((curves, _, _), label) in enumerate(
                zip(split, labels, strict=True)):
            curve = curves[o, i]
            keep = _plot_indices(curve.frequencies, xscale, max_points, window)
            floor, _, _ = _draw_magnitude(
                axis, curve, keep, label, f"C{index}", std_band,
                zorder=2.0 + (n_curves - index) / (n_curves + 1),
                band_alpha=0.3 if index == 0 else 0.15)
            floors.append(floor)
        reference = None if references is None else references[o, i]
        if reference is not None:
            keep = _plot_indices(reference.frequencies, xscale, None, window)
            _draw_magnitude(axis, reference, keep, "true", "k", 0.0,
                            linestyle="--", zorder=3.5)
        low, high = _frequency_span([c[o, i] for c, _, _ in split], reference,
                                    xscale)
        if window is not None:
            low, high = window
        if nyquist is not None:
            if high > nyquist:
                axis.axvspan(nyquist, high, color="0.5", alpha=0.08, linewidth=0,
                             zorder=0)
            axis.axvline(nyquist, color="0.3", linestyle=":", linewidth=1.2,
                         label=f"slow Nyquist {nyquist:.4g} Hz")
        finite = [f for f in floors if np.isfinite(f)]
        if finite:
            axis.set_ylim(bottom=min(finite))
        axis.set_xscale(xscale)
        axis.grid(True, which="major", alpha=0.4)
        axis.grid(True, which="minor", alpha=0.15)
        if high > low:
            axis.set_xlim(low, high)
        axis.set_title(f"{inputs[i]} → {outputs[o]}", fontsize="small")
        if i == 0:
            axis.set_ylabel(f"|G| [dB re 1 {units}]" if units else "|G| [dB]")
        if o == shape[0] - 1:
            axis.set_xlabel("Frequency [Hz]")
    if legend != "none":
        handles, names = axes[0, 0].get_legend_handles_labels()
        if std_band > 0 and any(c[0, 0].std is not None for c, _, _ in split):
            from matplotlib.patches import Patch

            handles.append(Patch(color="0.5", alpha=0.35, linewidth=0))
            names.append(f"±{std_band:g} std (shaded)")
        if legend == "outside":
            fig.legend(handles, names, loc="outside right upper", fontsize="small")
        else:
            axes[0, 0].legend(handles, names, loc="best", fontsize="small")
    if title:
        fig.suptitle(title)
    return fig, axes


# ---------------------------------------------------------------------------
# Private helpers
# ---------------------------------------------------------------------------


class _Channel:
    """One channel of a MIMO estimate, with the estimator attributes that
    :func:`frf_curve` reads."""

    def __init__(self, est, o, i, siso, std, valid):
        pick = (lambda a: a) if siso else (lambda a: np.asarray(a)[o, i])
        self.frequencies_ = est.frequencies_
        self.frf_ = pick(est.frf_)
        if std is not None:
            self.frf_std_ = pick(std)
        if valid is not None:
            self.valid_ = pick(valid)
        for name in ("downsampling_factor_", "sample_time_", "n_samples_"):
            if hasattr(est, name):
                setattr(self, name, getattr(est, name))


def _frd_data(frd) -> np.ndarray:
    data = getattr(frd, "frdata", None)
    if data is None:
        data = frd.fresp
    data = np.asarray(data)
    return data if data.ndim == 3 else data[None, None]


def _labels(labels, count: int, prefix: str) -> list[str]:
    if labels is None or len(labels) != count:
        return [f"{prefix}{index}" for index in range(count)]
    return [str(label) for label in labels]


def _grid_axes(ax, shape, pyplot):
    if ax is None:
        fig, axes = pyplot().subplots(
            *shape, sharex=True, squeeze=False, layout="constrained",
            figsize=(2.8 * shape[1] + 2.0, 2.0 * shape[0] + 0.8))
        return fig, axes
    axes = np.asarray(ax, dtype=object)
    if axes.shape != shape:
        raise ValueError(
            f"`ax` for a MIMO FRF must be an array of Axes of shape (n_y, n_u) = "
            f"{shape}. Got shape {axes.shape}. Create it with "
            f"fig.subplots({shape[0]}, {shape[1]}, squeeze=False)."
        )
    return axes[0, 0].figure, axes


def _true_grid(true, curves, window):
    """Reference curves per channel, or None."""
    if true is None:
        return None
    shape = curves.shape
    references = np.empty(shape, dtype=object)
    if _is_lti(true):
        if (true.noutputs, true.ninputs) != shape:
            raise ValueError(
                f"The true system has {true.noutputs} outputs and {true.ninputs} "
                f"inputs; the FRF has {shape[0]} x {shape[1]}. Pass a matching "
                "system."
            )
        for o, i in np.ndindex(shape):
            references[o, i] = _true_curve(true[o, i], curves[o, i], window)
        return references
    if isinstance(true, np.ndarray):
        if true.shape != shape + curves[0, 0].frequencies.shape:
            raise ValueError(
                f"An array `true` for a MIMO FRF must have shape (n_y, n_u, K) = "
                f"{shape + curves[0, 0].frequencies.shape}. Got {true.shape}."
            )
        for o, i in np.ndindex(shape):
            references[o, i] = _true_curve(true[o, i], curves[o, i], window)
        return references
    split, _, _ = channel_curves(true)
    if split.shape != shape:
        raise ValueError(
            f"`true` has {split.shape[0]} x {split.shape[1]} channels; the FRF "
            f"has {shape[0]} x {shape[1]}."
        )
    return split
