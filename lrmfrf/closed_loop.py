r"""The open-loop plant from an FRF identified in closed loop.

Setting (paper eq. EquivalentSystems): the excitation ``r`` enters at the plant
input, ``u = r - c`` with ``c`` the output of a known discrete controller ``C``
that reads the outputs ``S y`` (``S`` selects ``feedback_outputs``), and an
estimator was fitted from ``r`` to the slow-rate outputs ``y_l``. It estimated
the equivalent system ``G_eq``; :func:`plant_from_closed_loop` removes the
known loop and returns the plant ``P``.

**Fast-rate loop** (``controller.dt == sample_time``). Per fast bin,
``G_eq = P (I + C S P)^-1``, hence ``I - C S G_eq = (I + C S P)^-1`` and

.. math:: P = G_{eq} (I - C S G_{eq})^{-1}.

**Slow-rate loop** (``controller.dt == F sample_time``, vision in the loop).
The controller runs on the slow samples ``y_l(m) = y_h(m F)`` and its output
is held over ``F`` fast samples (zero-order hold), ``u_h(n) = r(n) - c(\lfloor
n / F \rfloor)``. With ``N = M F`` and the unnormalised DFTs on the fast and
slow grids (periodic steady state; transients are the estimator's business):

1. Hold: ``sum_n c(floor(n/F)) e^{-j 2 pi k n / N} = C_slow(k) H(k)`` with
   ``H(k) = sum_{i<F} exp(-j 2 pi k i / N)``, ``C_slow`` ``M``-periodic in k.
2. Controller: ``C_slow(k) = C_l(k) S Y_l(k)``, ``C_l(k)`` the controller at
   ``z = exp(j 2 pi k / M)`` (its own sample time ``F Ts``).
3. Downsampling: ``Y_l(k) = (1/F) sum_f Y_h(k + f M)``, and ``Y_h = P U_h``.

Hence ``Y_l(k) = (1/F) sum_f P(k_f) R(k_f) - Lam(k) C_l(k) S Y_l(k)`` with
``k_f = k + f M`` and ``Lam(k) = (1/F) sum_f P(k_f) H(k_f)``, so

.. math:: Y_l(k) = \frac{1}{F} \sum_f (I + \Lambda C_l S)^{-1} P(k_f) R(k_f):

the data from ``r`` to ``y_l`` follow the beyond-Nyquist model with
``G_eq(k_f) = (I + Lam(k) C_l(k) S)^-1 P(k_f)``. Summing this over the bands
with the weights ``H(k_f) / F`` gives ``Lam_eq = (I + Lam C_l S)^-1 Lam``, hence
``I - Lam_eq C_l S = (I + Lam C_l S)^-1`` and the inverse map

.. math:: P(k_f) = (I - \Lambda_{eq}(k) C_l(k) S)^{-1} G_{eq}(k_f),

(SISO: ``P = G_eq / (1 - Lam_eq C_l)``), which needs ``G_eq`` on every band
``k + f M`` of a slow bin: the estimate must cover the whole one-sided fast
DFT grid (LRM/LPM do; bins above ``N/2`` are the complex conjugates).

**Uncertainty** (first order). Fast loop: ``dP = (I + P C S) dG_eq (I - C S
G_eq)^-1``. Slow loop: ``dP(k_f) = Z sum_g dG_eq(k_g) R_g`` with ``Z = (I -
Lam_eq C_l S)^-1`` and ``R_g = delta_{fg} I + (H(k_g) / F) C_l S P(k_f)``.
Both are ``dP = L (sum_g dG_g R_g)`` with a left factor mixing the output
rows; with ``J[o, i, p, j] = E[dG_oi conj(dG_pj)]`` the covariance of the
entries of one bin (``frf_joint_cov_`` of the estimator, between output rows
too),

.. math:: E|dP_{ab}|^2 = \sum_g \sum_{o,p,i,j} L_{ao} \bar L_{ap}
          (R_g)_{ib} (\bar R_g)_{jb} J_g[o, i, p, j]

(``_entry_variance``). The rows
of ``dG_eq`` are correlated when the loop feeds the output noise back: the
noise then reaches several outputs through the controller and the plant, and
the residuals of the rows' local fits in a window are correlated
(:func:`lrmfrf.uncertainty.cross_row_covariance`); with ``(I + P C S)``
mixing the rows, the cross terms can cancel much of the diagonal ones (a
3x2 slow loop, fed-back bins: ``frf_std_`` 1.10-1.86x the Monte-Carlo std
without them, 1.05-1.23x with them; the rest is the estimator's per-row
std, 1.00-1.09x there, and its correlation, 0.55 against 0.68 measured,
magnified by the cancellation; a fast loop: 1.11-1.53x and 1.05-1.24x;
``benchmarks/closed_loop_row_covariance.py``).
Without ``frf_joint_cov_`` the rows are independent, each with the covariance
``frf_cov_`` of the estimator (``E[dG_oi conj(dG_oj)]``), or with
independent entries of variances ``frf_std_**2`` when it has none.
Neglected: covariance between bins (the F bands of one slow bin come from
one local fit) and the pseudo-covariance ``E[dG dG^T]`` (which matters only
where a bin and its mirror ``N - k`` fall in the same band set, i.e. the DC
and slow Nyquist slow bins).
"""

