"""The result of :func:`lrmfrf.diagnose`: findings, gaps, updated model, plot."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from .._validation import renamed_keyword

__all__ = ["Finding", "DiagnosisReport"]


@dataclass
class Finding:
    """One effect named (or flagged) by the workflow.

    Attributes
    ----------
    effect : str
        ``"gain"``, ``"delay"``, ``"low_pass"``, ``"missing_mode"``,
        ``"mode_shift"``, MIMO also ``"input_gain"``, ``"output_gain"``,
        ``"input_low_pass"``, ``"input_delay"`` (catalogue names), ``"model_error"`` (unnamed
        low-order fit) or ``"ambiguous"`` (several effects explain the gap
        about equally well; nothing was added to the model).
    parameters : dict
        The effect's parameters (see :mod:`lrmfrf.discrepancy.effects`); for
        ``"ambiguous"`` the best candidate's. A per-channel effect's channel
        comes first, as an int (``{"input": 1, "gain": 1.2}``: input ``u1``).
    band : tuple of float
        ``(low, high)`` in Hz holding 90 % of the improvement in fit.
    statistic : float
        Likelihood-ratio statistic ``(J_before - J_after) / c`` of the step
        that found the effect.
    p_value : float
        Its chi-square p-value.
    confidence_intervals : dict
        95 % intervals ``{name: (low, high)}`` from the joint refit.
    description : str
        Plain-text description.
    candidates : list of dict
        The ranked alternatives of the step: ``label``, ``bic``, ``parameters``
        (by BIC, except that an all-channel effect is put before a
        per-channel refinement less than ``ic_margin`` better, and named).
    nuisance : dict
        Other fitted values (e.g. the residue of a missing mode).
    """

    effect: str
    parameters: dict
    band: tuple
    statistic: float
    p_value: float
    confidence_intervals: dict = field(default_factory=dict)
    description: str = ""
    candidates: list = field(default_factory=list)
    nuisance: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "effect": self.effect,
            "parameters": _plain(self.parameters),
            "band_hz": _plain(list(self.band)),
            "statistic": _plain(self.statistic),
            "p_value": _plain(self.p_value),
            "confidence_intervals": {
                k: _plain(list(v)) for k, v in self.confidence_intervals.items()
            },
            "description": self.description,
            "candidates": _plain(self.candidates),
            "nuisance": _plain(self.nuisance),
        }


@dataclass
class DiagnosisReport:
    """What is missing from the model, with the evidence.

    Attributes
    ----------
    findings : list of Finding
        Empty when model and measurement agree within noise.
    gap_before, gap_after : float
        Whitened RMS gap ``sqrt(mean_k |G_meas - G_model|^2 / std_k^2)`` of the
        original and of the updated model, both with the same ``std`` (the
        attribute below: the estimator std times ``kappa``, its error scale
        calibrated at the updated model, estimator bias included), so that
        ``gap_before / gap_after`` is the shrink of the residual. About 1
        means agreement within noise. The tests of the original model
        (``p_value_before``, ``spectrum_before``, ``threshold_before``) use
        its own calibration (``calibration``), the null hypothesis there.
    updated_plant : control.StateSpace
        The plant with the accepted effects, discrete at the fast sample time
        (delays as shift-register states).
    plant : control.StateSpace
        The plant as given (discretised with ZOH if it was continuous).
    frequencies : ndarray of shape (K,)
        Compared bins in Hz.
    measured, std : ndarray of shape (K,) or (n_y, n_u, K)
        Measured FRF (complex) and its calibrated std ``kappa * std``
        (per entry for a MIMO system).
    model_before, model_after : ndarray of shape (K,) or (n_y, n_u, K), complex
        Model FRFs of the measured system (closed loop if a controller); the
        estimator bias is not added (it is counted in ``std``).
    spectrum_before, spectrum_after : ndarray of shape (K,)
        Discrepancy spectrum (moving mean of the whitened squared residual;
        for MIMO of its mean over the entries).
    threshold_before, threshold_after : float
        Level each spectrum exceeds by chance with probability ``alpha / 2``.
    p_value_before, p_value_after : float
        Global-test p-values.
    slow_nyquist : float
        Slow-rate Nyquist frequency in Hz.
    closed_loop : bool
        Whether a controller was given.
    calibration, calibration_after : Calibration
        Null behaviour of the estimator at the original and the updated model.
    settings : dict
        ``alpha``, ``ic_margin``, ``max_effects`` and calibration settings.
    skipped_candidates : list of str
        Labels of the candidate models (single effects or joint refits) the
        search skipped because their closed loop with the controller is
        unstable, so they cannot have produced the data; one entry per skip.
        Empty in open loop.
    """

    findings: list
    gap_before: float
    gap_after: float
    updated_plant: object
    plant: object
    frequencies: np.ndarray
    measured: np.ndarray
    std: np.ndarray
    model_before: np.ndarray
    model_after: np.ndarray
    spectrum_before: np.ndarray
    spectrum_after: np.ndarray
    threshold_before: float
    threshold_after: float
    p_value_before: float
    p_value_after: float
    slow_nyquist: float
    closed_loop: bool
    calibration: object = None
    calibration_after: object = None
    settings: dict = field(default_factory=dict)
    skipped_candidates: list = field(default_factory=list)

    @property
    def effects(self) -> list[str]:
        """Names of the findings, in order."""
        return [f.effect for f in self.findings]

    def summary(self) -> str:
        """Plain-text summary: verdict, gaps and one paragraph per finding."""
        lines = ["Model-vs-measurement diagnosis"]
        mimo = self.measured.ndim > 1
        loop = ("open loop (plant)" if not self.closed_loop
                else "closed loop P (I + C P)^-1" if mimo
                else "closed loop P/(1+CP)")
        lines.append(
            f"  compared: {loop}, {self.frequencies.size} bins up to "
            f"{self.frequencies.max():.4g} Hz (slow Nyquist {self.slow_nyquist:.4g} Hz)"
        )
        lines.append(
            f"  whitened RMS gap: before {self.gap_before:.3g} "
            f"(p = {self.p_value_before:.2g}), after {self.gap_after:.3g} "
            f"(p = {self.p_value_after:.2g}); about 1 = agreement within noise"
        )
        if self.skipped_candidates:
            labels = sorted(set(self.skipped_candidates))
            lines.append(
                f"  skipped: {len(self.skipped_candidates)} candidate model(s) whose "
                "closed loop with the controller is unstable (" + ", ".join(labels)
                + ")"
            )
        if not self.findings:
            lines.append("  no significant discrepancy: the model agrees with the "
                         "measurement within noise.")
            return "\n".join(lines)
        for i, finding in enumerate(self.findings, 1):
            lines.append(f"  {i}. {finding.effect}: {finding.description}")
            for name, value in finding.parameters.items():
                ci = finding.confidence_intervals.get(name)
                ci_text = f"  95% CI [{ci[0]:.4g}, {ci[1]:.4g}]" if ci else ""
                lines.append(f"       {name} = {value:.5g}{ci_text}")
            lines.append(
                f"       evidence: band {finding.band[0]:.4g}-{finding.band[1]:.4g} Hz,"
                f" LR statistic {finding.statistic:.3g} (p = {finding.p_value:.2g})"
            )
            if finding.effect == "ambiguous":
                alternatives = ", ".join(
                    f"{c['label']} (BIC {c['bic']:.1f})" for c in finding.candidates[:4]
                )
                lines.append(f"       alternatives: {alternatives}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-serialisable summary (no arrays of the full spectra)."""
        return {
            "findings": [f.to_dict() for f in self.findings],
            "gap_before": _plain(self.gap_before),
            "gap_after": _plain(self.gap_after),
            "p_value_before": _plain(self.p_value_before),
            "p_value_after": _plain(self.p_value_after),
            "slow_nyquist_hz": _plain(self.slow_nyquist),
            "closed_loop": self.closed_loop,
            "n_bins": int(self.frequencies.size),
            "calibration": _calibration_dict(self.calibration),
            "settings": _plain(self.settings),
            "skipped_candidates": list(self.skipped_candidates),
        }

    def plot(self, *, ax=None, units: str | None = None, axes=None,
             entry: tuple | None = None):
        """Bode plot with the +/-2 std band, and the discrepancy spectra.

        Magnitude in dB, phase unwrapped (continuous, in degrees; the measured
        points are placed within 180 degrees of the updated model), and the
        discrepancy spectrum before and after with its thresholds. The slow
        Nyquist frequency is the dotted vertical line (labelled in the legend).

        Parameters
        ----------
        ax : sequence of 3 matplotlib Axes, optional
            Magnitude, phase and discrepancy axes; created (sharing the
            frequency axis) if not given.
        units : str, optional
            Units of the plant (e.g. ``"m/N"``): the magnitude axis then reads
            "Magnitude [dB re 1 m/N]", else "Magnitude [dB]".
        axes : sequence of 3 matplotlib Axes, optional
            Deprecated name of ``ax`` (removed in the next release).
        entry : (int, int), optional
            MIMO: the ``(output, input)`` entry in the Bode panels (default
            ``(0, 0)``); the discrepancy panel is that of all entries.

        Returns
        -------
        fig : matplotlib.figure.Figure
        axes : ndarray of shape (3,) of matplotlib Axes
            Magnitude, phase and discrepancy axes.

        Notes
        -----
        Before issue 12 this returned a dict ``{"figure", "axes", ...}``; the
        returned pair still answers ``result["figure"]`` and the other old
        keys for one release, with a ``FutureWarning``.
        """
        ax = renamed_keyword(ax, axes, new="ax", old="axes")
        fig, axes = _diagnosis_axes(ax)
        mag, phase, disc = axes
        drawn = _draw_entry(mag, phase, self.frequencies, *self._entry(entry))
        self._draw_discrepancy(disc)
        for axis in axes:
            axis.axvline(self.slow_nyquist, color="0.3", ls=":", lw=1.2,
                         label=f"slow Nyquist {self.slow_nyquist:.4g} Hz"
                         if axis is mag else None)
            axis.set_xscale("log")
            axis.grid(True, which="major", alpha=0.4)
        mag.set_ylabel(f"Magnitude [dB re 1 {units}]" if units else "Magnitude [dB]")
        phase.set_ylabel("Phase [deg]")
        disc.set_xlabel("Frequency [Hz]")
        mag.legend(loc="best", fontsize="small")
        disc.legend(loc="best", fontsize="small")
        names = ", ".join(self.effects) or "no findings"
        where = "" if self.measured.ndim == 1 else (
            " (entry y{}/u{})".format(*(entry or (0, 0))))
        mag.set_title(f"Diagnosis: {names}{where}")
        drawn.update(figure=fig, axes=list(axes))
        return _PlotResult(fig, axes, drawn)

    def plot_grid(self, *, units: str | None = None, output_labels=None,
                  input_labels=None):
        """Bode plots of all FRF entries in one figure, and the discrepancy.

        The MIMO view of :meth:`plot`: for each output a row of magnitudes and
        a row of phases, one column per input (entry ``(o, i)`` is input ``i``
        to output ``o``), each with the measurement, its +/-2 std band, the
        model and the updated model as in :meth:`plot`; below, spanning the
        columns, the discrepancy spectra before and after (of all entries
        together: the tests and gaps are over all entries) with their
        thresholds. A SISO report gives a 1 x 1 grid.

        Parameters
        ----------
        units : str, optional
            Units of the plant, as in :meth:`plot`.
        output_labels, input_labels : sequence of str, optional
            Names of the outputs and inputs (e.g. the data's column names);
            default ``y0, y1, ...`` and ``u0, u1, ...``.

        Returns
        -------
        fig : matplotlib.figure.Figure
        axes : tuple ``(magnitude, phase, discrepancy)``
            ``magnitude`` and ``phase`` are arrays of Axes of shape
            ``(n_y, n_u)``; ``discrepancy`` is one Axes.
        """
        from ..plotting._draw import _pyplot

        n_y, n_u = (1, 1) if self.measured.ndim == 1 else self.measured.shape[:2]
        outputs = _channel_labels(output_labels, n_y, "y", "output_labels")
        inputs = _channel_labels(input_labels, n_u, "u", "input_labels")
        fig = _pyplot().figure(figsize=(3.4 * n_u + 1.6, 3.6 * n_y + 2.6),
                               layout="constrained")
        grid = fig.add_gridspec(2 * n_y + 1, n_u,
                                height_ratios=[1.25, 0.9] * n_y + [1.3])
        mag = np.empty((n_y, n_u), dtype=object)
        phase = np.empty((n_y, n_u), dtype=object)
        first = None
        for o, i in np.ndindex(n_y, n_u):
            mag[o, i] = fig.add_subplot(grid[2 * o, i], sharex=first)
            first = first or mag[o, i]
            phase[o, i] = fig.add_subplot(grid[2 * o + 1, i], sharex=first)
            _draw_entry(mag[o, i], phase[o, i], self.frequencies,
                        *self._entry(None if self.measured.ndim == 1 else (o, i)))
            mag[o, i].set_title(f"{inputs[i]} → {outputs[o]}", fontsize="small")
            mag[o, i].tick_params(labelbottom=False)
            if i == 0:
                mag[o, i].set_ylabel(f"|G| [dB re 1 {units}]" if units
                                     else "|G| [dB]")
                phase[o, i].set_ylabel("Phase [deg]")
            if o < n_y - 1:
                phase[o, i].tick_params(labelbottom=False)
        disc = fig.add_subplot(grid[2 * n_y, :], sharex=first)
        self._draw_discrepancy(disc)
        if n_y * n_u > 1:
            disc.set_title(f"Discrepancy spectrum: mean over the {n_y * n_u} "
                           "entries (what the tests use)", fontsize="small")
        for axis in (*mag.ravel(), *phase.ravel(), disc):
            axis.axvline(self.slow_nyquist, color="0.3", ls=":", lw=1.2,
                         label=f"slow Nyquist {self.slow_nyquist:.4g} Hz"
                         if axis is first else None)
            axis.set_xscale("log")
            axis.grid(True, which="major", alpha=0.4)
        disc.set_xlabel("Frequency [Hz]")
        handles, names = first.get_legend_handles_labels()
        fig.legend(handles, names, loc="outside lower center", ncol=len(names),
                   fontsize="small", markerscale=3)
        disc.legend(loc="best", fontsize="small")
        effects = ", ".join(self.effects) or "no findings"
        over = f" over all {n_y * n_u} entries" if n_y * n_u > 1 else ""
        fig.suptitle(f"Diagnosis: {effects} (whitened RMS gap{over}: "
                     f"{self.gap_before:.3g} before, {self.gap_after:.3g} after)")
        return fig, (mag, phase, disc)

    def _draw_discrepancy(self, disc) -> None:
        """The discrepancy spectra before and after, with their thresholds."""
        f = self.frequencies
        disc.plot(f, self.spectrum_before, "C0", label="before")
        disc.plot(f, self.spectrum_after, "C3", label="after")
        disc.axhline(self.threshold_before, color="C0", ls=":",
                     label="threshold before")
        disc.axhline(self.threshold_after, color="C3", ls=":",
                     label="threshold after")
        disc.set_yscale("log")
        disc.set_ylabel("Discrepancy [whitened |ΔG|²]")

    def _entry(self, entry):
        """The measured, std and model arrays of one entry (SISO: as they are)."""
        arrays = (self.measured, self.std, self.model_before, self.model_after)
        if self.measured.ndim == 1:
            if entry not in (None, (0, 0)):
                raise ValueError(f"`entry` is for MIMO reports; got {entry!r}.")
            return arrays
        i, j = (0, 0) if entry is None else entry
        n_y, n_u = self.measured.shape[:2]
        if not (0 <= i < n_y and 0 <= j < n_u):
            raise ValueError(
                f"`entry` must be (output, input) within ({n_y}, {n_u}); got {entry!r}."
            )
        return tuple(a[i, j] for a in arrays)


