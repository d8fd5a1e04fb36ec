"""Continuous plant models, exact ZOH discretisation and frequency responses.

The discrepancy workflow names effects in continuous time (a delay in seconds,
a cutoff and a mode in Hz) and compares models with a measured FRF on the fast
DFT grid. A model is a :class:`ContinuousPlant` (state space plus an input
delay, one for all input channels or one per input; SISO or MIMO); it is
turned into the discrete model the data see by an exact zero-order-hold
discretisation, fractional delays included. Responses of a SISO model have shape ``(K,)``, of
a MIMO one ``(n_y, n_u, K)`` (python-control's layout).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import control
import numpy as np
import scipy.linalg

from .._validation import check_siso_system

__all__ = [
    "ContinuousPlant",
    "Resonance",
    "as_continuous_plant",
    "check_system_shape",
    "discrete_response",
    "frequency_response",
    "resonances",
    "to_discrete_ss",
]


@dataclass(frozen=True)
class ContinuousPlant:
    """Continuous state-space model ``y = C x + D u(t - delay)``.

    Attributes
    ----------
    A, B, C, D : ndarray
        Shapes (n, n), (n, n_u), (n_y, n), (n_y, n_u); time in seconds.
    delay : float or tuple of float
        Input delay in seconds, >= 0: one value for every input channel, or a
        tuple of ``n_u`` values, input ``j`` delayed by ``delay[j]`` (one
        actuator's delay, :class:`lrmfrf.discrepancy.effects.InputDelay`); a
        list or array is stored as that tuple.

    Raises
    ------
    ValueError
        If a delay is negative or not finite, or ``delay`` is a sequence whose
        length is not ``n_u``.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    delay: float = 0.0
    labels: tuple = field(default=(), compare=False)

    def __post_init__(self):
        delays = np.asarray(self.delay, dtype=float)
        if delays.ndim:
            if delays.shape != (self.n_inputs,):
                raise ValueError(
                    f"`delay` has shape {delays.shape}, but the plant has "
                    f"{self.n_inputs} input(s): pass one delay for all inputs or "
                    f"one delay per input: {self.n_inputs} values.")
            object.__setattr__(self, "delay", tuple(float(d) for d in delays))
        else:  # a numpy scalar or 0-d array: a float, as documented
            object.__setattr__(self, "delay", float(delays))
        if not np.all(np.isfinite(delays)):
            raise ValueError(f"`delay` must be finite seconds; got {self.delay!r}.")
        if np.any(delays < 0):
            raise ValueError("`delay` is an input delay in seconds, 0 or more "
                             f"(a model cannot answer before its input); got "
                             f"{self.delay!r}.")

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    @property
    def n_inputs(self) -> int:
        return self.B.shape[1]

    @property
    def n_outputs(self) -> int:
        return self.C.shape[0]

    @property
    def input_delays(self) -> np.ndarray:
        """The delay of each input channel in seconds, shape ``(n_u,)``."""
        delays = np.broadcast_to(np.asarray(self.delay, dtype=float),
                                 (self.n_inputs,))
        return np.maximum(delays, 0.0)

    @property
    def is_siso(self) -> bool:
        """One input and one output: responses have shape ``(K,)``."""
        return self.n_inputs == 1 and self.n_outputs == 1

    def with_(self, **changes) -> ContinuousPlant:
        values = {
            "A": self.A, "B": self.B, "C": self.C, "D": self.D,
            "delay": self.delay, "labels": self.labels,
        }
        values.update(changes)
        return ContinuousPlant(**values)


@dataclass(frozen=True)
class Resonance:
    """A lightly damped complex pole pair of a model (continuous time).

    Attributes
    ----------
    frequency : float
        Undamped natural frequency in Hz.
    damping : float
        Damping ratio.
    index : int
        Position in the list returned by :func:`resonances` (by frequency).
    """

    frequency: float
    damping: float
    index: int


def as_continuous_plant(plant, sample_time: float, *,
                        shape: tuple | None = None) -> ContinuousPlant:
    """Convert a python-control model to a :class:`ContinuousPlant`.

    A continuous model is used as is. A discrete model must have
    ``dt == sample_time``; it is taken to be the zero-order-hold
    discretisation of a continuous model, which is recovered exactly with the
    matrix logarithm of the augmented matrix ``[[Phi, Gamma], [0, 1]]``.

    Parameters
    ----------
    plant : control.StateSpace or control.TransferFunction
        Model of the plant.
    sample_time : float
        Fast sample time in seconds.
    shape : (int, int), optional
        ``(n_y, n_u)`` the data have; default ``(1, 1)`` (SISO). A model
        with other dimensions is an error that says so.

    Returns
    -------
    ContinuousPlant

    Raises
    ------
    TypeError
        If ``plant`` is not a python-control LTI model.
    ValueError
        If its dimensions are not ``shape`` (SISO by default), its sample time
        differs from ``sample_time``, or it has no continuous ZOH equivalent
        (a pole on the negative real axis).
    """
    check_system_shape(plant, "`plant`", shape, hint="stage.plant[0, 0] for y4")
    system = control.ss(plant)
    n_y, n_u = system.noutputs, system.ninputs
    A = np.array(system.A, dtype=float)
    B = np.array(system.B, dtype=float).reshape(-1, n_u)
    C = np.array(system.C, dtype=float).reshape(n_y, -1)
    D = np.array(system.D, dtype=float).reshape(n_y, n_u)
    if control.isctime(system, strict=True) or system.dt == 0:
        return ContinuousPlant(A, B, C, D)
    if system.dt is None or system.dt is True:
        raise ValueError(
            f"`plant` has an unspecified sample time (dt={system.dt!r}). Give it the "
            f"fast sample time, e.g. control.ss(A, B, C, D, {sample_time})."
        )
    if not math.isclose(float(system.dt), sample_time, rel_tol=1e-9):
        raise ValueError(
            f"`plant` has sample time dt={float(system.dt)!r} s but the data have "
            f"sample_time={sample_time!r} s. Pass the model discretised at the fast "
            "(actuator) sample time, or a continuous model."
        )
    return _inverse_zoh(A, B, C, D, sample_time)


def check_system_shape(system, name: str, shape: tuple | None, *, hint: str):
    """Check ``system`` is a python-control model with ``shape == (n_y, n_u)``.

    ``shape=None`` (or ``(1, 1)``) asks for a SISO model, with the SISO message
    of :func:`lrmfrf._validation.check_siso_system`.
    """
    if shape is None or tuple(shape) == (1, 1):
        return check_siso_system(system, name, discrete=False, hint=hint)
    if not isinstance(system, (control.StateSpace, control.TransferFunction)):
        raise TypeError(
            f"{name} must be a control.StateSpace or TransferFunction (python-control "
            f"StateSpace); got {type(system).__name__}. Build it with control.ss(...)."
        )
    if (system.noutputs, system.ninputs) != tuple(shape):
        raise ValueError(
            f"{name} has {system.noutputs} output(s) and {system.ninputs} input(s), "
            f"but the records have {shape[0]} output and {shape[1]} input "
            "channel(s). Pass a model with one output per row of y_l and one "
            "input per row of u_h (e.g. stage.plant[0:2, 0:2])."
        )
    return system


def _inverse_zoh(Phi, Gamma, C, D, sample_time) -> ContinuousPlant:
    n = Phi.shape[0]
    if n == 0:
        return ContinuousPlant(Phi, Gamma, C, D)
    eig = np.linalg.eigvals(Phi)
    bad = (np.abs(eig.imag) < 1e-9 * np.maximum(1.0, np.abs(eig))) & (eig.real <= 0)
    if bad.any():
        raise ValueError(
            "`plant` is discrete with a pole on the non-positive real axis "
            f"(z = {eig[bad][0].real:.4g}); it is not the zero-order-hold "
            "discretisation of a continuous model. Pass the continuous model instead."
        )
    m = Gamma.shape[1]
    augmented = np.zeros((n + m, n + m))
    augmented[:n, :n] = Phi
    augmented[:n, n:] = Gamma
    augmented[n:, n:] = np.eye(m)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        log = scipy.linalg.logm(augmented)
    log = np.real_if_close(log, tol=1e6)
    if np.iscomplexobj(log):
        raise ValueError(
            "`plant` has no real continuous zero-order-hold equivalent. Pass the "
            "continuous model instead."
        )
    log = np.asarray(log, dtype=float) / sample_time
    A, B = log[:n, :n], log[:n, n:]
    check = scipy.linalg.expm(log * sample_time)
    error = np.max(np.abs(check - augmented)) / max(1.0, np.max(np.abs(augmented)))
    if not np.isfinite(error) or error > 1e-6:
        raise ValueError(
            "`plant` could not be converted to its continuous zero-order-hold "
            f"equivalent (round-trip error {error:.2g}). Pass the continuous model."
        )
    return ContinuousPlant(A, B, C, D)


def _split_delay(delay: float, sample_time: float) -> tuple[int, float]:
    """``delay = whole T + frac``, ``0 <= frac < T`` (a frac within 1e-12 T of
    zero is zero)."""
    delay = max(float(delay), 0.0)
    whole = int(math.floor(delay / sample_time + 1e-12))
    frac = delay - whole * sample_time
    if frac < 1e-12 * sample_time:
        frac = 0.0
    return whole, frac


def _zoh_delay_matrices(plant: ContinuousPlant, sample_time: float):
    """Exact ZOH matrices with input delay ``d T + eps``, ``0 <= eps < T``.

    ``x[k+1] = Phi x[k] + Gamma0 u[k-d] + Gamma1 u[k-d-1]``. With one delay
    per input (``plant.delay`` a tuple) ``whole`` and ``has_frac`` are arrays
    of shape ``(n_u,)`` and column ``j`` of ``Gamma0``/``Gamma1`` is input
    ``j``'s with its own ``d_j`` and ``eps_j``.
    """
    n = plant.n_states
    m = plant.n_inputs

    def integral(h, B):  # (exp(A h), int_0^h exp(A s) ds B)
        k = B.shape[1]
        aug = np.zeros((n + k, n + k))
        aug[:n, :n] = plant.A * h
        aug[:n, n:] = B * h
        e = scipy.linalg.expm(aug)
        return e[:n, :n], e[:n, n:]

    if np.ndim(plant.delay) == 0:  # one delay for all inputs
        whole, frac = _split_delay(plant.delay, sample_time)
        Phi_rest, Gamma0 = integral(sample_time - frac, plant.B)
        if frac > 0:
            Phi_frac, Psi = integral(frac, plant.B)
            Gamma1 = Phi_rest @ Psi
            Phi = Phi_rest @ Phi_frac
        else:
            Gamma1 = np.zeros_like(Gamma0)
            Phi = Phi_rest
        return Phi, Gamma0, Gamma1, whole, frac > 0
    # one delay per input: each column with its own fraction of a sample
    Phi, _ = integral(sample_time, plant.B[:, :0])
    Gamma0 = np.zeros((n, m))
    Gamma1 = np.zeros((n, m))
    whole = np.zeros(m, dtype=int)
    has_frac = np.zeros(m, dtype=bool)
    for j, delay in enumerate(plant.input_delays):
        whole[j], frac = _split_delay(delay, sample_time)
        column = plant.B[:, j:j + 1]
        Phi_rest, gamma0 = integral(sample_time - frac, column)
        Gamma0[:, j:j + 1] = gamma0
        if frac > 0:
            _, psi = integral(frac, column)
            Gamma1[:, j:j + 1] = Phi_rest @ psi
            has_frac[j] = True
    return Phi, Gamma0, Gamma1, whole, has_frac


def discrete_response(
    plant: ContinuousPlant, frequencies: np.ndarray, sample_time: float
) -> np.ndarray:
    """Frequency response of the exact ZOH discretisation of ``plant``.

    Parameters
    ----------
    plant : ContinuousPlant
    frequencies : ndarray of shape (K,)
        Frequencies in Hz (``z = exp(j 2 pi f T)``).
    sample_time : float
        Sample time ``T`` in seconds.

    Returns
    -------
    ndarray of shape (K,) (SISO) or (n_y, n_u, K), complex
    """
    z = np.exp(2j * np.pi * np.asarray(frequencies, dtype=float) * sample_time)
    Phi, Gamma0, Gamma1, whole, has_frac = _zoh_delay_matrices(plant, sample_time)
    n = plant.n_states
    zinv = 1.0 / z
    rows = plant.C  # (n_y, n): every output row at once
    if np.ndim(whole):  # one delay per input: factors of shape (n_u, K)
        feed = plant.D[..., None] * np.where(has_frac[:, None], zinv, 1.0)
        shift = zinv ** whole[:, None]
    else:
        feed = plant.D[..., None] * (zinv if has_frac else 1.0)
        shift = zinv**whole
    if n:
        m = plant.n_inputs
        parts = _resolvent_apply(Phi, [*Gamma0.T, *Gamma1.T], z, rows)
        responses = [x0 + x1 * zinv for x0, x1 in zip(parts[:m], parts[m:],
                                                        strict=True)]
        response = np.stack(responses, axis=-2) + feed  # (n_y, n_u, K)
    else:
        response = np.broadcast_to(feed, plant.D.shape + z.shape).astype(complex)
    response = response * shift
    return response[0, 0] if plant.is_siso else response


def _resolvent_apply(matrix, columns, points, row):
    """``row (p I - matrix)^-1 column`` for every point, via the Schur form.

    One complex Schur decomposition and a back substitution vectorised over
    the points: ``O(n^2 K)`` instead of ``K`` dense solves.
    """
    T, Q = scipy.linalg.schur(np.asarray(matrix, dtype=complex), output="complex")
    n = T.shape[0]
    left = np.asarray(row, dtype=complex) @ Q  # (n,) or (n_rows, n)
    results = []
    for column in columns:
        acc = np.repeat((Q.conj().T @ np.asarray(column, dtype=complex))[:, None],
                        points.size, axis=1)
        # elementwise updates only: tiny BLAS calls thread badly on a busy machine
        for i in range(n - 1, -1, -1):
            acc[i] /= points - T[i, i]
            if i:
                acc[:i] += T[:i, i, None] * acc[i]
        results.append((left[..., :, None] * acc).sum(axis=-2))
    return results


def frequency_response(system, frequencies: np.ndarray, sample_time: float):
    """Frequency response of a python-control model on a grid in Hz.

    Discrete models are evaluated at ``z = exp(j 2 pi f dt)``, continuous ones
    at ``s = j 2 pi f`` (``sample_time`` is then not used). Shape ``(K,)`` for
    a SISO model, ``(n_outputs, n_inputs, K)`` otherwise.
    """
    freqs = np.asarray(frequencies, dtype=float)
    if control.isdtime(system, strict=True):
        points = np.exp(2j * np.pi * freqs * float(system.dt))
    else:
        points = 2j * np.pi * freqs
    ss = control.ss(system)
    siso = ss.ninputs == 1 and ss.noutputs == 1
    n = ss.nstates
    D = np.asarray(ss.D, dtype=complex)
    if n == 0:
        response = np.broadcast_to(D[..., None], D.shape + freqs.shape).copy()
    else:
        rows = np.asarray(ss.C)
        columns = list(np.asarray(ss.B).T)
        response = np.stack(_resolvent_apply(np.asarray(ss.A), columns, points, rows),
                            axis=-2) + D[..., None]
    return response[0, 0] if siso else response


def to_discrete_ss(plant: ContinuousPlant, sample_time: float) -> control.StateSpace:
    """Exact ZOH discretisation as a python-control model (delays as states).

    The delay ``d T + eps`` becomes ``d`` (plus one when ``eps > 0``) extra
    shift-register states on each input. With one delay per input every input
    gets the longest register; input ``j`` enters the plant from its own
    ``d_j`` (the register states past it are unobservable).
    """
    Phi, Gamma0, Gamma1, whole, has_frac = _zoh_delay_matrices(plant, sample_time)
    if np.ndim(whole):
        return _to_discrete_ss_per_input(plant, sample_time, Phi, Gamma0, Gamma1,
                                         whole, has_frac)
    n, m = plant.n_states, plant.n_inputs
    n_shift = whole + (1 if has_frac else 0)
    if n_shift == 0:
        return control.ss(Phi, Gamma0, plant.C, plant.D, sample_time)
    # shift register s[k] = [u[k-1], ..., u[k-n_shift]] (m states each)
    size = n + n_shift * m
    A = np.zeros((size, size))
    B = np.zeros((size, m))
    A[:n, :n] = Phi
    B[n:n + m] = np.eye(m)
    for i in range(1, n_shift):
        A[n + i * m:n + (i + 1) * m, n + (i - 1) * m:n + i * m] = np.eye(m)

    def slot(lag):  # the states holding u[k - lag]
        return slice(n + (lag - 1) * m, n + lag * m)

    def add_input(gain, lag):  # x[k+1] += gain * u[k - lag]
        if lag == 0:
            B[:n] += gain
        else:
            A[:n, slot(lag)] += gain

    add_input(Gamma0, whole)
    if has_frac:
        add_input(Gamma1, whole + 1)
    C = np.zeros((plant.n_outputs, size))
    C[:, :n] = plant.C
    D = np.zeros((plant.n_outputs, m))
    lag_d = whole + (1 if has_frac else 0)
    if lag_d == 0:
        D[:] = plant.D
    else:
        C[:, slot(lag_d)] += plant.D
    return control.ss(A, B, C, D, sample_time)


def _to_discrete_ss_per_input(plant, sample_time, Phi, Gamma0, Gamma1, whole,
                              has_frac) -> control.StateSpace:
    """:func:`to_discrete_ss` with one delay per input (``whole``, ``has_frac``
    of shape ``(n_u,)``)."""
    n, m = plant.n_states, plant.n_inputs
    lags = whole + has_frac.astype(int)  # input j's lag of its feedthrough
    n_shift = int(lags.max())
    size = n + n_shift * m
    A = np.zeros((size, size))
    B = np.zeros((size, m))
    A[:n, :n] = Phi
    if n_shift:
        B[n:n + m] = np.eye(m)
    for i in range(1, n_shift):
        A[n + i * m:n + (i + 1) * m, n + (i - 1) * m:n + i * m] = np.eye(m)
    C = np.zeros((plant.n_outputs, size))
    C[:, :n] = plant.C
    D = np.zeros((plant.n_outputs, m))

    def state(lag, j):  # the state holding u_j[k - lag], lag >= 1
        return n + (lag - 1) * m + j

    for j in range(m):
        for gain, lag in ((Gamma0[:, j], whole[j]), (Gamma1[:, j], whole[j] + 1)):
            if lag == whole[j] + 1 and not has_frac[j]:
                continue
            if lag == 0:
                B[:n, j] += gain
            else:
                A[:n, state(lag, j)] += gain
        if lags[j] == 0:
            D[:, j] = plant.D[:, j]
        else:
            C[:, state(lags[j], j)] += plant.D[:, j]
    return control.ss(A, B, C, D, sample_time)


def resonances(plant: ContinuousPlant, *, max_damping: float = 0.3) -> list[Resonance]:
    """Lightly damped complex pole pairs of ``plant``, sorted by frequency.

    Parameters
    ----------
    plant : ContinuousPlant
    max_damping : float, default=0.3
        Pairs with a larger damping ratio are not listed.

    Returns
    -------
    list of Resonance
    """
    poles = np.linalg.eigvals(plant.A) if plant.n_states else np.array([])
    upper = poles[poles.imag > 1e-9 * np.maximum(1.0, np.abs(poles))]
    found = []
    for pole in upper:
        omega = abs(pole)
        zeta = -pole.real / omega
        if zeta < max_damping:
            found.append((omega / (2 * np.pi), zeta))
    found.sort()
    return [Resonance(f, z, i) for i, (f, z) in enumerate(found)]