from __future__ import annotations

import math

import control
import numpy as np

from ._validation import check_discrete_controller, check_feedback_outputs
from .simulate import _matrix_response, _system_matrices

__all__ = ["ClosedLoopPlant", "plant_from_closed_loop"]

# Loop matrices worse conditioned than this mark their bins invalid.
_MAX_LOOP_CONDITION = 1e12


class ClosedLoopPlant:
    """The open-loop plant recovered by :func:`plant_from_closed_loop`.

    Attributes
    ----------
    frequencies_ : ndarray of shape (K,)
        Frequencies in Hz (those of the estimator).
    frf_ : ndarray of complex, shape (K,) or (n_y, n_u, K)
        Plant FRF ``P``; 1-D when ``n_u == n_y == 1``. NaN where invalid.
    frf_std_ : ndarray of shape (K,) or (n_y, n_u, K)
        First-order standard deviation ``sqrt(E|dP|^2)`` (module docstring
        for what is neglected). NaN where invalid.
    valid_ : ndarray of bool, shape (K,) or (n_y, n_u, K)
        False at bins where an entry of the estimate it depends on is invalid
        (all entries of the bin, and for a slow loop of all bands of its slow
        bin), where the loop matrix ``I - Q`` is singular (condition number or
        cancellation factor ``||(I - Q)^-1|| ||Q||`` above 1e12), or where the
        controller has a pole on the unit circle (an integrator at DC: the
        loop maps the plant to zero there, for a slow loop on all bands of
        the slow bin). The same for all entries of a bin.
    sample_time_ : float
        Fast sample time in s.
    downsampling_factor_ : int
        ``F`` of the estimator.
    n_inputs_, n_outputs_ : int
        Plant inputs ``n_u`` and outputs ``n_y``.
    feedback_outputs_ : tuple of int
        Outputs the controller reads.
    loop_rate_ : {"fast", "slow"}
        Rate of the controller.
    """

    def __init__(self, **attributes):
        for name, value in attributes.items():
            setattr(self, name, value)

    def __repr__(self) -> str:
        return (
            f"ClosedLoopPlant(n_outputs_={self.n_outputs_}, n_inputs_="
            f"{self.n_inputs_}, loop_rate_={self.loop_rate_!r}, "
            f"K={self.frequencies_.size})"
        )

    def to_frd(self, *, return_std: bool = False):
        """The valid bins as a ``control.FrequencyResponseData``.

        Parameters
        ----------
        return_std : bool, default=False
            Also return ``frf_std_`` at the same bins.

        Returns
        -------
        frd : control.FrequencyResponseData
            ``n_y`` outputs, ``n_u`` inputs, ``omega`` in rad/s, ``dt`` the
            fast sample time; bins with ``valid_ == False`` are left out.
        std : ndarray of shape (n_valid,) or (n_y, n_u, n_valid)
            Only with ``return_std=True``.
        """
        keep = self.valid_ if self.valid_.ndim == 1 else self.valid_.all(axis=(0, 1))
        frd = control.FrequencyResponseData(
            self.frf_[..., keep], 2 * np.pi * self.frequencies_[keep],
            dt=self.sample_time_,
        )
        if return_std:
            return frd, self.frf_std_[..., keep].copy()
        return frd


