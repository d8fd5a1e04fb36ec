"""MIMO OAT-like wafer stage: four corner actuators, four encoders, one scanner.

The paper's prototype wafer stage (OAT) drives a plate with four vertical
actuators at its corners, reads four corner encoders at the fast rate and a
scanning sensor at a point of interest (POI) on the wafer at the slow rate, and
runs in closed loop. The identified systems are the equivalent closed-loop
systems of eq. (EquivalentSystems), here as a matrix,

.. math::

    G = P (I + C P_y)^{-1} : r \\mapsto [y_1, y_2, y_3, y_4, z],

with ``r`` (4 forces, N) added at the plant input, ``P`` the 5 x 4 plant, ``P_y``
its four encoder rows and ``C`` the 4 x 4 controller.

Geometry (m): corner ``j`` at ``(x_j, y_j)`` = ``(+a, +b), (-a, +b), (-a, -b),
(+a, -b)``; actuator ``j`` and encoder ``j`` are collocated there; the POI at
``poi``. Vertical displacement at ``(x, y)``: ``w = h + y theta_x - x theta_y``.

Plant (continuous, modal; inputs in N, outputs in m)::

    P_oj(s) = sum_d c_od g_dj / (M_d s^2)
              + sum_i phi_i(o) phi_i(j) / (m (s^2 + 2 zeta_i w_i s + w_i^2))

over the rigid degrees of freedom ``d`` = heave (mass ``m``), roll (inertia
``J_x``) and pitch (``J_y``), with ``g_dj = (1, y_j, -x_j)`` and ``c_od = (1,
y_o, -x_o)``, and over the flexible modes ``i`` with shapes ``phi_i`` given at
the corners and the POI (:class:`PlateMode`). Default modes
(:data:`DEFAULT_PLATE_MODES`), the frequencies of the SISO stage
(:func:`lrmfrf.plants.wafer_stage`):

=====  ======  =====================  ========  ======================
f Hz   zeta    corner pattern         |corner|  note
=====  ======  =====================  ========  ======================
170    0.010   torsion (+, -, +, -)   0.60      invisible to the loops
235    0.008   heave   (+, +, +, +)   0.25
440    0.012   pitch   (-, +, +, -)   0.55      > 333.3 Hz, aliases
610    0.015   roll    (+, +, -, -)   0.45      > 333.3 Hz, aliases
=====  ======  =====================  ========  ======================

Controller (decoupled, fast rate): the encoders are mapped to heave, roll and
pitch by ``T_y = pinv(C_r)`` (``C_r`` the 4 x 3 rigid output matrix), each
degree of freedom has the lead-PID of :func:`lrmfrf.plants.lead_pid_controller`
tuned on its own mass or inertia, and the three forces and torques go to the
four actuators through ``T_u = pinv(G_r)`` (minimum-norm over-actuation). The
corner patterns above make ``T_y P_y T_u`` exactly diagonal: each flexible mode
appears in at most one loop, and the torsion mode in none (the fourth actuator
direction is not controlled).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import control
import numpy as np
import scipy.linalg

from .._validation import check_sample_time
from .loops import (
    Margins,
    _check_mass,
    _close_loop,
    _zoh,
    lead_pid_controller,
    loop_margins,
)

__all__ = [
    "DEFAULT_PLATE_MODES",
    "MIMOWaferStage",
    "PlateMode",
    "mimo_wafer_stage",
    "plate_plant",
]

ENCODER_NAMES = ("y1", "y2", "y3", "y4")
OUTPUT_NAMES = ENCODER_NAMES + ("z",)
INPUT_NAMES = ("u1", "u2", "u3", "u4")
RIGID_DOFS = ("heave", "roll", "pitch")
_CORNER_SIGNS = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])


@dataclass(frozen=True)
class PlateMode:
    """One flexible mode of the plate, by its shape at the sensors.

    Parameters
    ----------
    frequency_hz : float
        Undamped natural frequency in Hz, > 0.
    damping : float
        Relative damping ratio, in ``[0, 1)``.
    corners : tuple of 4 float
        Mode shape at corners 1-4 (collocated actuators and encoders),
        dimensionless, mass-normalised with the plate mass.
    poi : float
        Mode shape at the point of interest.
    """

    frequency_hz: float
    damping: float
    corners: tuple[float, float, float, float]
    poi: float

    def shape(self) -> np.ndarray:
        """Shape at the five outputs ``[y1, y2, y3, y4, z]``, shape (5,)."""
        return np.array([*self.corners, self.poi], dtype=float)


DEFAULT_PLATE_MODES: tuple[PlateMode, ...] = (
    PlateMode(170.0, 0.010, (0.60, -0.60, 0.60, -0.60), -1.5),
    PlateMode(235.0, 0.008, (0.25, 0.25, 0.25, 0.25), 1.0),
    PlateMode(440.0, 0.012, (-0.55, 0.55, 0.55, -0.55), -2.2),
    PlateMode(610.0, 0.015, (0.45, 0.45, -0.45, -0.45), 1.8),
)
"""Default flexible modes of :func:`mimo_wafer_stage` (module docstring)."""


@dataclass(frozen=True, eq=False)
class MIMOWaferStage:
    """MIMO OAT-like stage in closed loop; build it with :func:`mimo_wafer_stage`.

    Attributes
    ----------
    plant : control.StateSpace
        Discrete (ZOH) plant, inputs ``u1..u4`` (N), outputs ``y1..y4, z`` (m).
    plant_continuous : control.StateSpace
        Continuous modal plant, same states, inputs and outputs.
    controller : control.StateSpace
        Discrete decoupled controller, inputs ``y1..y4`` (m), outputs ``u1..u4``
        (N), ``dt = sample_time``.
    G : control.StateSpace
        Discrete closed-loop system ``r -> [y1..y4, z]``, 5 x 4,
        eq. (EquivalentSystems).
    sample_time : float
        Fast sample time in s.
    modes : tuple of PlateMode
        Flexible modes (after ``damping_scale``), in plant-state order.
    mass : float
        Plate mass in kg.
    inertia : tuple of float
        Roll and pitch inertia ``(J_x, J_y)`` in kg m^2.
    half_width : tuple of float
        Corner coordinates ``(a, b)`` in m.
    poi : tuple of float
        Point-of-interest coordinates ``(x, y)`` in m.
    controller_bandwidth : float
        Target crossover frequency of each decoupled loop in Hz.
    downsampling_factor : int
        Slow-to-fast sample-time ratio ``F`` of the scanning sensor.
    """

    plant: control.StateSpace
    plant_continuous: control.StateSpace
    controller: control.StateSpace
    G: control.StateSpace
    sample_time: float
    modes: tuple[PlateMode, ...]
    mass: float
    inertia: tuple[float, float]
    half_width: tuple[float, float]
    poi: tuple[float, float]
    controller_bandwidth: float = 40.0
    downsampling_factor: int = 3

    #: Indices of the plant outputs the controller feeds back (the encoders).
    feedback_outputs: tuple[int, ...] = (0, 1, 2, 3)

    @property
    def slow_nyquist_hz(self) -> float:
        """Nyquist frequency of the slow sensor, ``1 / (2 F Ts)`` in Hz."""
        return 1.0 / (2.0 * self.downsampling_factor * self.sample_time)

    @property
    def sensor_decoupling(self) -> np.ndarray:
        """``T_y``, shape (3, 4): encoders to heave (m), roll, pitch (rad)."""
        return _decoupling(self.half_width)[0]

    @property
    def actuator_decoupling(self) -> np.ndarray:
        """``T_u``, shape (4, 3): heave force (N), roll and pitch torques (N m)
        to the four actuator forces (minimum norm)."""
        return _decoupling(self.half_width)[1]

    def controller_at(
        self, sample_time: float, *, bandwidth_hz: float | None = None
    ) -> control.StateSpace:
        """The stage's decoupled lead-PID design, discretised at another rate.

        E.g. ``stage.controller_at(F * stage.sample_time)`` is a controller
        that runs on the slow samples of the encoders (vision in the loop, see
        :func:`lrmfrf.simulate.simulate_slow_feedback`).

        Parameters
        ----------
        sample_time : float
            Controller sample time in s.
        bandwidth_hz : float, optional
            Crossover of each decoupled loop; default ``controller_bandwidth``
            (a slow loop usually needs a lower one for its phase margin).

        Returns
        -------
        control.StateSpace
            4 x 4, encoders in, actuator forces out, ``dt = sample_time``.
            Check the loop it closes (e.g. with
            :func:`lrmfrf.simulate.simulate_slow_feedback`, which refuses an
            unstable one).
        """
        check_sample_time(sample_time)
        bandwidth = self.controller_bandwidth if bandwidth_hz is None else bandwidth_hz
        if not (np.isfinite(bandwidth) and bandwidth > 0):
            raise ValueError(
                f"bandwidth_hz must be a positive number of Hz; got {bandwidth_hz!r}."
            )
        parts = _rigid_controllers(bandwidth, (self.mass, *self.inertia), sample_time)
        return _decoupled_controller(parts, *_decoupling(self.half_width), sample_time)

    def margins(self) -> dict[str, Margins]:
        """Margins of the three decoupled loops, ``{"heave": ..., "roll": ...,
        "pitch": ...}``.

        ``T_y P_y T_u`` is diagonal (module docstring), so breaking one loop
        with the others closed gives the same margins as each loop alone.
        """
        decoupled = _static(self.sensor_decoupling, self.sample_time) * (
            self.plant[list(self.feedback_outputs), :]
            * _static(self.actuator_decoupling, self.sample_time)
        )
        diagonal = _rigid_controllers(
            self.controller_bandwidth, (self.mass, *self.inertia), self.sample_time
        )
        return {
            dof: loop_margins(decoupled[d, d], diagonal[d])
            for d, dof in enumerate(RIGID_DOFS)
        }


def mimo_wafer_stage(
    *,
    sample_time: float = 0.5e-3,
    mass: float = 4.0,
    modes: Sequence[PlateMode] | None = None,
    damping_scale: float = 1.0,
    controller_bandwidth: float = 40.0,
    downsampling_factor: int = 3,
    half_width: tuple[float, float] = (0.15, 0.15),
    poi: tuple[float, float] = (0.06, -0.04),
) -> MIMOWaferStage:
    """Build the MIMO OAT-like stage and its closed-loop equivalent system.

    Parameters
    ----------
    sample_time : float, default 0.5e-3
        Fast (actuator and encoder) sample time in s.
    mass : float, default 4.0
        Plate mass in kg; the inertias are those of a uniform rectangular
        plate, ``J_x = m b^2 / 3``, ``J_y = m a^2 / 3``.
    modes : sequence of PlateMode, optional
        Flexible modes; default :data:`DEFAULT_PLATE_MODES`.
    damping_scale : float, default 1.0
        Factor applied to every modal damping ratio.
    controller_bandwidth : float, default 40.0
        Target crossover frequency of each decoupled loop in Hz.
    downsampling_factor : int, default 3
        Slow-to-fast ratio ``F`` of the scanning sensor (stored).
    half_width : tuple of float, default (0.15, 0.15)
        Corner coordinates ``(a, b)`` in m, both > 0.
    poi : tuple of float, default (0.06, -0.04)
        Point of interest ``(x, y)`` in m.

    Returns
    -------
    MIMOWaferStage

    Raises
    ------
    ValueError
        For non-physical parameters or a controller that does not stabilise
        the loop.

    Examples
    --------
    >>> stage = mimo_wafer_stage()
    >>> (stage.G.noutputs, stage.G.ninputs)
    (5, 4)
    """
    check_sample_time(sample_time)
    _check_mass(mass)
    half_width = _check_pair(half_width, "half_width", positive=True)
    poi = _check_pair(poi, "poi", positive=False)
    if not (np.isfinite(damping_scale) and damping_scale >= 0):
        raise ValueError(
            f"damping_scale must be a finite number >= 0; got {damping_scale!r}."
        )
    if isinstance(downsampling_factor, bool) or not isinstance(
        downsampling_factor, (int, np.integer)
    ) or downsampling_factor < 1:
        raise ValueError(
            f"downsampling_factor must be an int >= 1; got {downsampling_factor!r}."
        )
    base = DEFAULT_PLATE_MODES if modes is None else _check_plate_modes(modes)
    scaled = tuple(
        PlateMode(m.frequency_hz, m.damping * damping_scale, m.corners, m.poi)
        for m in base
    )
    if any(m.damping >= 1.0 for m in scaled):
        raise ValueError(
            f"damping_scale={damping_scale!r} pushes a damping ratio to >= 1; "
            "keep damping * damping_scale below 1."
        )
    inertia = (mass * half_width[1] ** 2 / 3.0, mass * half_width[0] ** 2 / 3.0)
    plant_continuous = plate_plant(mass, inertia, scaled, half_width, poi)
    plant = _zoh(plant_continuous, sample_time)
    parts = _rigid_controllers(controller_bandwidth, (mass, *inertia), sample_time)
    controller = _decoupled_controller(parts, *_decoupling(half_width), sample_time)
    closed = _close_loop(plant, plant[: len(ENCODER_NAMES), :], controller)
    G = control.ss(
        closed.A, closed.B, closed.C, closed.D, closed.dt,
        inputs=["r1", "r2", "r3", "r4"], outputs=list(OUTPUT_NAMES), name="G",
    )
    return MIMOWaferStage(
        plant=plant,
        plant_continuous=plant_continuous,
        controller=controller,
        G=G,
        sample_time=float(sample_time),
        modes=scaled,
        mass=float(mass),
        inertia=inertia,
        half_width=half_width,
        poi=poi,
        controller_bandwidth=float(controller_bandwidth),
        downsampling_factor=int(downsampling_factor),
    )


def plate_plant(
    mass: float,
    inertia: tuple[float, float],
    modes: Sequence[PlateMode],
    half_width: tuple[float, float],
    poi: tuple[float, float],
) -> control.StateSpace:
    """Continuous modal plant of the plate, 4 inputs and 5 outputs.

    Rigid degrees of freedom have states ``[position, velocity]`` (heave in m,
    roll and pitch in rad); flexible mode ``i`` has ``[w_i q_i, dq_i/dt]``,
    block ``[[0, w_i], [-w_i, -2 zeta_i w_i]]``, input row ``phi_i(j) / m`` and
    output column ``phi_i(o) / w_i``, as :func:`lrmfrf.plants.modal_plant`.

    Returns
    -------
    control.StateSpace
        Continuous system with ``6 + 2 len(modes)`` states.
    """
    corners = _corner_xy(half_width)
    outputs_xy = np.vstack([corners, np.asarray(poi, dtype=float)])
    gen_force = _rigid_rows(corners).T  # (3, 4)
    out_rows = _rigid_rows(outputs_xy)  # (5, 3)
    masses = (mass, inertia[0], inertia[1])
    blocks, b_rows, c_cols, names = [], [], [], []
    for d, dof in enumerate(RIGID_DOFS):
        blocks.append(np.array([[0.0, 1.0], [0.0, 0.0]]))
        b_rows.append(np.vstack([np.zeros(4), gen_force[d] / masses[d]]))
        c_cols.append(np.column_stack([out_rows[:, d], np.zeros(5)]))
        names += [f"{dof}.position", f"{dof}.velocity"]
    for index, mode in enumerate(modes, start=1):
        omega = 2.0 * math.pi * mode.frequency_hz
        blocks.append(np.array([[0.0, omega], [-omega, -2.0 * mode.damping * omega]]))
        corners_shape = np.asarray(mode.corners, dtype=float)
        b_rows.append(np.vstack([np.zeros(4), corners_shape / mass]))
        c_cols.append(np.column_stack([mode.shape() / omega, np.zeros(5)]))
        names += [f"mode{index}.scaled_position", f"mode{index}.velocity"]
    return control.ss(
        scipy.linalg.block_diag(*blocks),
        np.vstack(b_rows),
        np.hstack(c_cols),
        np.zeros((5, 4)),
        inputs=list(INPUT_NAMES),
        outputs=list(OUTPUT_NAMES),
        states=names,
        name="mimo_wafer_stage_plant",
    )


# ---------------------------------------------------------------------------
# Private helpers
# ---------------------------------------------------------------------------


def _corner_xy(half_width) -> np.ndarray:
    """Corner coordinates, shape (4, 2), in the order of the module docstring."""
    return _CORNER_SIGNS * np.asarray(half_width, dtype=float)


def _rigid_rows(points_xy: np.ndarray) -> np.ndarray:
    """Displacement per unit heave, roll, pitch at each point, shape (n, 3)."""
    points_xy = np.atleast_2d(points_xy)
    return np.column_stack(
        [np.ones(len(points_xy)), points_xy[:, 1], -points_xy[:, 0]]
    )


def _static(gain: np.ndarray, dt: float) -> control.StateSpace:
    gain = np.atleast_2d(gain)
    return control.ss(
        np.zeros((0, 0)), np.zeros((0, gain.shape[1])),
        np.zeros((gain.shape[0], 0)), gain, dt,
    )


def _decoupling(half_width) -> tuple[np.ndarray, np.ndarray]:
    """``(T_y, T_u)``: pseudo-inverses of the rigid output and input maps."""
    rows = _rigid_rows(_corner_xy(half_width))  # (4, 3)
    return np.linalg.pinv(rows), np.linalg.pinv(rows.T)


def _rigid_controllers(bandwidth_hz, masses, sample_time) -> list:
    """The lead-PIDs of heave, roll and pitch, each tuned on its mass/inertia."""
    return [
        lead_pid_controller(bandwidth_hz, m, sample_time=sample_time)
        for m in masses
    ]


def _decoupled_controller(parts, t_y, t_u, sample_time) -> control.StateSpace:
    """``T_u diag(C_heave, C_roll, C_pitch) T_y`` as one 4 x 4 state space."""
    A = scipy.linalg.block_diag(*[p.A for p in parts])
    B = scipy.linalg.block_diag(*[p.B for p in parts]) @ t_y
    C = t_u @ scipy.linalg.block_diag(*[p.C for p in parts])
    D = t_u @ np.diag([float(p.D[0, 0]) for p in parts]) @ t_y
    return control.ss(
        A, B, C, D, sample_time,
        inputs=list(ENCODER_NAMES), outputs=list(INPUT_NAMES), name="controller",
    )


def _check_pair(value, name: str, *, positive: bool) -> tuple[float, float]:
    pair = np.asarray(value, dtype=float) if np.ndim(value) == 1 else None
    if pair is None or pair.shape != (2,) or not np.all(np.isfinite(pair)) or (
        positive and np.any(pair <= 0)
    ):
        need = "two finite numbers > 0" if positive else "two finite numbers"
        raise ValueError(f"`{name}` must be {need} (x, y) in m; got {value!r}.")
    return (float(pair[0]), float(pair[1]))


def _check_plate_modes(modes) -> tuple[PlateMode, ...]:
    modes = tuple(modes)
    for index, mode in enumerate(modes):
        if not isinstance(mode, PlateMode):
            raise TypeError(
                f"modes[{index}] must be a PlateMode(frequency_hz, damping, "
                f"corners, poi); got {mode!r}."
            )
        values = np.array(
            [mode.frequency_hz, mode.damping, *np.ravel(mode.corners), mode.poi],
            dtype=float,
        )
        if len(np.ravel(mode.corners)) != 4 or not np.all(np.isfinite(values)):
            raise ValueError(
                f"modes[{index}] needs a finite frequency, damping, 4 corner "
                f"values and a POI value; got {mode!r}."
            )
        if mode.frequency_hz <= 0 or not 0.0 <= mode.damping < 1.0:
            raise ValueError(
                f"modes[{index}] needs frequency_hz > 0 and damping in [0, 1); "
                f"got {mode!r}."
            )
    return modes
