"""OAT-like wafer-stage test plant under internal feedback.

A python-control model of the prototype wafer stage (Over Actuated Test-rig,
OAT) of the paper's "Experimental Validation" section: the actuators run at the
fast sample time ``Ts = 0.5 ms``, the scanning sensor at ``F * Ts = 1.5 ms``
(``F = 3``), so the slow sampling frequency is 666.7 Hz and the slow Nyquist
frequency 333.3 Hz. The stage is in closed loop with a PID-plus-lead
controller, and the systems to identify are the equivalent closed-loop
systems of eq. (EquivalentSystems),

.. math::

    G_{y_4} = P_{y_4} (1 + C P_y)^{-1} : u_h \\mapsto y_4, \\qquad
    G_z = P_z (1 + C P_y)^{-1} : u_h \\mapsto z,

where ``u_h`` is a disturbance force added at the plant input. Here the
feedback output is the corner output itself, ``y = y4`` (the real OAT averages
the four corners; with one input the average only rescales the corner
participations, so a single corner keeps the model small).

Plant model (vertical direction, input ``u_h`` in N, outputs in m)::

    P_o(s) = 1 / (m s^2) + sum_i p_{o,i} / (m (s^2 + 2 zeta_i w_i s + w_i^2))

for outputs ``o`` in ``{y4, z}``. The participation ``p_{o,i}`` is the product
of the mode shape at the actuators and at output ``o``, normalised by the
rigid-body mass (dimensionless). Default parameters (:data:`DEFAULT_MODES`):

=====  ==========  ========  ===============  ==============  ==================
mode   f (Hz)      zeta      p_y4             p_z             note
=====  ==========  ========  ===============  ==============  ==================
rigid  0           0         1                1               mass m = 4 kg
1      170         0.010     +0.08            -0.90           torsion-like
2      235         0.008     +0.06            +0.25
3      440         0.012     +0.30            -1.20           > 333.3 Hz
4      610         0.015     +0.20            +0.80           > 333.3 Hz
=====  ==========  ========  ===============  ==============  ==================

Mode 3 (440 Hz) lies above the slow Nyquist frequency and aliases, about the
slow sampling frequency, to ``|440 - 666.7| = 226.7 Hz``, 8.3 Hz (5 bins of a
1200-sample record at 0.5 ms) from mode 2 at 235 Hz. Mode 4 (610 Hz) aliases
to 56.7 Hz, just above the closed-loop bandwidth. The corner sensor ``y4``
sits near the nodal lines of the flexible modes (small ``p_y4 > 0``), so the
feedback loop is gain-stabilised at every mode; the point of interest ``z``
sees the modes strongly and with sign changes, which gives ``G_z`` different
(anti-)resonances from ``G_y4`` - the reason the paper measures ``z``
directly.

Controller (:func:`lead_pid_controller`), crossover ``w_c = 2 pi f_c``::

    C(s) = k (1 + w_i / s) (1 + s / w_z) / (1 + s / w_p)
             * w_lp^2 / (s^2 + 2 zeta_lp w_lp s + w_lp^2)

with ``w_i = w_c / 6``, ``w_z = w_c / 4``, ``w_p = 4 w_c``, ``w_lp = 8 w_c``,
``zeta_lp = 0.6`` and ``k`` such that ``|C(j w_c)| / (m w_c^2) = 1``. It is
discretised with the Tustin method pre-warped at ``w_c``; the plant with a
zero-order hold (no extra computation delay). For the defaults
(``f_c = 40 Hz``) :func:`loop_margins` (``control.stability_margins`` on the
exact discrete loop ``C P_y4``) gives: gain crossover 39.6 Hz, phase margin
40.2 deg, gain margin 2.15 (6.7 dB, phase crossing at 172.8 Hz, mode 1),
lower gain margin 0.126 (-18.0 dB at 9.1 Hz; PID on a double integrator is
conditionally stable), modulus margin 0.46 (peak sensitivity 6.7 dB, at
171.6 Hz). See :meth:`WaferStage.margins`. The closed-loop resonances (poles
of ``G_y4`` and ``G_z``) are 171.2 Hz (zeta 0.67 %), 235.3 Hz (0.54 %),
439.3 Hz (1.14 %) and 609.9 Hz (1.51 %); the other closed-loop poles are
well damped (43.8 Hz, zeta 0.86; 326 Hz, 0.58; real at 35.2 and 5.7 Hz).

References
----------
The equivalent systems and the experimental settings follow the paper
``lrm-beyond-nyquist.tex``, section "Experimental Validation",
eq. (EquivalentSystems) and Table "Experimental settings".
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import control
import numpy as np
import scipy.linalg

from .._validation import check_sample_time, check_siso_system
from .loops import (
    Margins,
    _check_mass,
    _close_loop,
    _zoh,
    lead_pid_controller,
    loop_margins,
)

__all__ = [
    "DEFAULT_MODES",
    "Mode",
    "WaferStage",
    "closed_loop",
    "modal_plant",
    "wafer_stage",
]

_OUTPUT_NAMES = ("y4", "z")


@dataclass(frozen=True)
class Mode:
    """One lightly damped flexible mode of the wafer stage.

    Parameters
    ----------
    frequency_hz : float
        Undamped natural frequency in Hz, > 0.
    damping : float
        Relative damping ratio ``zeta``, in ``[0, 1)``.
    participation_y4 : float
        Modal participation in the chuck-corner output ``y4``
        (dimensionless, relative to the rigid-body mass).
    participation_z : float
        Modal participation in the point-of-interest output ``z``.
    """

    frequency_hz: float
    damping: float
    participation_y4: float
    participation_z: float

    def participation(self, output: str) -> float:
        """Participation of this mode in ``output`` (``"y4"`` or ``"z"``)."""
        return self.participation_y4 if output == "y4" else self.participation_z


DEFAULT_MODES: tuple[Mode, ...] = (
    Mode(170.0, 0.010, 0.08, -0.90),
    Mode(235.0, 0.008, 0.06, 0.25),
    Mode(440.0, 0.012, 0.30, -1.20),
    Mode(610.0, 0.015, 0.20, 0.80),
)
"""Default flexible modes of :func:`wafer_stage` (see the module docstring)."""


@dataclass(frozen=True, eq=False)
class WaferStage:
    """OAT-like wafer stage in closed loop; build it with :func:`wafer_stage`.

    Attributes
    ----------
    plant : control.StateSpace
        Discrete (ZOH) plant, 1 input ``u_h`` (N), 2 outputs ``[y4, z]`` (m).
    plant_continuous : control.StateSpace
        Continuous modal plant, same states, inputs and outputs.
    controller : control.StateSpace
        Discrete feedback controller, input ``y4`` (m), output force (N).
    G_y4 : control.StateSpace
        Discrete closed-loop system ``u_h -> y4``, eq. (EquivalentSystems).
    G_z : control.StateSpace
        Discrete closed-loop system ``u_h -> z``, eq. (EquivalentSystems).
    sample_time : float
        Fast sample time ``Ts`` in s.
    modes : tuple of Mode
        Flexible modes (after ``damping_scale``), in plant-state order.
    mass : float
        Rigid-body mass in kg.
    downsampling_factor : int
        Ratio ``F`` of the slow (sensor) to the fast sample time.
    suspension : (frequency_hz, damping) or None
        The suspension of the body (None: a free rigid body).
    """

    plant: control.StateSpace
    plant_continuous: control.StateSpace
    controller: control.StateSpace
    G_y4: control.StateSpace
    G_z: control.StateSpace
    sample_time: float
    modes: tuple[Mode, ...]
    mass: float
    downsampling_factor: int = 3
    suspension: tuple[float, float] | None = None

    @property
    def slow_nyquist_hz(self) -> float:
        """Nyquist frequency of the slow sensor, ``1 / (2 F Ts)`` in Hz."""
        return 1.0 / (2.0 * self.downsampling_factor * self.sample_time)

    @property
    def resonance_frequencies_hz(self) -> tuple[float, ...]:
        """Open-loop natural frequencies of the flexible modes in Hz."""
        return tuple(mode.frequency_hz for mode in self.modes)

    def margins(self) -> Margins:
        """Stability margins of the loop ``C P_y4``; see :func:`loop_margins`."""
        return loop_margins(self.plant[0, 0], self.controller)


def modal_plant(
    mass: float,
    modes: Sequence[Mode],
    *,
    outputs: Sequence[str] = _OUTPUT_NAMES,
    suspension: tuple[float, float] | None = None,
) -> control.StateSpace:
    """Continuous rigid-body-plus-modes plant in a well-scaled modal form.

    The state matrix is block diagonal with one 2x2 block per mode: the rigid
    body has states ``[position, velocity]`` (block ``[[0, 1], [0, 0]]``, or
    ``[[0, 1], [-w_s^2, -2 zeta_s w_s]]`` when suspended); flexible mode ``i``
    has states ``[w_i q_i, dq_i/dt]`` (scaled so both are velocities), block
    ``[[0, w_i], [-w_i, -2 zeta_i w_i]]``, input column ``[0, 1/m]`` and
    output row ``[p_{o,i} / w_i, 0]``. No transfer-function polynomials are
    formed.

    Parameters
    ----------
    mass : float
        Rigid-body mass in kg, > 0.
    modes : sequence of Mode
        Flexible modes; frequencies > 0 Hz, damping in ``[0, 1)``.
    outputs : sequence of str, default ("y4", "z")
        Outputs to include, in order; each ``"y4"`` or ``"z"``.
    suspension : (frequency_hz, damping), optional
        Suspend the body on a spring and damper: its ``1 / (m s^2)`` becomes
        ``1 / (m (s^2 + 2 zeta_s w_s s + w_s^2))``, a stable plant (needed for
        an open-loop experiment). Default: a free rigid body.

    Returns
    -------
    control.StateSpace
        Continuous system with ``2 + 2 * len(modes)`` states, 1 input (N) and
        ``len(outputs)`` outputs (m).
    """
    _check_mass(mass)
    modes = _check_modes(modes)
    suspension = _check_suspension(suspension)
    outputs = tuple(outputs)
    bad = [name for name in outputs if name not in _OUTPUT_NAMES]
    if bad or not outputs:
        raise ValueError(
            f"outputs must be a non-empty sequence of {_OUTPUT_NAMES}; got "
            f"{outputs!r}. Use e.g. outputs=('y4', 'z')."
        )
    blocks = [np.array([[0.0, 1.0], [0.0, 0.0]])]
    if suspension is not None:
        omega_s = 2.0 * math.pi * suspension[0]
        blocks[0][1] = [-(omega_s**2), -2.0 * suspension[1] * omega_s]
    columns = [np.array([0.0, 1.0 / mass])]
    rows = [np.ones((len(outputs), 1)) * np.array([[1.0, 0.0]])]
    state_names = ["rigid.position", "rigid.velocity"]
    for index, mode in enumerate(modes, start=1):
        omega = 2.0 * math.pi * mode.frequency_hz
        blocks.append(np.array([[0.0, omega], [-omega, -2.0 * mode.damping * omega]]))
        columns.append(np.array([0.0, 1.0 / mass]))
        participations = np.array([mode.participation(name) for name in outputs])
        rows.append(np.column_stack([participations / omega, np.zeros(len(outputs))]))
        state_names += [f"mode{index}.scaled_position", f"mode{index}.velocity"]
    return control.ss(
        scipy.linalg.block_diag(*blocks),
        np.concatenate(columns)[:, np.newaxis],
        np.hstack(rows),
        np.zeros((len(outputs), 1)),
        inputs=["u_h"],
        outputs=list(outputs),
        states=state_names,
        name="wafer_stage_plant",
    )


def closed_loop(
    plant_output_ss: control.StateSpace,
    plant_feedback_ss: control.StateSpace,
    controller: control.StateSpace | control.TransferFunction,
) -> control.StateSpace:
    """Closed-loop system ``P_o (1 + C P_y)^-1`` of eq. (EquivalentSystems).

    The disturbance ``u_h`` enters at the plant input, ``w = u_h - C y``,
    ``y = P_y w`` and the returned system maps ``u_h`` to ``P_o w``. Both plant
    outputs must come from the same realisation (same ``A`` and ``B``, e.g.
    ``plant[0, 0]`` and ``plant[1, 0]``) so that the closed loop has the plant
    states once and no uncontrollable copy of the rigid-body poles.

    Parameters
    ----------
    plant_output_ss : control.StateSpace
        Discrete SISO plant ``u -> o`` (the output to identify).
    plant_feedback_ss : control.StateSpace
        Discrete SISO plant ``u -> y`` (the measured feedback output).
    controller : control.StateSpace or control.TransferFunction
        Discrete SISO controller ``y -> force``, same sample time.

    Returns
    -------
    control.StateSpace
        Discrete SISO closed loop with states ``[plant; controller]``.

    Raises
    ------
    ValueError
        If the systems are not discrete SISO with one sample time, the plant
        realisations differ, the loop is algebraically singular, or the closed
        loop is not stable (a pole on or outside the unit circle).
    """
    systems = {
        "plant_output_ss": plant_output_ss,
        "plant_feedback_ss": plant_feedback_ss,
        "controller": controller,
    }
    for name, system in systems.items():
        check_siso_system(system, name, hint="plant[0, 0]")
    dts = {float(system.dt) for system in systems.values()}
    if len(dts) != 1:
        raise ValueError(
            f"all systems must share one sample time; got {sorted(dts)} s. "
            "Discretise them with the same sample time."
        )
    output = plant_output_ss
    feedback = plant_feedback_ss
    if not isinstance(output, control.StateSpace) or not isinstance(
        feedback, control.StateSpace
    ):
        raise TypeError(
            "plant_output_ss and plant_feedback_ss must be control.StateSpace "
            "channels of one plant realisation, e.g. plant[1, 0] and plant[0, 0]."
        )
    if output.A.shape != feedback.A.shape or not (
        np.array_equal(output.A, feedback.A) and np.array_equal(output.B, feedback.B)
    ):
        raise ValueError(
            "plant_output_ss and plant_feedback_ss must share A and B (two outputs "
            "of one plant realisation); pass e.g. plant[1, 0] and plant[0, 0]."
        )
    ctrl = control.ss(controller)
    return _close_loop(output, feedback, ctrl)


def wafer_stage(
    *,
    sample_time: float = 0.5e-3,
    mass: float = 4.0,
    modes: Sequence[Mode] | None = None,
    damping_scale: float = 1.0,
    controller_bandwidth: float = 40.0,
    downsampling_factor: int = 3,
    suspension: tuple[float, float] | None = None,
) -> WaferStage:
    """Build the OAT-like wafer stage and its closed-loop equivalent systems.

    Parameters
    ----------
    sample_time : float, default 0.5e-3
        Fast (actuator) sample time ``Ts`` in s.
    mass : float, default 4.0
        Rigid-body mass in kg.
    modes : sequence of Mode, optional
        Flexible modes; default :data:`DEFAULT_MODES` (170, 235, 440, 610 Hz).
    damping_scale : float, default 1.0
        Factor applied to every modal damping ratio (the scaled ratios must
        stay in ``[0, 1)``); use < 1 for lighter damping.
    controller_bandwidth : float, default 40.0
        Target crossover frequency of the feedback loop in Hz.
    downsampling_factor : int, default 3
        Slow-to-fast sample-time ratio ``F`` of the scanning sensor (stored;
        used by :attr:`WaferStage.slow_nyquist_hz`).
    suspension : (frequency_hz, damping), optional
        A suspended body instead of a free rigid body (see
        :func:`modal_plant`): the plant is then stable, so it can be
        identified in open loop. The controller is designed as for the free
        body.

    Returns
    -------
    WaferStage
        Plant, controller and the closed-loop systems ``G_y4`` and ``G_z``.

    Raises
    ------
    ValueError
        For non-physical parameters or a controller that does not stabilise
        the loop.

    Examples
    --------
    >>> stage = wafer_stage()
    >>> round(stage.slow_nyquist_hz, 1)
    333.3
    >>> stage.G_z.nstates
    14
    """
    check_sample_time(sample_time)
    if not (np.isfinite(damping_scale) and damping_scale >= 0):
        raise ValueError(
            f"damping_scale must be a finite number >= 0; got {damping_scale!r}."
        )
    if isinstance(downsampling_factor, bool) or not isinstance(
        downsampling_factor, (int, np.integer)
    ):
        raise TypeError(
            f"downsampling_factor must be an int; got {downsampling_factor!r}."
        )
    if downsampling_factor < 1:
        raise ValueError(
            f"downsampling_factor must be >= 1; got {downsampling_factor}."
        )
    base = DEFAULT_MODES if modes is None else _check_modes(modes)
    scaled = tuple(
        Mode(
            m.frequency_hz,
            m.damping * damping_scale,
            m.participation_y4,
            m.participation_z,
        )
        for m in base
    )
    if any(m.damping >= 1.0 for m in scaled):
        raise ValueError(
            f"damping_scale={damping_scale!r} pushes a damping ratio to >= 1; "
            "keep damping * damping_scale below 1."
        )
    suspension = _check_suspension(suspension)
    plant_continuous = modal_plant(mass, scaled, suspension=suspension)
    plant = _zoh(plant_continuous, sample_time)
    controller = lead_pid_controller(
        controller_bandwidth, mass, sample_time=sample_time
    )
    g_y4 = _close_loop(plant[0, 0], plant[0, 0], controller)
    g_z = _close_loop(plant[1, 0], plant[0, 0], controller)
    return WaferStage(
        plant=plant,
        plant_continuous=plant_continuous,
        controller=controller,
        G_y4=_named(g_y4, "G_y4", "y4"),
        G_z=_named(g_z, "G_z", "z"),
        sample_time=float(sample_time),
        modes=scaled,
        mass=float(mass),
        downsampling_factor=int(downsampling_factor),
        suspension=suspension,
    )


# ---------------------------------------------------------------------------
# Private helpers
# ---------------------------------------------------------------------------


def _check_suspension(suspension) -> tuple[float, float] | None:
    if suspension is None:
        return None
    try:
        frequency, damping = (float(v) for v in suspension)
    except (TypeError, ValueError):
        raise TypeError(
            "`suspension` must be a pair (frequency_hz, damping), e.g. (5.0, 0.1), "
            f"or None for a free rigid body; got {suspension!r}."
        ) from None
    if not (np.isfinite(frequency) and frequency > 0):
        raise ValueError(
            f"suspension frequency must be a finite value > 0 Hz; got {frequency!r}."
        )
    if not (np.isfinite(damping) and 0.0 < damping < 1.0):
        raise ValueError(
            f"suspension damping must be in (0, 1); got {damping!r}."
        )
    return frequency, damping


def _check_modes(modes: Sequence[Mode]) -> tuple[Mode, ...]:
    modes = tuple(modes)
    for index, mode in enumerate(modes):
        if not isinstance(mode, Mode):
            raise TypeError(
                f"modes[{index}] must be a Mode(frequency_hz, damping, "
                f"participation_y4, participation_z); got {mode!r}."
            )
        values = (
            mode.frequency_hz,
            mode.damping,
            mode.participation_y4,
            mode.participation_z,
        )
        if not all(np.isfinite(v) for v in values):
            raise ValueError(f"modes[{index}] has a non-finite value: {mode!r}.")
        if mode.frequency_hz <= 0:
            raise ValueError(
                f"modes[{index}].frequency_hz must be > 0 Hz; got "
                f"{mode.frequency_hz!r}. The rigid body is always included."
            )
        if not 0.0 <= mode.damping < 1.0:
            raise ValueError(
                f"modes[{index}].damping must be in [0, 1); got {mode.damping!r}."
            )
    return modes


def _named(system: control.StateSpace, name: str, output: str) -> control.StateSpace:
    return control.ss(
        system.A,
        system.B,
        system.C,
        system.D,
        system.dt,
        inputs=["u_h"],
        outputs=[output],
        name=name,
    )