def plant_from_closed_loop(
    estimator,
    controller: control.StateSpace | control.TransferFunction,
    feedback_outputs=None,
    *,
    hold: str = "zoh",
) -> ClosedLoopPlant:
    """Open-loop plant FRF from a closed-loop FRF and the known controller.

    The excitation ``r`` enters at the plant input and ``u = r - C
    y[feedback_outputs]``; ``estimator`` was fitted from ``r`` to the
    outputs (the equivalent systems ``G_eq = P (I + C P_y)^-1``). A fast-rate
    controller (``controller.dt == sample_time_``) gives ``P = G_eq (I - C
    G_eq[fb])^-1`` per bin; a slow-rate controller (``controller.dt == F
    sample_time_``) that reads the slow samples and holds its output over
    ``F`` fast samples gives ``P(k + f M) = (I - Lam_eq(k) C_l(k) S)^-1
    G_eq(k + f M)`` (derivation in :mod:`lrmfrf.closed_loop`).

    Parameters
    ----------
    estimator : fitted estimator
        Any object with the fitted attributes ``frequencies_``, ``frf_``,
        ``frf_std_``, ``valid_``, ``sample_time_``, ``downsampling_factor_``
        (and, for MIMO, ``n_inputs_``, ``n_outputs_``; optionally
        ``frf_cov_`` of shape (n_y, n_u, n_u, K), and ``frf_joint_cov_`` of
        shape (n_y, n_u, n_y, n_u, K), the covariance between output rows
        too, read when there are several outputs), e.g. a fitted
        :class:`lrmfrf.LRMBeyondNyquist` (whose ``frf_joint_cov_`` is
        computed on this first access: 2x the fit's time at M = 400, 20x at
        M = 40000). A
        slow-rate loop needs the full
        one-sided DFT grid ``k / (N Ts)``, ``k = 0..N//2``.
    controller : control.StateSpace or control.TransferFunction
        Discrete controller with ``n_u`` outputs and ``len(feedback_outputs)``
        inputs; its ``dt`` decides the loop rate.
    feedback_outputs : sequence of int, optional
        Indices of the outputs the controller reads; default all outputs
        (SISO: the output).
    hold : {"zoh"}, default "zoh"
        Hold of a slow-rate controller's output (zero-order hold; the only
        one supported).

    Returns
    -------
    ClosedLoopPlant

    Raises
    ------
    sklearn.exceptions.NotFittedError
        If ``estimator`` has no ``frf_``.
    TypeError
        If ``controller`` is not a python-control LTI system.
    ValueError
        For a continuous controller, a ``dt`` matching neither rate, shapes
        that do not match ``feedback_outputs``, an unknown ``hold``, or a
        slow-rate loop on an estimate that is not on the full DFT grid.

    Examples
    --------
    >>> import control, numpy as np
    >>> from types import SimpleNamespace
    >>> from lrmfrf.simulate import true_frf, frequency_grid
    >>> plant = control.ss([[0.9]], [[1.0]], [[1.0]], [[0.0]], 1e-3)
    >>> controller = control.ss([], [], [], [[0.5]], 1e-3)
    >>> loop = control.feedback(plant, controller)
    >>> G = true_frf(loop, 12)
    >>> fit = SimpleNamespace(frequencies_=frequency_grid(12, 1e-3), frf_=G,
    ...     frf_std_=np.zeros(7), valid_=np.ones(7, bool), sample_time_=1e-3,
    ...     downsampling_factor_=3)
    >>> P = plant_from_closed_loop(fit, controller)
    >>> bool(np.allclose(P.frf_, true_frf(plant, 12)))
    True
    """
    estimate = _read_estimate(estimator)
    n_outputs, n_inputs = estimate["frf"].shape[:2]
    if hold != "zoh":
        raise ValueError(
            f"hold must be 'zoh' (zero-order hold, the only one supported); got "
            f"{hold!r}."
        )
    feedback = check_feedback_outputs(feedback_outputs, n_outputs)
    A, B, C, D, dt = _controller_matrices(controller, n_inputs, feedback)
    sample_time, F = estimate["sample_time"], estimate["F"]
    if math.isclose(dt, sample_time, rel_tol=1e-9):
        rate = "fast"
        z = np.exp(2j * np.pi * estimate["frequencies"] * sample_time)
        frf, var, valid = _fast_loop(estimate, _matrix_response(A, B, C, D, z),
                                     feedback)
        valid &= ~_at_pole(A, z)
    elif math.isclose(dt, F * sample_time, rel_tol=1e-9):
        rate = "slow"
        frf, var, valid = _slow_loop(estimate, (A, B, C, D), feedback)
    else:
        raise ValueError(
            f"controller.dt={dt!r} s matches neither the fast sample time "
            f"{sample_time!r} s (fast-rate loop) nor F * sample_time = "
            f"{F * sample_time!r} s (slow-rate loop). Discretise the controller "
            "at the rate it runs at."
        )
    frf[..., ~valid] = np.nan
    std = np.sqrt(var)
    std[..., ~valid] = np.nan
    valid = np.broadcast_to(valid, frf.shape).copy()
    if estimate["siso"]:
        frf, std, valid = frf[0, 0], std[0, 0], valid[0, 0]
    return ClosedLoopPlant(
        frequencies_=estimate["frequencies"].copy(),
        frf_=frf,
        frf_std_=std,
        valid_=valid,
        sample_time_=sample_time,
        downsampling_factor_=F,
        n_inputs_=n_inputs,
        n_outputs_=n_outputs,
        feedback_outputs_=feedback,
        loop_rate_=rate,
    )


