"""Periodic local frequency windows and the regressor of eq. (Kvector).

The local model of the paper around slow bin ``k`` uses the ``2n+1`` slow bins
``k+r``, ``r = -n..n``. Windows wrap periodically (``k+r mod M`` for the slow
output, ``k+r+fM mod N`` for the fast input, see ``METHOD.md``): the DFT is
periodic, the estimate stays exactly conjugate-symmetric and the variance
formula holds at the edges.

The regressor is built with the *scaled* offset ``x = r/n`` instead of ``r``
(the model class is the same, only the coefficients of ``r^s`` are rescaled by
``n^s``); raw powers up to 7 on ``[-18, 18]`` give condition numbers near
1e15.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LocalModelLayout", "window_offsets", "local_regressor"]


@dataclass(frozen=True)
class LocalModelLayout:
    """Sizes and column positions of the local problem of eq. (Kvector).

    Parameters
    ----------
    F : int
        Downsampling factor (number of aliased bands).
    half_window : int
        ``n``: the window holds ``2n+1`` slow bins.
    num_degree, transient_degree, den_degree : int
        ``R_g``, ``R_t`` and ``R_e`` of the paper.
    n_experiments : int, default=1
        ``P`` records that share the system parameters; each has its own
        transient columns.

    Notes
    -----
    Column order (paper's eq. SummedParameters, Kronecker order "power outer,
    band inner"): the coefficient of ``x^s`` for band ``f`` is column
    ``s*F + f``; then the transient polynomial of experiment ``p`` at columns
    ``n_system + p*(R_t+1) + s``; then the denominator coefficients ``e_1..e_Re``.
    """

    F: int
    half_window: int
    num_degree: int
    transient_degree: int
    den_degree: int
    n_experiments: int = 1

    @property
    def window(self) -> int:
        """Number of slow bins in a window, ``2n+1``."""
        return 2 * self.half_window + 1

    @property
    def n_system(self) -> int:
        """Number of system-numerator columns, ``(R_g+1) F``."""
        return (self.num_degree + 1) * self.F

    @property
    def n_transient(self) -> int:
        """Number of transient columns over all experiments, ``P (R_t+1)``."""
        return self.n_experiments * (self.transient_degree + 1)

    @property
    def n_params(self) -> int:
        """Number of complex parameters of one local problem."""
        return self.n_system + self.n_transient + self.den_degree

    @property
    def n_equations(self) -> int:
        """Number of complex equations of one local problem, ``P (2n+1)``."""
        return self.n_experiments * self.window

    @property
    def dof(self) -> int:
        """Residual degrees of freedom ``q`` of the noise-variance estimate."""
        return self.n_equations - self.n_params

    @property
    def den_columns(self) -> slice:
        """Columns of the denominator coefficients ``e_1..e_Re``."""
        start = self.n_system + self.n_transient
        return slice(start, start + self.den_degree)

    def transient_column(self, experiment: int) -> int:
        """Column of the transient value ``T(k)`` of one experiment."""
        return self.n_system + experiment * (self.transient_degree + 1)


def window_offsets(half_window: int) -> tuple[np.ndarray, np.ndarray]:
    """Return the integer offsets ``r`` and the scaled offsets ``x = r/n``.

    Returns
    -------
    r : ndarray of shape (2n+1,), int
    x : ndarray of shape (2n+1,), float, in [-1, 1]
    """
    r = np.arange(-half_window, half_window + 1)
    return r, r / max(half_window, 1)


def local_regressor(
    U: np.ndarray, Y: np.ndarray, slow_bins: np.ndarray, layout: LocalModelLayout
) -> tuple[np.ndarray, np.ndarray]:
    """Build the local regressors of eq. (Kvector) for a batch of slow bins.

    Parameters
    ----------
    U : ndarray of shape (P, N), complex
        Unnormalised DFT of the fast input of each experiment.
    Y : ndarray of shape (P, M), complex
        Unnormalised DFT of the slow output of each experiment.
    slow_bins : ndarray of shape (B,), int
        Window centres ``k`` in ``0..M-1``.
    layout : LocalModelLayout

    Returns
    -------
    A : ndarray of shape (B, P*(2n+1), n_params), complex
        The transpose of the paper's ``K_n``: one row per equation, with
        ``x^s U(k+r+fM)``, ``x^s`` (transient) and ``-x^s Y_l(k+r)``.
    b : ndarray of shape (B, P*(2n+1)), complex
        The measured ``Y_l(k+r)``.
    """
    P, N = U.shape
    M = Y.shape[1]
    F = layout.F
    r, x = window_offsets(layout.half_window)
    L = r.size
    B = slow_bins.size
    centre = slow_bins[:, None] + r[None, :]  # (B, L)
    slow_idx = centre % M
    fast_idx = (centre[:, :, None] + M * np.arange(F)) % N  # (B, L, F)

    u_win = np.moveaxis(U[:, fast_idx], 0, 1)  # (B, P, L, F)
    y_win = np.moveaxis(Y[:, slow_idx], 0, 1)  # (B, P, L)

    powers_g = x[:, None] ** np.arange(layout.num_degree + 1)  # (L, Rg+1)
    system = powers_g[None, None, :, :, None] * u_win[:, :, :, None, :]
    system = system.reshape(B, P * L, layout.n_system)

    powers_t = x[:, None] ** np.arange(layout.transient_degree + 1)  # (L, Rt+1)
    transient = np.einsum("pq,ls->plqs", np.eye(P), powers_t)
    transient = np.broadcast_to(
        transient.reshape(1, P * L, layout.n_transient), (B, P * L, layout.n_transient)
    )

    powers_e = x[:, None] ** np.arange(1, layout.den_degree + 1)  # (L, Re)
    den = -(y_win[..., None] * powers_e).reshape(B, P * L, layout.den_degree)

    A = np.concatenate([system, transient.astype(system.dtype), den], axis=-1)
    return A, y_win.reshape(B, P * L)