class _PlotResult(tuple):
    """``(fig, axes)``; the old dict keys still work for one release (warning)."""

    def __new__(cls, fig, axes, drawn):
        result = super().__new__(cls, (fig, axes))
        result._drawn = drawn
        return result

    def __getitem__(self, key):
        if isinstance(key, str):
            warnings.warn(
                "DiagnosisReport.plot() now returns (fig, axes) (issue 12); indexing "
                f"the result with {key!r} will stop working in the next release. "
                "Use fig, axes = report.plot().",
                FutureWarning, stacklevel=2,
            )
            return self._drawn[key]
        return super().__getitem__(key)


def _diagnosis_axes(ax):
    from ..plotting._draw import axes_column

    return axes_column(ax, ("magnitude", "phase", "discrepancy"), figsize=(8, 9))


def _draw_entry(mag, phase, f, measured, std, model_before, model_after) -> dict:
    """Magnitude (measurement, its +/-2 std band, model, updated model) and
    phase of one FRF entry; returns the drawn artists by name."""
    drawn = {}
    meas = np.abs(measured)
    low = np.maximum(meas - 2 * std, meas * 1e-3)
    drawn["band"] = mag.fill_between(f, _db(low), _db(meas + 2 * std),
                                     color="0.8", label="measurement ± 2 std")
    (drawn["measured"],) = mag.plot(f, _db(meas), "k.", ms=2,
                                    label="measurement")
    (drawn["before"],) = mag.plot(f, _db(np.abs(model_before)), "C0",
                                  label="model")
    (drawn["after"],) = mag.plot(f, _db(np.abs(model_after)), "C3--",
                                 label="updated model")
    curves = np.concatenate([_db(meas), _db(np.abs(model_before)),
                             _db(np.abs(model_after))])
    curves = curves[np.isfinite(curves)]
    if curves.size:  # the band's lower edge can dive far below the data
        mag.set_ylim(bottom=curves.min() - 20.0)
    reference = np.degrees(np.unwrap(np.angle(model_after)))
    before = _shifted_to(np.degrees(np.unwrap(np.angle(model_before))),
                         reference[0])
    phase.plot(f, _nearest_branch(np.degrees(np.angle(measured)),
                                  reference), "k.", ms=2)
    phase.plot(f, before, "C0")
    phase.plot(f, reference, "C3--")
    return drawn