# ---------------------------------------------------------------------------
# Private helpers
# ---------------------------------------------------------------------------


def _read_estimate(estimator) -> dict:
    """The contract attributes as arrays: frf (n_y, n_u, K), cov (n_y, n_u,
    n_u, K), valid (K,) (all entries of a bin valid)."""
    from sklearn.exceptions import NotFittedError

    if not hasattr(estimator, "frf_"):
        raise NotFittedError(
            f"This {type(estimator).__name__} instance is not fitted yet (it has "
            "no frf_). Fit it from the excitation r to the outputs first."
        )
    frequencies = np.asarray(estimator.frequencies_, dtype=float)
    frf = np.asarray(estimator.frf_, dtype=complex)
    std = np.asarray(estimator.frf_std_, dtype=float)
    valid = np.asarray(estimator.valid_, dtype=bool)
    siso = frf.ndim == 1
    n_outputs = int(getattr(estimator, "n_outputs_", 1))
    n_inputs = int(getattr(estimator, "n_inputs_", 1))
    shape = (n_outputs, n_inputs, frequencies.size)
    if siso and n_outputs == n_inputs == 1:
        frf, std, valid = frf[None, None], std[None, None], valid[None, None]
    if frf.shape != shape or std.shape != shape or valid.shape != shape:
        raise ValueError(
            f"the estimator's frf_, frf_std_ and valid_ must have shape "
            f"(n_outputs_, n_inputs_, K) = {shape} (or (K,) for SISO); got "
            f"{frf.shape}, {std.shape} and {valid.shape}."
        )
    cov = getattr(estimator, "frf_cov_", None)
    if cov is None:
        eye = np.eye(n_inputs)
        cov = eye[None, :, :, None] * (std**2)[:, :, None, :]
    else:
        cov = np.asarray(cov, dtype=complex)
        if cov.shape != (n_outputs, n_inputs, n_inputs, frequencies.size):
            raise ValueError(
                f"the estimator's frf_cov_ must have shape (n_y, n_u, n_u, K) = "
                f"{(n_outputs, n_inputs, n_inputs, frequencies.size)}; got "
                f"{cov.shape}."
            )
    # (K, n_y, n_u, n_y, n_u): the rows' blocks on the diagonal, or the
    # estimator's covariance between rows too (read only when rows can mix)
    joint = getattr(estimator, "frf_joint_cov_", None) if n_outputs > 1 else None
    if joint is None:
        joint = np.zeros((frequencies.size, n_outputs, n_inputs, n_outputs,
                          n_inputs), dtype=complex)
        for o in range(n_outputs):
            joint[:, o, :, o, :] = np.moveaxis(cov[o], -1, 0)
    else:
        joint = np.asarray(joint, dtype=complex)
        expected = (n_outputs, n_inputs, n_outputs, n_inputs, frequencies.size)
        if joint.shape != expected:
            raise ValueError(
                f"the estimator's frf_joint_cov_ must have shape (n_y, n_u, n_y, "
                f"n_u, K) = {expected}; got {joint.shape}."
            )
        joint = np.moveaxis(joint, -1, 0)
    valid_bins = valid.all(axis=(0, 1)) & np.isfinite(frf).all(axis=(0, 1))
    return {
        "frequencies": frequencies,
        "frf": frf,
        "cov": joint,
        "valid": valid_bins,
        "siso": siso,
        "sample_time": float(estimator.sample_time_),
        "F": int(estimator.downsampling_factor_),
    }


