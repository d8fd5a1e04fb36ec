"""Feedback-loop tools shared by the test plants.

A lead-PID controller tuned on a rigid body, zero-order-hold discretisation,
state-space closed loops ``P (I + C P_y)^-1`` (eq. EquivalentSystems of the
paper) for SISO and MIMO plants, and stability margins of a discrete loop.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import control
import numpy as np
import scipy.linalg

from .._validation import check_sample_time

__all__ = ["Margins", "lead_pid_controller", "loop_margins"]


class Margins(NamedTuple):
    """Stability margins of a discrete feedback loop.

    Attributes
    ----------
    gain_margin : float
        Smallest factor > 1 by which the loop gain can grow before
        instability (absolute, not dB); ``inf`` if there is none.
    lower_gain_margin : float
        Largest factor < 1 to which the loop gain can shrink before
        instability (conditionally stable loops); 0 if there is none.
    phase_margin : float
        Smallest phase margin in degrees.
    crossover_hz : float
        Lowest gain-crossover frequency (``|L| = 1``) in Hz: the bandwidth.
    modulus_margin : float
        ``min |1 + L|`` over frequency (inverse peak sensitivity).
    """

    gain_margin: float
    lower_gain_margin: float
    phase_margin: float
    crossover_hz: float
    modulus_margin: float


def lead_pid_controller(
    bandwidth_hz: float,
    mass: float,
    *,
    sample_time: float,
) -> control.StateSpace:
    """Discrete PID controller with lead and second-order low-pass.

    ``C(s) = k (1 + w_i/s) (1 + s/w_z)/(1 + s/w_p) w_lp^2/(s^2 + 2 zeta_lp
    w_lp s + w_lp^2)`` with ``w_i = w_c/6``, ``w_z = w_c/4``, ``w_p = 4 w_c``,
    ``w_lp = 8 w_c``, ``zeta_lp = 0.6``, ``w_c = 2 pi bandwidth_hz``, and gain
    ``k`` chosen so that the loop with the rigid body ``1/(m s^2)`` crosses
    over at ``w_c``. Tustin discretisation pre-warped at ``w_c``.

    Parameters
    ----------
    bandwidth_hz : float
        Intended gain-crossover frequency in Hz, > 0 and below
        ``1 / (16 sample_time)`` (so the low-pass stays below Nyquist).
    mass : float
        Rigid-body mass in kg used to set the gain, > 0.
    sample_time : float
        Sample time in s, > 0.

    Returns
    -------
    control.StateSpace
        Discrete SISO controller (4 states), input position (m), output
        force (N), ``dt = sample_time``.
    """
    _check_mass(mass)
    check_sample_time(sample_time)
    if not (np.isfinite(bandwidth_hz) and 0.0 < bandwidth_hz < 1 / (16 * sample_time)):
        raise ValueError(
            f"bandwidth_hz must be in (0, {1 / (16 * sample_time):g}) Hz for "
            f"sample_time={sample_time:g} s; got {bandwidth_hz!r}. Choose a "
            "lower bandwidth or a shorter sample time."
        )
    omega_c = 2.0 * math.pi * bandwidth_hz
    s = control.tf("s")
    integrator = (s + omega_c / 6.0) / s
    lead = (1 + s / (omega_c / 4.0)) / (1 + s / (4.0 * omega_c))
    omega_lp = 8.0 * omega_c
    low_pass = omega_lp**2 / (s**2 + 2 * 0.6 * omega_lp * s + omega_lp**2)
    shape = integrator * lead * low_pass
    gain = mass * omega_c**2 / abs(shape(1j * omega_c))
    continuous = gain * shape
    discrete = control.sample_system(
        continuous, sample_time, method="tustin", prewarp_frequency=omega_c
    )
    return control.ss(discrete, inputs=["y4"], outputs=["force"], name="controller")


def loop_margins(
    plant_feedback_ss: control.StateSpace,
    controller: control.StateSpace | control.TransferFunction,
    *,
    n_frequencies: int = 6000,
) -> Margins:
    """Gain, phase and modulus margins of the discrete loop ``L = C P_y``.

    The loop frequency response is evaluated exactly from the state-space
    matrices on a logarithmic grid from 0.01 Hz to just below the Nyquist
    frequency and passed, as a ``control.FrequencyResponseData``, to
    :func:`control.stability_margins`. (Its polynomial method is unreliable for
    high-order, lightly damped discrete loops and falls back to a coarse
    grid.)

    Parameters
    ----------
    plant_feedback_ss : control.StateSpace
        Discrete SISO plant ``u -> y``.
    controller : control.StateSpace or control.TransferFunction
        Discrete SISO controller, same sample time.
    n_frequencies : int, default 6000
        Number of logarithmically spaced grid points (spacing 0.2 %: about
        8 points per half-power bandwidth of a 0.8 % damped mode; increase it
        for lighter damping). The margin calculation takes about 1 s.

    Returns
    -------
    Margins
        Smallest upward gain margin, largest downward gain margin (PID on a
        double integrator is conditionally stable), smallest phase margin,
        lowest gain-crossover frequency and modulus margin, all from
        ``control.stability_margins(..., returnall=True)``.
    """
    loop = control.series(control.ss(plant_feedback_ss), control.ss(controller))
    if not control.isdtime(loop, strict=True):
        raise ValueError(
            "loop_margins needs discrete-time systems; discretise them first."
        )
    nyquist_hz = 0.5 / float(loop.dt)
    frequencies_hz = np.geomspace(1e-2, nyquist_hz * (1 - 1e-6), n_frequencies)
    response = _discrete_response(loop, frequencies_hz)
    data = control.frd(response, 2.0 * math.pi * frequencies_hz)
    gains, phases, moduli, _, crossovers, _ = control.stability_margins(
        data, returnall=True
    )
    gains = np.asarray(gains, dtype=float)
    upper = gains[gains >= 1.0]
    lower = gains[gains < 1.0]
    return Margins(
        gain_margin=float(np.min(upper)) if upper.size else math.inf,
        lower_gain_margin=float(np.max(lower)) if lower.size else 0.0,
        phase_margin=float(np.min(phases)) if np.size(phases) else math.inf,
        crossover_hz=(
            float(np.min(crossovers)) / (2.0 * math.pi)
            if np.size(crossovers)
            else math.nan
        ),
        modulus_margin=float(np.min(moduli)) if np.size(moduli) else math.nan,
    )



# ---------------------------------------------------------------------------
# Private helpers
# ---------------------------------------------------------------------------


def _check_mass(mass: float) -> None:
    if not (np.isscalar(mass) and np.isfinite(mass) and mass > 0):
        raise ValueError(f"mass must be a finite number > 0 kg; got {mass!r}.")


def _zoh(system: control.StateSpace, sample_time: float) -> control.StateSpace:
    """Zero-order-hold discretisation via the augmented matrix exponential."""
    n_states, n_inputs = system.B.shape
    augmented = np.zeros((n_states + n_inputs, n_states + n_inputs))
    augmented[:n_states, :n_states] = system.A
    augmented[:n_states, n_states:] = system.B
    transition = scipy.linalg.expm(augmented * sample_time)
    return control.ss(
        transition[:n_states, :n_states],
        transition[:n_states, n_states:],
        system.C,
        system.D,
        sample_time,
        inputs=system.input_labels,
        outputs=system.output_labels,
        states=system.state_labels,
        name=f"{system.name}_zoh",
    )


def _close_loop(
    output: control.StateSpace,
    feedback: control.StateSpace,
    controller: control.StateSpace,
) -> control.StateSpace:
    """State-space closed loop ``r -> P_o (I + C P_y)^-1 r``, with checks.

    ``output`` (``P_o``) and ``feedback`` (``P_y``) are outputs of one plant
    realisation (same ``A`` and ``B``); the excitation ``r`` enters at the plant
    input, ``w = r - C y``. With ``S = (I + D_C D_y)^-1`` the algebraic loop gives
    ``w = S (r - D_C C_y x - C_C x_C)``. SISO is the 1 x 1 case.
    """
    a, b = output.A, output.B
    c_out, d_out = output.C, output.D
    c_fb, d_fb = feedback.C, feedback.D
    ac, bc, cc, dc = controller.A, controller.B, controller.C, controller.D
    loop = np.eye(b.shape[1]) + dc @ d_fb
    if np.linalg.cond(loop) > 1e12:
        raise ValueError(
            "the feedback loop is algebraically singular (I + D_C D_P is "
            "singular); add a delay or change the controller feedthrough."
        )
    s = np.linalg.inv(loop)
    a_cl = np.block(
        [
            [a - b @ s @ dc @ c_fb, -b @ s @ cc],
            [bc @ c_fb - bc @ d_fb @ s @ dc @ c_fb, ac - bc @ d_fb @ s @ cc],
        ]
    )
    b_cl = np.vstack([b @ s, bc @ d_fb @ s])
    c_cl = np.hstack([c_out - d_out @ s @ dc @ c_fb, -d_out @ s @ cc])
    d_cl = d_out @ s
    radius = float(np.max(np.abs(np.linalg.eigvals(a_cl))))
    if radius >= 1.0:
        raise ValueError(
            f"the controller does not stabilise the loop: largest closed-loop "
            f"pole magnitude is {radius:.6g} >= 1. Lower the controller "
            "bandwidth, or reduce the feedback-output participation "
            "(participation_y4) or raise the damping of the modes above it."
        )
    return control.ss(a_cl, b_cl, c_cl, d_cl, output.dt)


def _discrete_response(
    system: control.StateSpace, frequencies_hz: np.ndarray
) -> np.ndarray:
    """SISO ``C (z I - A)^-1 B + D`` at ``z = exp(j 2 pi f dt)``, shape (n_f,)."""
    from ..simulate import _resolvent_response

    z = np.exp(2j * math.pi * frequencies_hz * float(system.dt))
    A = np.asarray(system.A, dtype=float)
    return _resolvent_response(A, system.C[0], system.B[:, 0], z) + system.D[0, 0]
