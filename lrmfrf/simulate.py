"""Fast, exact simulation of discrete state-space systems with a slow sensor.

:func:`simulate` runs a finite record ``u_h -> y_h`` of a discrete
``control.StateSpace`` system, including its real transient (the system is at
rest before the record unless ``x0`` is given), downsamples the output,
``y_l(m) = y_h(m F)``, and adds white measurement noise at the slow rate. The
simulation is exact (a modal decomposition of the state recursion, no
transfer-function polynomials) and runs 1e6 samples of a 14-state system in
a fraction of a second.

:func:`true_frf` evaluates ``G(z) = C (z I - A)^-1 B + D`` on the DFT grid
``z_k = exp(j 2 pi k / N)`` and :func:`transient_frf` the exact leakage term
``T(z) = C (z I - A)^-1 z (x(0) - x(N))``, so that, with the unnormalised DFT
``np.fft.fft``,

.. math:: Y_h(k) = G(z_k) U_h(k) + T(z_k)

holds to rounding error (paper eq. (FastSampledOutput)).

MIMO systems (issue 13) use python-control's convention, channels first and
time last: ``u_h`` of shape ``(n_u, N)``, ``y_h`` ``(n_y, N)``, ``y_l``
``(n_y, M)``; :func:`true_frf` is then ``(n_y, n_u, K)`` and
:func:`transient_frf` ``(n_y, K)``, with ``Y_o = sum_i G_oi U_i + T_o`` for
every output ``o``. A SISO system with a 1-D record keeps 1-D arrays.
:func:`simulate_slow_feedback` closes a loop around a plant with a
controller that runs on the slow samples (vision in the loop).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import control
import numpy as np
import scipy.linalg
import scipy.signal
import scipy.sparse
import scipy.sparse.csgraph

from ._validation import (
    check_discrete_controller,
    check_downsampling_factor,
    check_feedback_outputs,
    check_nonnegative_int,
    check_rng,
    check_sample_time,
    check_siso_system,
)
from .solvers import CHUNK_BYTES

__all__ = [
    "FeedbackSimulationResult",
    "SimulationResult",
    "frequency_grid",
    "periodic_state",
    "simulate",
    "simulate_slow_feedback",
    "transient_frf",
    "true_frf",
]

# Eigenvector matrices better conditioned than this use the fast diagonal
# recursion (relative rounding error about cond * 1e-16); others use the
# (slower, backward-stable) complex Schur cascade.
_MAX_EIGENVECTOR_CONDITION = 1e5


@dataclass(frozen=True, eq=False)
class SimulationResult:
    """Result of :func:`simulate`.

    Attributes
    ----------
    u_h : ndarray of shape (N,) or (n_u, N)
        Fast-rate input (a copy), in input units.
    y_h : ndarray of shape (N,) or (n_y, N)
        Noise-free fast-rate output.
    y_l : ndarray of shape (M,) or (n_y, M)
        Noisy slow-rate output ``y_h[..., ::F] + v_l``, ``M = N / F``.
    y_l_clean : ndarray of shape (M,) or (n_y, M)
        Noise-free slow-rate output ``y_h[..., ::F]``.
    noise_std : float or ndarray of shape (n_y,)
        Standard deviation of the added white noise (0 if none), per output
        channel for 2-D outputs.
    downsampling_factor : int
        ``F``.
    sample_time : float or None
        Fast sample time in s (``None`` if the system's is unspecified).
    x0 : ndarray of shape (n_states,)
        State at the start of the record.
    x_final : ndarray of shape (n_states,)
        State ``x(N)`` after the last input sample.
    """

    u_h: np.ndarray
    y_h: np.ndarray
    y_l: np.ndarray
    y_l_clean: np.ndarray
    noise_std: float
    downsampling_factor: int
    sample_time: float | None
    x0: np.ndarray
    x_final: np.ndarray

    @property
    def noise(self) -> np.ndarray:
        """The added slow-rate noise ``y_l - y_l_clean``, shape of ``y_l``."""
        return self.y_l - self.y_l_clean


def simulate(
    system: control.StateSpace | control.TransferFunction,
    u_h: np.ndarray,
    F: int,
    *,
    sample_time: float | None = None,
    x0: np.ndarray | None = None,
    snr_db: float | None = None,
    noise_std: float | None = None,
    rng: int | np.random.Generator | None = None,
) -> SimulationResult:
    """Simulate a finite record of a discrete system and a slow sensor.

    ``x(n+1) = A x(n) + B u_h(n)``, ``y_h(n) = C x(n) + D u_h(n)`` for
    ``n = 0..N-1`` with ``x(0) = x0`` (zero by default: at rest before the
    record), then ``y_l(m) = y_h(m F) + v_l(m)`` with white Gaussian noise
    ``v_l``, independent between output channels.

    The outputs are 1-D for a SISO system and a 1-D record, and 2-D
    (channels first) whenever the system is not SISO or ``u_h`` is 2-D.

    Parameters
    ----------
    system : control.StateSpace or control.TransferFunction
        Discrete-time system, SISO or MIMO. A transfer function is converted
        with ``control.ss`` (as ``diagnose`` does); ``x0`` and ``x_final``
        then refer to the states of that realisation.
    u_h : array_like of shape (N,) or (n_u, N)
        Fast-rate input, one record, channels first; finite, ``N`` a
        multiple of ``F``. 1-D only for a system with one input.
    F : int
        Downsampling factor (slow / fast sample time), >= 1.
    sample_time : float, optional
        Fast sample time in s; if given it must equal ``system.dt``.
    x0 : array_like of shape (n_states,), optional
        Initial state ``x(0)``; default zeros.
    snr_db : float or array_like of shape (n_y,), optional
        Output signal-to-noise ratio ``10 log10(var(y_l_clean) / noise_std^2)``
        in dB (``np.var``, mean removed), **per output channel**: each
        output's noise is set from that output's own variance. Mutually
        exclusive with ``noise_std``.
    noise_std : float or array_like of shape (n_y,), optional
        Standard deviation of the slow-rate noise, in output units, >= 0; one
        value for all outputs or one per output.
    rng : int, numpy.random.Generator or None
        Seed or generator for the noise.

    Returns
    -------
    SimulationResult

    Raises
    ------
    TypeError
        If ``system`` is not a ``control.StateSpace`` or
        ``control.TransferFunction``, or ``rng`` is invalid.
    ValueError
        For continuous systems, mismatched sample times, an input whose
        shape does not match the system's inputs or that is not finite,
        ``N`` not a multiple of ``F``, a wrong ``x0`` shape, both or invalid
        noise settings.

    Examples
    --------
    >>> import control, numpy as np
    >>> system = control.ss([[0.5]], [[1.0]], [[1.0]], [[0.0]], 1e-3)
    >>> result = simulate(system, np.ones(6), 3)
    >>> result.y_l
    array([0.  , 1.75])
    """
    A, B, C, D, dt = _system_matrices(system, sample_time)
    F = check_downsampling_factor(F)
    u = _check_input(u_h, F, n_inputs=B.shape[1])
    x_start = _check_initial_state(x0, A.shape[0])
    generator = check_rng(rng)
    if snr_db is not None and noise_std is not None:
        raise ValueError(
            f"give either snr_db or noise_std, not both; got {snr_db=} and "
            f"{noise_std=}. Set the other to None."
        )
    if _is_siso(system):  # the SISO kernel, also for a (1, N) record
        y_h, x_final = _simulate_kernel(
            A, B[:, 0], C[0], float(D[0, 0]), u.ravel(), x_start
        )
        y_l_clean = y_h[::F].copy()
        std = _noise_std(y_l_clean, snr_db, noise_std)
        y_l = y_l_clean.copy()
        if std > 0:
            y_l += std * generator.standard_normal(y_l.shape[0])
        if u.ndim == 2:
            y_h, y_l, y_l_clean = y_h[None], y_l[None], y_l_clean[None]
            std = np.array([std])
    else:
        u = u.reshape(B.shape[1], -1)
        y_h, x_final = _simulate_kernel_mimo(A, B, C, D, u, x_start)
        y_l_clean = y_h[:, ::F].copy()
        std = _noise_std_per_output(y_l_clean, snr_db, noise_std)
        y_l = y_l_clean.copy()
        if np.any(std > 0):
            y_l += std[:, np.newaxis] * generator.standard_normal(y_l.shape)
    return SimulationResult(
        u_h=u,
        y_h=y_h,
        y_l=y_l,
        y_l_clean=y_l_clean,
        noise_std=std,
        downsampling_factor=F,
        sample_time=dt,
        x0=x_start,
        x_final=x_final,
    )


@dataclass(frozen=True, eq=False)
class FeedbackSimulationResult(SimulationResult):
    """Result of :func:`simulate_slow_feedback`.

    The attributes of :class:`SimulationResult` (``u_h`` is the realised
    plant input ``r - hold(c)``, which a user can also measure; ``y_l`` the
    noisy slow outputs the controller read; ``x0``/``x_final`` the plant
    states), and:

    Attributes
    ----------
    r : ndarray of shape (N,) or (n_u, N)
        The excitation (a copy).
    controller_output : ndarray of shape (M,) or (n_u, M)
        Controller output ``c(m)`` at the slow samples, before the hold.
    """

    r: np.ndarray = None
    controller_output: np.ndarray = None


def simulate_slow_feedback(
    plant: control.StateSpace | control.TransferFunction,
    controller: control.StateSpace | control.TransferFunction,
    r: np.ndarray,
    F: int,
    *,
    feedback_outputs=None,
    x0: np.ndarray | None = None,
    snr_db: float | None = None,
    noise_std: float | None = None,
    rng: int | np.random.Generator | None = None,
) -> FeedbackSimulationResult:
    """Simulate a plant in a slow-rate feedback loop (vision in the loop).

    The controller runs on the slow samples of the measured outputs
    ``feedback_outputs``, ``c = C_l y_l[feedback_outputs]`` with ``y_l(m) =
    y_h(m F) + v_l(m)``, and its output is held over ``F`` fast samples
    (zero-order hold) and subtracted at the plant input::

        u_h(n) = r(n) - c(floor(n / F)),   y_h = P u_h.

    The measurement noise ``v_l`` enters at the slow outputs, hence also in
    the loop. The closed loop is simulated exactly: the plant lifted over
    ``F`` fast samples and the controller form one slow-rate state-space
    system (algebraic loops through feedthroughs solved), whose controller
    output gives ``u_h``; the plant is then simulated at the fast rate
    from ``u_h``. The controller starts at rest.

    Parameters
    ----------
    plant : control.StateSpace or control.TransferFunction
        Discrete fast-rate plant (``dt`` = fast sample time), ``n_y`` outputs,
        ``n_u`` inputs.
    controller : control.StateSpace or control.TransferFunction
        Discrete controller with ``dt == F * plant.dt``, ``n_u`` outputs and
        ``len(feedback_outputs)`` inputs.
    r : array_like of shape (N,) or (n_u, N)
        Excitation at the plant input, as ``u_h`` of :func:`simulate`.
    F : int
        Downsampling factor of the sensor and of the controller.
    feedback_outputs : sequence of int, optional
        Plant outputs the controller reads; default all.
    x0 : array_like of shape (n_states,), optional
        Initial plant state; default zeros.
    snr_db, noise_std : float or array_like of shape (n_y,), optional
        Slow-rate measurement noise per output channel, as in
        :func:`simulate`; ``snr_db`` refers to each output of the noise-free
        closed loop.
    rng : int, numpy.random.Generator or None
        Seed or generator for the noise.

    Returns
    -------
    FeedbackSimulationResult
        1-D arrays for a SISO plant and a 1-D ``r``, else channels first.

    Raises
    ------
    ValueError
        As :func:`simulate`, and for a controller whose ``dt`` is not ``F``
        times the plant's, whose shape does not match, or that does not
        stabilise the loop.

    Examples
    --------
    >>> import control, numpy as np
    >>> plant = control.ss([[0.9]], [[1.0]], [[1.0]], [[0.0]], 1e-3)
    >>> controller = control.ss([], [], [], [[0.2]], 3e-3)
    >>> result = simulate_slow_feedback(plant, controller, np.ones(6), 3)
    >>> result.u_h
    array([1.   , 1.   , 1.   , 0.458, 0.458, 0.458])
    """
    A, B, C, D, dt = _system_matrices(plant, None)
    F = check_downsampling_factor(F)
    r_checked = _check_input(r, F, n_inputs=B.shape[1], name="r")
    n_outputs, n_inputs = D.shape
    x_start = _check_initial_state(x0, A.shape[0])
    generator = check_rng(rng)
    if snr_db is not None and noise_std is not None:
        raise ValueError(
            f"give either snr_db or noise_std, not both; got {snr_db=} and "
            f"{noise_std=}. Set the other to None."
        )
    feedback = check_feedback_outputs(feedback_outputs, n_outputs)
    controller_matrices = _slow_controller_matrices(
        controller, dt, F, n_inputs, len(feedback)
    )
    lifted = _lifted_loop(A, B, C, D, controller_matrices, F, feedback)
    excitation = r_checked.reshape(n_inputs, -1)
    n_slow = excitation.shape[1] // F
    # lifted input: r(mF + i) for i < F, stacked i-major, then the noise
    stacked = excitation.reshape(n_inputs, n_slow, F).transpose(2, 0, 1)
    stacked = stacked.reshape(F * n_inputs, n_slow)

    def run(noise):
        lifted_input = np.vstack([stacked, noise[list(feedback)]])
        start = np.concatenate([x_start, np.zeros(lifted[0].shape[0] - x_start.size)])
        held, _ = _simulate_kernel_mimo(*lifted, lifted_input, start)
        u = excitation - np.repeat(held, F, axis=1)
        y, x_end = _simulate_kernel_mimo(A, B, C, D, u, x_start)
        return u, y, x_end, held

    zero_noise = np.zeros((n_outputs, n_slow))
    u, y_h, x_final, held = run(zero_noise)
    std = _noise_std_per_output(y_h[:, ::F], snr_db, noise_std)
    noise = zero_noise
    if np.any(std > 0):
        noise = std[:, np.newaxis] * generator.standard_normal((n_outputs, n_slow))
        u, y_h, x_final, held = run(noise)
    y_l_clean = y_h[:, ::F].copy()
    y_l = y_l_clean + noise
    if r_checked.ndim == 1 and n_outputs == 1:
        u, y_h, y_l, y_l_clean, held = u[0], y_h[0], y_l[0], y_l_clean[0], held[0]
        std = float(std[0])
    elif r_checked.ndim == 1:
        u = u[0]
    return FeedbackSimulationResult(
        u_h=u, y_h=y_h, y_l=y_l, y_l_clean=y_l_clean, noise_std=std,
        downsampling_factor=F, sample_time=dt, x0=x_start, x_final=x_final,
        r=r_checked, controller_output=held,
    )


def true_frf(
    system: control.StateSpace | control.TransferFunction,
    n_samples: int,
    *,
    one_sided: bool = True,
) -> np.ndarray:
    """Frequency response ``C (z I - A)^-1 B + D`` on the DFT grid.

    Evaluated at ``z_k = exp(j 2 pi k / N)`` directly from the state-space
    matrices (complex Schur form and triangular solves), in DFT order.

    Parameters
    ----------
    system : control.StateSpace or control.TransferFunction
        Discrete-time system, SISO or MIMO.
    n_samples : int
        Record length ``N`` (number of DFT bins), >= 1.
    one_sided : bool, default True
        Return bins ``k = 0..N//2`` (else ``k = 0..N-1``).

    Returns
    -------
    ndarray of complex, shape (K,) or (n_y, n_u, K)
        ``G(z_k)``, ``K = N//2 + 1`` or ``N``; 1-D for a SISO system;
        ``inf``/``nan`` at bins that coincide with a pole on the
        unit circle (e.g. ``k = 0`` for an integrator).

    Examples
    --------
    >>> import control
    >>> delay = control.ss([[0.0]], [[1.0]], [[1.0]], [[0.0]], 1.0)
    >>> bool(np.allclose(true_frf(delay, 4), [1.0, -1.0j, -1.0]))
    True
    """
    A, B, C, D, _ = _system_matrices(system, None)
    z = _dft_grid(n_samples, one_sided)
    if _is_siso(system):
        return _resolvent_response(A, C[0], B[:, 0], z) + D[0, 0]
    return _matrix_response(A, B, C, D, z)


def transient_frf(
    system: control.StateSpace | control.TransferFunction,
    n_samples: int,
    x0: np.ndarray,
    x_final: np.ndarray,
    *,
    one_sided: bool = True,
) -> np.ndarray:
    """Exact leakage term ``T(z) = C (z I - A)^-1 z (x(0) - x(N))``.

    For a record of ``N`` samples, ``np.fft.fft(y_h) = G(z_k) U_h(k) +
    T(z_k)`` exactly, with ``U_h = np.fft.fft(u_h)`` and ``z_k = exp(j 2 pi
    k / N)``; ``x(0)`` and ``x(N)`` are ``SimulationResult.x0`` and
    ``.x_final``.

    Parameters
    ----------
    system : control.StateSpace or control.TransferFunction
        Discrete-time system, SISO or MIMO.
    n_samples : int
        Record length ``N``, >= 1.
    x0, x_final : array_like of shape (n_states,)
        States at the start and the end of the record.
    one_sided : bool, default True
        Return bins ``k = 0..N//2`` (else ``k = 0..N-1``).

    Returns
    -------
    ndarray of complex, shape (K,) or (n_y, K)
        ``K = N//2 + 1`` or ``N``; one row per output for a MIMO system (the
        transient does not depend on the inputs).
    """
    A, _, C, _, _ = _system_matrices(system, None)
    start = _check_initial_state(x0, A.shape[0], name="x0")
    end = _check_initial_state(x_final, A.shape[0], name="x_final")
    z = _dft_grid(n_samples, one_sided)
    left = C[0] if _is_siso(system) else C
    return _resolvent_response(A, left, start - end, z) * z


def periodic_state(
    system: control.StateSpace | control.TransferFunction,
    u_h: np.ndarray,
    *,
    sample_time: float | None = None,
) -> np.ndarray:
    """Initial state of the periodic steady state under one period ``u_h``.

    The ``x0`` with ``x(N) = x0``: ``simulate(system, u_h, F, x0=x0)`` then
    records the steady state of ``u_h`` applied periodically (no transient,
    ``transient_frf`` is zero), as after many periods of a multisine.
    Solves ``(I - A^N) x0 = x_N``, ``x_N`` the state after one period from
    rest.

    Parameters
    ----------
    system : control.StateSpace or control.TransferFunction
        Discrete-time system, SISO or MIMO, with every pole inside the unit
        circle.
    u_h : ndarray of shape (N,) or (n_u, N)
        One period of the input.
    sample_time : float, optional
        As in :func:`simulate`.

    Returns
    -------
    ndarray of shape (n_states,)

    Raises
    ------
    ValueError
        If the system has a pole on or outside the unit circle (e.g. a free
        rigid body, whose position drifts): it has no periodic steady state.
    """
    A, _, _, _, _ = _system_matrices(system, sample_time)
    radius = float(np.max(np.abs(np.linalg.eigvals(A)), initial=0.0))
    if radius >= 1.0 - 1e-9:
        raise ValueError(
            f"the system has a pole of magnitude {radius:.6g} (on or outside the "
            "unit circle, e.g. a free rigid body): it has no periodic steady "
            "state. Close the loop around it, or suspend the body "
            "(lrmfrf.plants.wafer_stage(suspension=...))."
        )
    end = simulate(system, u_h, 1, sample_time=sample_time).x_final
    n = np.shape(u_h)[-1]
    return np.linalg.solve(np.eye(A.shape[0]) - np.linalg.matrix_power(A, n), end)


def frequency_grid(n_samples: int, sample_time: float) -> np.ndarray:
    """One-sided DFT frequencies ``k / (N Ts)`` in Hz for ``k = 0..N//2``.

    Parameters
    ----------
    n_samples : int
        Record length ``N``, >= 1.
    sample_time : float
        Sample time ``Ts`` in s, > 0.

    Returns
    -------
    ndarray of shape (N//2 + 1,)
        Frequencies in Hz.

    Examples
    --------
    >>> frequency_grid(4, 0.5e-3)
    array([   0.,  500., 1000.])
    """
    n = _check_n_samples(n_samples)
    sample_time = check_sample_time(sample_time)
    return np.arange(n // 2 + 1) / (n * sample_time)


# ---------------------------------------------------------------------------
# Private helpers
# ---------------------------------------------------------------------------


def _check_system(system, sample_time):
    """Return ``A, B (n,), C (n,), D (scalar), dt`` of a discrete SISO system
    (a ``control.TransferFunction`` is converted with ``control.ss``)."""
    check_siso_system(system, "system")
    A, B, C, D, dt = _system_matrices(system, sample_time)
    return A, B[:, 0], C[0, :], float(D[0, 0]), dt


def _system_matrices(system, sample_time):
    """Return ``A, B (n, n_u), C (n_y, n), D (n_y, n_u), dt`` of a discrete
    SISO or MIMO system (a ``control.TransferFunction`` is converted with
    ``control.ss``)."""
    if not isinstance(system, (control.StateSpace, control.TransferFunction)):
        raise TypeError(
            "system must be a control.StateSpace or TransferFunction (python-"
            f"control StateSpace); got {type(system).__name__}. Build it with "
            "control.ss(...)."
        )
    if not control.isdtime(system, strict=True):
        raise ValueError(
            f"system must be discrete-time; got dt={system.dt!r}. Discretise it "
            "first, e.g. control.sample_system(sys, Ts, 'zoh')."
        )
    if isinstance(system, control.TransferFunction):
        system = control.ss(system)
    dt = None if system.dt is True else float(system.dt)
    if sample_time is not None:
        sample_time = check_sample_time(sample_time)
        if dt is not None and not math.isclose(dt, sample_time, rel_tol=1e-9):
            raise ValueError(
                f"sample_time={sample_time!r} s does not match system.dt={dt!r} s. "
                "Pass the system's sample time or resample the system."
            )
        dt = float(sample_time) if dt is None else dt
    A = np.asarray(system.A, dtype=float).reshape(system.nstates, system.nstates)
    B = np.asarray(system.B, dtype=float).reshape(system.nstates, system.ninputs)
    C = np.asarray(system.C, dtype=float).reshape(system.noutputs, system.nstates)
    D = np.asarray(system.D, dtype=float).reshape(system.noutputs, system.ninputs)
    return A, B, C, D, dt


def _is_siso(system) -> bool:
    return system.ninputs == 1 and system.noutputs == 1


def _check_input(u_h, F: int, *, n_inputs: int = 1, name: str = "u_h") -> np.ndarray:
    """A finite float copy of one record: (N,), or (n_inputs, N) channels first."""
    if np.iscomplexobj(u_h):
        raise TypeError(f"{name} must be real-valued; got a complex array.")
    try:
        u = np.array(u_h, dtype=float, copy=True)
    except (TypeError, ValueError) as error:
        raise TypeError(
            f"{name} must be a real numeric array of shape (N,) or (n_u, N); got "
            f"{type(u_h)}."
        ) from error
    if not (u.ndim == 1 and n_inputs == 1) and not (
        u.ndim == 2 and u.shape[0] == n_inputs
    ):
        one_d = "1-D of shape (N,) or " if n_inputs == 1 else ""
        raise ValueError(
            f"{name} must be {one_d}2-D of shape (n_u, N) = ({n_inputs}, N), "
            f"channels first, for a system with {n_inputs} input(s); got shape "
            f"{u.shape}. Pass one record; simulate several experiments one at "
            "a time."
        )
    if u.size == 0:
        raise ValueError(f"{name} is empty; pass at least F samples.")
    if not np.all(np.isfinite(u)):
        raise ValueError(f"{name} contains NaN or inf; pass a finite input signal.")
    length = u.shape[-1]
    if length % F:
        raise ValueError(
            f"len({name})={length} is not a multiple of F={F}. Trim the record to "
            f"{length - length % F} samples."
        )
    return u


def _slow_controller_matrices(controller, plant_dt, F, n_inputs, n_feedback):
    check_discrete_controller(
        controller, hint="Discretise it at F times the plant's."
    )
    if plant_dt is None or not math.isclose(
        float(controller.dt), F * plant_dt, rel_tol=1e-9
    ):
        raise ValueError(
            f"controller.dt={controller.dt!r} s must be F * plant.dt = "
            f"{F} * {plant_dt!r} s (the controller runs on the slow samples). "
            "Discretise the controller at the slow sample time."
        )
    if controller.noutputs != n_inputs or controller.ninputs != n_feedback:
        raise ValueError(
            f"the controller must have n_u = {n_inputs} outputs and "
            f"len(feedback_outputs) = {n_feedback} inputs; got "
            f"{controller.noutputs} outputs and {controller.ninputs} inputs."
        )
    return _system_matrices(controller, None)[:4]


def _lifted_loop(A, B, C, D, controller, F, feedback):
    """Slow-rate closed loop of the plant lifted over ``F`` samples and the
    controller: state ``[x(mF), x_c(m)]``, input ``[r(mF), ..., r(mF+F-1),
    v_fb(m)]``, output the controller output ``c(m)``; ``(A, B, C, D)``.

    With ``S`` the selection, ``y_fb = S C x + S D (r_0 - c) + v``, ``c = C_c
    x_c + D_c y_fb`` gives ``c = W (D_c S C x + C_c x_c + D_c S D r_0 + D_c
    v)``, ``W = (I + D_c S D)^-1``; ``x+ = A^F x + sum_i A^(F-1-i) B (r_i -
    c)``, ``x_c+ = A_c x_c + B_c y_fb``.
    """
    Ac, Bc, Cc, Dc = controller
    n, n_u = B.shape
    select = np.eye(C.shape[0])[list(feedback)]
    SC, SD = select @ C, select @ D
    loop = np.eye(n_u) + Dc @ SD
    if np.linalg.cond(loop) > 1e12:
        raise ValueError(
            "the feedback loop is algebraically singular (I + D_C D_P is "
            "singular); add a delay or change the controller feedthrough."
        )
    W = np.linalg.inv(loop)
    powers = [np.eye(n)]
    for _ in range(F - 1):
        powers.append(A @ powers[-1])
    lifted_B = np.hstack([powers[F - 1 - i] @ B for i in range(F)])
    Gamma = sum(powers[i] @ B for i in range(F))
    Phi = A @ powers[-1]
    first = np.zeros((n_u, F * n_u))
    first[:, :n_u] = np.eye(n_u)
    # c = K_x x + K_c x_c + K_r r_lift + K_v v
    K_x, K_c, K_r, K_v = W @ Dc @ SC, W @ Cc, W @ Dc @ SD @ first, W @ Dc
    # y_fb = SC x + SD first r_lift - SD c + v
    Y_x, Y_c = SC - SD @ K_x, -SD @ K_c
    Y_r, Y_v = SD @ first - SD @ K_r, np.eye(len(feedback)) - SD @ K_v
    A_loop = np.block([[Phi - Gamma @ K_x, -Gamma @ K_c], [Bc @ Y_x, Ac + Bc @ Y_c]])
    B_loop = np.block([[lifted_B - Gamma @ K_r, -Gamma @ K_v], [Bc @ Y_r, Bc @ Y_v]])
    C_loop = np.hstack([K_x, K_c])
    D_loop = np.hstack([K_r, K_v])
    radius = float(np.max(np.abs(np.linalg.eigvals(A_loop)), initial=0.0))
    if radius >= 1.0:
        raise ValueError(
            f"the slow-rate controller does not stabilise the loop: largest "
            f"closed-loop pole magnitude (slow rate) is {radius:.6g} >= 1. Lower "
            "the controller bandwidth."
        )
    return A_loop, B_loop, C_loop, D_loop


def _check_initial_state(x0, n_states: int, name: str = "x0") -> np.ndarray:
    if x0 is None:
        return np.zeros(n_states)
    state = np.array(x0, dtype=float, copy=True)
    if state.shape != (n_states,):
        raise ValueError(
            f"{name} must have shape ({n_states},) (one entry per state); got "
            f"shape {state.shape}."
        )
    if not np.all(np.isfinite(state)):
        raise ValueError(f"{name} contains NaN or inf; pass a finite state.")
    return state


def _check_n_samples(n_samples) -> int:
    return check_nonnegative_int(n_samples, "n_samples", minimum=1)


def _noise_std(y_clean: np.ndarray, snr_db, noise_std) -> float:
    if noise_std is not None:
        if not (isinstance(noise_std, numbers.Real) and math.isfinite(noise_std)):
            raise ValueError(f"noise_std must be a finite number; got {noise_std!r}.")
        if noise_std < 0:
            raise ValueError(f"noise_std must be >= 0; got {noise_std!r}.")
        return float(noise_std)
    if snr_db is None:
        return 0.0
    if not (isinstance(snr_db, numbers.Real) and math.isfinite(snr_db)):
        raise ValueError(
            f"snr_db must be a finite number of dB; got {snr_db!r}. Use "
            "noise_std=0 for a noise-free output."
        )
    power = float(np.var(y_clean))
    if power == 0.0:
        raise ValueError(
            "snr_db cannot set the noise level: the noise-free slow output is "
            "constant (zero variance). Pass noise_std instead."
        )
    return math.sqrt(power / 10.0 ** (snr_db / 10.0))


def _noise_std_per_output(y_clean: np.ndarray, snr_db, noise_std) -> np.ndarray:
    """Noise std per output channel, shape (n_y,), from a scalar or per-output
    ``noise_std`` or ``snr_db`` (the SNR of each output channel)."""
    n_outputs = y_clean.shape[0]
    setting, name = (noise_std, "noise_std") if noise_std is not None else (
        snr_db, "snr_db")
    if setting is None:
        return np.zeros(n_outputs)
    values = np.asarray(setting, dtype=object)
    if values.ndim == 0:
        values = np.full(n_outputs, setting, dtype=object)
    if values.shape != (n_outputs,):
        raise ValueError(
            f"{name} must be a number or one value per output channel, shape "
            f"({n_outputs},); got shape {values.shape}."
        )
    stds = np.empty(n_outputs)
    for output, value in enumerate(values):
        try:
            if name == "noise_std":
                stds[output] = _noise_std(y_clean[output], None, value)
            else:
                stds[output] = _noise_std(y_clean[output], value, None)
        except ValueError as error:
            raise ValueError(f"output {output}: {error}") from None
    return stds


def _dft_grid(n_samples, one_sided: bool) -> np.ndarray:
    n = _check_n_samples(n_samples)
    k = np.arange(n // 2 + 1 if one_sided else n)
    return np.exp(2j * np.pi * k / n)


def _balance(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``S^-1 A S`` with diagonal ``S = diag(scale)`` of powers of two (exact).

    Equalising row and column norms before the orthogonal transformations
    keeps small entries accurate; for the wafer-stage closed loop it improves
    the frequency response at low-gain bins by one to two orders of magnitude.
    """
    if A.shape[0] == 0:
        return A, np.ones(0)
    balanced, (scale, _) = scipy.linalg.matrix_balance(A, permute=False, separate=True)
    return balanced, scale


def _resolvent_response(
    A: np.ndarray, left: np.ndarray, right: np.ndarray, z: np.ndarray
) -> np.ndarray:
    """``left @ (z I - A)^-1 @ right`` for every ``z``.

    ``left`` of shape (n,) gives shape (len(z),); ``left`` of shape (n_y, n)
    gives (n_y, len(z)).

    Balancing, complex Schur form and back substitution vectorised over
    ``z``; ``inf``/``nan`` where ``z`` is an eigenvalue of ``A``.
    """
    if A.shape[0] == 0:
        return np.zeros(np.shape(left)[:-1] + z.shape, dtype=complex)
    balanced, scale = _balance(A)
    schur, unitary = _complex_schur(balanced)
    with np.errstate(divide="ignore", invalid="ignore"):
        states = _triangular_resolvent(schur, unitary.conj().T @ (right / scale), z)
        return ((left * scale) @ unitary) @ states


def _matrix_response(A, B, C, D, z) -> np.ndarray:
    """``C (z I - A)^-1 B + D`` for every ``z``, shape (n_y, n_u, len(z)),
    one input column at a time (memory of one (n, len(z)) state array)."""
    response = np.empty((C.shape[0], B.shape[1], z.size), dtype=complex)
    for column in range(B.shape[1]):
        response[:, column] = _resolvent_response(A, C, B[:, column], z)
        response[:, column] += D[:, column, np.newaxis]
    return response


def _complex_schur(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``A = Q T Q^H`` with ``T`` upper triangular (complex Schur form)."""
    schur, unitary = scipy.linalg.schur(A.astype(complex), output="complex")
    return schur, unitary


def _triangular_resolvent(T: np.ndarray, rhs: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Solve ``(z I - T) x = rhs`` for every ``z``; returns shape (n, len(z)).

    Back substitution, vectorised over ``z``: ``x_i = (rhs_i + sum_{j>i}
    T_ij x_j) / (z - T_ii)``.
    """
    n = T.shape[0]
    states = np.zeros((n, z.size), dtype=complex)
    for i in range(n - 1, -1, -1):
        coupling = T[i, i + 1 :] @ states[i + 1 :] if i < n - 1 else 0.0
        states[i] = (rhs[i] + coupling) / (z - T[i, i])
    return states


def _simulate_kernel(A, B, C, D, u, x0):
    """Exact ``y(n) = C x(n) + D u(n)``, ``x(n+1) = A x(n) + B u(n)``.

    Returns ``y`` (N,) and ``x(N)``. States that ``A`` does not couple (the
    weakly connected components of its sparsity graph, e.g. the modes of a
    modal plant) are simulated as separate systems, so a defective block (a
    rigid body's double integrator) needs the slower Schur cascade only for
    its own states.
    """
    n_states = A.shape[0]
    if n_states == 0:
        return D * u, np.zeros(0)
    n_blocks, labels = scipy.sparse.csgraph.connected_components(
        scipy.sparse.csr_matrix(A != 0), directed=True, connection="weak"
    )
    if n_blocks == 1:
        return _simulate_block(A, B, C, D, u, x0)
    y = D * u
    x_final = np.empty(n_states)
    for block in range(n_blocks):
        index = np.flatnonzero(labels == block)
        y_block, x_final[index] = _simulate_block(
            A[np.ix_(index, index)], B[index], C[index], 0.0, u, x0[index]
        )
        y += y_block
    return y, x_final


def _simulate_block(A, B, C, D, u, x0):
    """:func:`_simulate_kernel` for one block of coupled states.

    Balances ``A`` (exact diagonal scaling), then uses its eigendecomposition
    when that is well conditioned, else the complex Schur cascade.
    """
    balanced, scale = _balance(A)
    B, C, x0 = B / scale, C * scale, x0 / scale
    eigenvalues, vectors = np.linalg.eig(balanced)
    if np.linalg.cond(vectors) <= _MAX_EIGENVECTOR_CONDITION:
        y, x_final = _simulate_diagonal(eigenvalues, vectors, B, C, D, u, x0)
    else:
        y, x_final = _simulate_schur(balanced, B, C, D, u, x0)
    return y, x_final * scale


def _first_order_states(pole, forcing, start):
    """States ``s(0..L-1)`` and ``s(L)`` of ``s(n+1) = pole s(n) + forcing(n)``."""
    shifted, _ = scipy.signal.lfilter(
        [1.0], [1.0, -pole], forcing, zi=np.array([pole * start])
    )
    states = np.empty_like(shifted)
    states[0] = start
    states[1:] = shifted[:-1]
    return states, shifted[-1]


def _simulate_diagonal(eigenvalues, vectors, B, C, D, u, x0):
    """Diagonal recursion ``q(n+1) = lambda q(n) + (V^-1 B) u(n)``, ``x = V q``.

    Only one eigenvalue of each complex-conjugate pair is simulated; its
    output contribution is doubled (real part) and its partner's final state
    is the conjugate, which is exact because ``eig`` of a real matrix returns
    exact conjugate pairs. The output row ``c_i`` is folded into the filter,
    which then returns ``c_i q_i(n+1)`` directly.
    """
    inverse = np.linalg.inv(vectors)
    b = inverse @ B
    c = C @ vectors
    q0 = inverse @ x0.astype(complex)
    q_final = np.empty_like(q0)
    y = D * u
    u_complex = u.astype(complex)
    for index, pole in enumerate(eigenvalues):
        if pole.imag < 0:
            continue
        gain = c[index] if c[index] != 0 else 1.0
        numerator, start = gain * b[index], gain * q0[index]
        if pole.imag == 0:  # real mode: real arithmetic (eigenvector is real)
            weight, signal = 1.0, u
            pole, numerator, start = pole.real, numerator.real, start.real
        else:
            weight, signal = 2.0, u_complex
        shifted, _ = scipy.signal.lfilter(
            [numerator], [1.0, -pole], signal, zi=np.array([pole * start])
        )
        q_final[index] = shifted[-1] / gain
        if c[index] != 0:
            y[0] += weight * start.real
            y[1:] += weight * shifted[:-1].real
    for index in np.flatnonzero(eigenvalues.imag < 0):
        partner = np.argmin(np.abs(eigenvalues - np.conj(eigenvalues[index])))
        q_final[index] = np.conj(q_final[partner])
    return y, (vectors @ q_final).real


def _simulate_schur(A, B, C, D, u, x0):
    """Complex Schur cascade ``A = Q T Q^H``, processed in chunks.

    With ``s = Q^H x``, ``s_i(n+1) = T_ii s_i(n) + (Q^H B)_i u(n) + sum_{j>i}
    T_ij s_j(n)``: states are solved from the last to the first, each a
    first-order recursion driven by the already computed later states.
    Backward stable for any ``A`` (also defective, e.g. double integrators).
    """
    T, Q = _complex_schur(A)
    b = Q.conj().T @ B
    c = C @ Q
    n = T.shape[0]
    state = Q.conj().T @ x0.astype(complex)
    y = np.empty_like(u)
    # forcing and states: two complex (n, chunk) arrays within CHUNK_BYTES
    chunk_length = max(1, CHUNK_BYTES // (32 * n))
    for begin in range(0, u.size, chunk_length):
        chunk = u[begin : begin + chunk_length]
        forcing = np.outer(b, chunk)
        states = np.empty((n, chunk.size), dtype=complex)
        for i in range(n - 1, -1, -1):
            states[i], state[i] = _first_order_states(T[i, i], forcing[i], state[i])
            if i > 0:
                forcing[:i] += np.outer(T[:i, i], states[i])
        y[begin : begin + chunk.size] = (c @ states).real + D * chunk
    return y, (Q @ state).real


def _simulate_kernel_mimo(A, B, C, D, u, x0):
    """:func:`_simulate_kernel` for ``B`` (n, n_u), ``C`` (n_y, n), ``D`` (n_y,
    n_u) and ``u`` (n_u, N); returns ``y`` (n_y, N) and ``x(N)``. Uncoupled
    blocks of ``A`` are simulated separately, as in the SISO kernel."""
    n_states = A.shape[0]
    y = D @ u
    if n_states == 0:
        return y, np.zeros(0)
    n_blocks, labels = scipy.sparse.csgraph.connected_components(
        scipy.sparse.csr_matrix(A != 0), directed=True, connection="weak"
    )
    x_final = np.empty(n_states)
    for block in range(n_blocks):
        index = np.flatnonzero(labels == block)
        y_block, x_final[index] = _simulate_block_mimo(
            A[np.ix_(index, index)], B[index], C[:, index], u, x0[index]
        )
        y += y_block
    return y, x_final


def _simulate_block_mimo(A, B, C, u, x0):
    """:func:`_simulate_block` without feedthrough for ``B`` (k, n_u), ``C``
    (n_y, k): eigendecomposition when well conditioned, else Schur cascade."""
    balanced, scale = _balance(A)
    B, C, x0 = B / scale[:, np.newaxis], C * scale, x0 / scale
    eigenvalues, vectors = np.linalg.eig(balanced)
    if np.linalg.cond(vectors) <= _MAX_EIGENVECTOR_CONDITION:
        y, x_final = _simulate_diagonal_mimo(eigenvalues, vectors, B, C, u, x0)
    else:
        y, x_final = _simulate_schur_mimo(balanced, B, C, u, x0)
    return y, x_final * scale


def _simulate_diagonal_mimo(eigenvalues, vectors, B, C, u, x0):
    """:func:`_simulate_diagonal` for several inputs and outputs: each mode
    ``q_i(n+1) = lambda_i q_i(n) + b_i^T u(n)`` (``b = V^-1 B``) is one
    first-order filter, its output contribution ``c_i q_i`` (``c = C V``)."""
    inverse = np.linalg.inv(vectors)
    b = inverse @ B
    c = C @ vectors
    q0 = inverse @ x0.astype(complex)
    q_final = np.empty_like(q0)
    y = np.zeros((C.shape[0], u.shape[1]))
    for index, pole in enumerate(eigenvalues):
        if pole.imag < 0:
            continue
        forcing, start = b[index] @ u, q0[index]
        if pole.imag == 0:  # real mode: real arithmetic (eigenvector is real)
            weight, pole = 1.0, pole.real
            forcing, start, gain = forcing.real, start.real, c[:, index].real
        else:
            weight, gain = 2.0, c[:, index]
        shifted, _ = scipy.signal.lfilter(
            [1.0], [1.0, -pole], forcing, zi=np.array([pole * start])
        )
        q_final[index] = shifted[-1]
        if np.any(gain != 0):
            states = np.empty_like(shifted)
            states[0], states[1:] = start, shifted[:-1]
            y += weight * np.outer(gain, states).real
    for index in np.flatnonzero(eigenvalues.imag < 0):
        partner = np.argmin(np.abs(eigenvalues - np.conj(eigenvalues[index])))
        q_final[index] = np.conj(q_final[partner])
    return y, (vectors @ q_final).real


def _simulate_schur_mimo(A, B, C, u, x0):
    """:func:`_simulate_schur` for ``B`` (n, n_u), ``C`` (n_y, n), ``u``
    (n_u, N), without feedthrough."""
    T, Q = _complex_schur(A)
    b = Q.conj().T @ B
    c = C @ Q
    n = T.shape[0]
    state = Q.conj().T @ x0.astype(complex)
    y = np.empty((C.shape[0], u.shape[1]))
    chunk_length = max(1, CHUNK_BYTES // (32 * n))
    for begin in range(0, u.shape[1], chunk_length):
        chunk = u[:, begin : begin + chunk_length]
        forcing = b @ chunk
        states = np.empty((n, chunk.shape[1]), dtype=complex)
        for i in range(n - 1, -1, -1):
            states[i], state[i] = _first_order_states(T[i, i], forcing[i], state[i])
            if i > 0:
                forcing[:i] += np.outer(T[:i, i], states[i])
        y[:, begin : begin + chunk.shape[1]] = (c @ states).real
    return y, (Q @ state).real