def _controller_matrices(controller, n_inputs: int, feedback: tuple[int, ...]):
    check_discrete_controller(
        controller, hint="Discretise it, e.g. control.sample_system(C, Ts, 'tustin')."
    )
    if controller.noutputs != n_inputs or controller.ninputs != len(feedback):
        raise ValueError(
            f"the controller must have n_u = {n_inputs} outputs and "
            f"len(feedback_outputs) = {len(feedback)} inputs (feedback_outputs="
            f"{feedback}); got {controller.noutputs} outputs and "
            f"{controller.ninputs} inputs. Pass the feedback_outputs it reads."
        )
    return _system_matrices(controller, None)


def _batched(array: np.ndarray) -> np.ndarray:
    """(a, b, K) -> (K, a, b)."""
    return np.moveaxis(array, -1, 0)


def _unbatched(array: np.ndarray) -> np.ndarray:
    return np.moveaxis(array, 0, -1)


def _safe_inverse(matrices: np.ndarray, subtracted: np.ndarray):
    """Inverses of the loop matrices ``X = I - Q``, (K, n, n), and where they
    are usable: finite, ``cond(X)`` and the cancellation factor ``||X^-1||
    ||Q||`` (by which forming ``I - Q`` amplifies relative errors of ``Q``)
    below ``_MAX_LOOP_CONDITION``. The factor is the loop gain: a scalar loop
    ``1 - q`` has condition 1 but loses all digits when ``q`` is ``1 + 1e-13``.
    """
    eye = np.eye(matrices.shape[1])
    finite = np.isfinite(matrices).all(axis=(1, 2)) & np.isfinite(subtracted).all(
        axis=(1, 2))
    safe = np.where(finite[:, None, None], matrices, eye)
    with np.errstate(all="ignore"):
        ok = finite & (np.linalg.cond(safe) < _MAX_LOOP_CONDITION)
        safe[~ok] = eye
        inverse = np.linalg.inv(safe)
        gain = np.linalg.norm(np.where(ok[:, None, None], subtracted, 0), ord=2,
                              axis=(1, 2))
        ok &= np.linalg.norm(inverse, ord=2, axis=(1, 2)) * gain < _MAX_LOOP_CONDITION
    return inverse, ok


def _sandwich(right, joint) -> np.ndarray:
    """``T[k, o, p, b] = sum_ij right_ib J[o, i, p, j] conj(right_jb)``: the
    covariance between rows ``o`` and ``p`` of column ``b`` of ``dG right``.

    ``right`` (K, n_u, n_u), ``joint`` (K, n_y, n_u, n_y, n_u) with
    ``J[o, i, p, j] = E[dG_oi conj(dG_pj)]``; returns (K, n_y, n_y, n_u).
    """
    return np.einsum("kib,koipj,kjb->kopb", right, joint, right.conj())


def _entry_variance(left, rows) -> np.ndarray:
    """``E|(left X)_ab|^2`` from the row covariance ``rows`` of ``X``
    (:func:`_sandwich`); ``left`` (K, n_y, n_y); returns (K, n_y, n_u)."""
    return np.einsum("kao,kopb,kap->kab", left, rows, left.conj()).real


def _fast_loop(estimate, controller_frf, feedback):
    G = _batched(estimate["frf"])  # (K, n_y, n_u)
    Cz = _batched(controller_frf)  # (K, n_u, n_fb)
    n_outputs, n_inputs = G.shape[1:]
    with np.errstate(all="ignore"):
        gain = Cz @ G[:, feedback, :]
    inverse, ok = _safe_inverse(np.eye(n_inputs) - gain, gain)
    valid = estimate["valid"] & ok
    with np.errstate(all="ignore"):
        P = G @ inverse
        left = np.tile(np.eye(n_outputs, dtype=complex), (G.shape[0], 1, 1))
        left[:, :, feedback] += P @ Cz
        var = _entry_variance(left, _sandwich(inverse, estimate["cov"]))
    return _unbatched(P), _unbatched(var), valid