def _channel_labels(labels, count: int, prefix: str, name: str) -> list[str]:
    """``labels`` as ``count`` strings, default ``prefix0, prefix1, ...``."""
    if labels is None:
        return [f"{prefix}{index}" for index in range(count)]
    labels = [str(label) for label in labels]
    if len(labels) != count:
        raise ValueError(f"`{name}` must have {count} names (one per channel); "
                         f"got {len(labels)}: {labels!r}.")
    return labels


def _db(magnitude: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(magnitude)


def _shifted_to(phase: np.ndarray, target: float) -> np.ndarray:
    """``phase`` moved by a whole number of turns to start near ``target`` (deg)."""
    return phase - 360.0 * np.round((phase[0] - target) / 360.0)


def _nearest_branch(phase: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Each phase (deg) moved by whole turns to within 180 deg of the reference."""
    return phase - 360.0 * np.round((phase - reference) / 360.0)


def _calibration_dict(calibration) -> dict | None:
    if calibration is None:
        return None
    return {
        "method": calibration.method,
        "n_runs": calibration.n_runs,
        "std_scale_rms": _plain(calibration.std_scale),
        "inflation": _plain(calibration.inflation),
        "spectrum_shape": _plain(calibration.spectrum_shape),
        "smoothing_bins": calibration.smoothing_bins,
    } | ({"n_entries": calibration.n_entries}
         if getattr(calibration, "n_entries", 1) > 1 else {})


def _plain(value):
    """Convert numpy scalars, arrays and tuples to JSON-friendly values."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    return value