def _slow_loop(estimate, controller, feedback):
    frequencies, F = estimate["frequencies"], estimate["F"]
    n_samples = _full_grid_length(frequencies, estimate["sample_time"], F)
    slow = n_samples // F
    K = frequencies.size
    mirror = np.arange(n_samples)
    upper = mirror > n_samples // 2
    mirror[upper] = n_samples - mirror[upper]
    # the estimate on the two-sided grid q = f M + k, reshaped (F, M, ...)
    G = _batched(estimate["frf"])[mirror]
    G[upper] = G[upper].conj()
    cov = estimate["cov"][mirror]
    cov[upper] = cov[upper].conj()
    valid = estimate["valid"][mirror].reshape(F, slow).all(axis=0)
    q = np.arange(n_samples)
    hold = np.exp(-2j * np.pi * np.outer(q, np.arange(F)) / n_samples).sum(axis=1)
    z_slow = np.exp(2j * np.pi * np.arange(slow) / slow)
    Cl = _batched(_matrix_response(*controller, z_slow))  # (M, n_u, n_fb)
    n_outputs, n_inputs = G.shape[1:]
    with np.errstate(all="ignore"):
        weighted = (G * hold[:, None, None]).reshape(F, slow, n_outputs, n_inputs)
        lam = weighted.mean(axis=0)  # (M, n_y, n_u)
        gain = np.zeros((slow, n_outputs, n_outputs), dtype=complex)
        gain[:, :, feedback] = lam @ Cl
    Z, ok = _safe_inverse(np.eye(n_outputs) - gain, gain)
    valid &= ok & ~_at_pole(controller[0], z_slow)
    bins = np.arange(K)
    k = bins % slow
    with np.errstate(all="ignore"):
        P = Z[k] @ G[:K]
        # dP(q) = Z sum_g dG(k_g) R_g, R_g = delta I + (H(k_g)/F) C_l S P(q)
        CSP = Cl[k] @ P[:, feedback, :]  # (K, n_u, n_u)
        rows = np.zeros((K, n_outputs, n_outputs, n_inputs), dtype=complex)
        for band in range(F):  # (bins independent: no cross-band terms)
            source = k + band * slow
            right = (hold[source] / F)[:, None, None] * CSP
            right[source == bins] += np.eye(n_inputs)
            rows += _sandwich(right, cov[source])
        var = _entry_variance(Z[k], rows)
    return _unbatched(P), _unbatched(var), valid[k]


def _at_pole(A: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Where ``z`` is (within 1e-9) a pole of the controller on the unit circle:
    its gain is infinite there (e.g. an integrator at DC), the loop maps the
    plant to zero and the data cannot identify it."""
    if A.shape[0] == 0:
        return np.zeros(z.shape, dtype=bool)
    poles = np.linalg.eigvals(A)
    return (np.abs(z[:, None] - poles[None, :]) < 1e-9).any(axis=1)


def _full_grid_length(frequencies: np.ndarray, sample_time: float, F: int) -> int:
    """``N`` of an estimate on the one-sided grid ``k / (N Ts)``, ``k = 0..N//2``."""
    message = (
        "a slow-rate loop needs the estimate on the full one-sided fast DFT "
        "grid k / (N sample_time), k = 0..N//2, with N a multiple of F (as "
        "LRMBeyondNyquist and LPMBeyondNyquist give; not a spectral-analysis "
        "segment grid)"
    )
    if frequencies.size < 2 or frequencies[0] != 0.0:
        raise ValueError(message + f"; got {frequencies.size} frequencies.")
    n_samples = int(round(1.0 / (frequencies[1] * sample_time)))
    expected = np.arange(n_samples // 2 + 1) / (n_samples * sample_time)
    if (
        n_samples % F
        or frequencies.size != expected.size
        or not np.allclose(frequencies, expected, rtol=1e-9, atol=0)
    ):
        raise ValueError(message + f"; got {frequencies.size} frequencies for "
                         f"N = {n_samples}, F = {F}.")
    return n_samples
