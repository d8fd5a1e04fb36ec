"""Periodic local frequency windows and the regressor of eq. (Kvector).

The local model of the paper around slow bin ``k`` uses the ``2n+1`` slow bins
``k+r``, ``r = -n..n``. Windows wrap periodically (``k+r mod M`` for the slow
output, ``k+r+fM mod N`` for the fast input, see ``docs/method.md``): the DFT is
periodic, the estimate stays exactly conjugate-symmetric and the variance
formula holds at the edges.

The regressor is built with the *scaled* offset ``x = r/n`` instead of ``r``
(the model class is the same, only the coefficients of ``r^s`` are rescaled by
``n^s``); raw powers up to 7 on ``[-18, 18]`` give condition numbers near
1e15.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

__all__ = ["LocalModelLayout", "band_indices", "window_offsets", "local_regressor"]


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
    n_inputs : int, default=1
        ``n_u`` inputs. The local problem of one output row holds the local
        models of all inputs over all ``F`` bands: ``F n_u`` "bands", band
        ``b = i F + f`` being input ``i`` at ``U_i(k+r+fM)`` (see
        :func:`band_indices`). Nothing else depends on ``n_u``.

    Notes
    -----
    Column order (paper's eq. SummedParameters, Kronecker order "power outer,
    band inner"): the coefficient of ``x^s`` for band ``b`` is column
    ``s*n_bands + b``; then the transient polynomial of experiment ``p`` at columns
    ``n_system + p*(R_t+1) + s``; then the denominator coefficients ``e_1..e_Re``.
    """

    F: int
    half_window: int
    num_degree: int
    transient_degree: int
    den_degree: int
    n_experiments: int = 1
    n_inputs: int = 1

    @property
    def n_bands(self) -> int:
        """Number of input bands of the local problem, ``F n_u``."""
        return self.F * self.n_inputs

    @property
    def window(self) -> int:
        """Number of slow bins in a window, ``2n+1``."""
        return 2 * self.half_window + 1

    @property
    def n_system(self) -> int:
        """Number of system-numerator columns, ``(R_g+1) F n_u``."""
        return (self.num_degree + 1) * self.n_bands

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


def band_indices(centre: np.ndarray, layout: LocalModelLayout, n_slow: int):
    """Indices into the flattened inputs of the bands at slow bins ``centre``.

    The inputs of all experiments are kept as (P, n_u N) arrays (input ``i``
    at ``i N .. (i+1) N - 1``; SISO: the (P, N) DFT itself). Band
    ``b = i F + f`` at slow bin ``j`` is input ``i`` at fast bin
    ``(j + fM) mod N``.

    Parameters
    ----------
    centre : ndarray of int, any shape
        Slow bins ``j`` (any integers; taken periodically).
    layout : LocalModelLayout
    n_slow : int
        ``M``.

    Returns
    -------
    ndarray of shape centre.shape + (n_bands,), int
    """
    F = layout.F
    N = F * n_slow
    b = np.arange(layout.n_bands)
    offset = (b // F) * N
    return offset + (centre[..., None] + n_slow * (b % F)) % N


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
    U : ndarray of shape (P, n_u N), complex
        Unnormalised DFT of the fast inputs of each experiment, inputs
        concatenated (see :func:`band_indices`; ``(P, N)`` for one input).
    Y : ndarray of shape (P, M), complex
        Unnormalised DFT of the slow output (one output channel) of each
        experiment.
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
    P = U.shape[0]
    M = Y.shape[1]
    r, x = window_offsets(layout.half_window)
    L = r.size
    B = slow_bins.size
    centre = slow_bins[:, None] + r[None, :]  # (B, L)
    slow_idx = centre % M
    fast_idx = band_indices(centre, layout, M)  # (B, L, n_bands)

    u_win = np.moveaxis(U[:, fast_idx], 0, 1)  # (B, P, L, n_bands)
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


# ---------------------------------------------------------------------------
# Structured normal equations: the Gram matrix of every window from moments
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class LocalBasis:
    """Well-conditioned polynomial bases of one window and their monomial map.

    The fast solver parameterises each polynomial of the local model in a
    basis ``[1, q_1(x), .., q_R(x)]`` (numerator, transient) or
    ``[q_1(x), .., q_Re(x)]`` (denominator), where the ``q_s`` are
    orthonormal on the window grid and span ``x, .., x^R``. They vanish at
    ``x = 0``, so the coefficient of the constant ``1`` is the value at the
    window centre (``G(k+fM)/F``, ``T(k)``) in both bases; the model class is
    the same as with monomials.

    Attributes
    ----------
    num, transient : ndarray of shape (2n+1, R+1)
        Basis values at the window offsets (first column ones).
    den : ndarray of shape (2n+1, R_e)
    num_to_monomial, transient_to_monomial : ndarray of shape (R+1, R+1)
        ``c_monomial = T @ c_basis``.
    den_to_monomial : ndarray of shape (R_e, R_e)
    """

    num: np.ndarray
    transient: np.ndarray
    den: np.ndarray
    num_to_monomial: np.ndarray
    transient_to_monomial: np.ndarray
    den_to_monomial: np.ndarray


def _vanishing_basis(x: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal basis of span(x, .., x^degree) and its monomial map."""
    if degree == 0:
        return np.empty((x.size, 0)), np.empty((0, 0))
    vander = x[:, None] ** np.arange(1, degree + 1)
    q, r = np.linalg.qr(vander)
    sign = np.sign(np.diag(r))
    q, r = q * sign, r * sign[:, None]
    return q, np.linalg.inv(r)


def _with_constant(x: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    q, to_mono = _vanishing_basis(x, degree)
    basis = np.concatenate([np.ones((x.size, 1)), q], axis=1)
    transform = np.zeros((degree + 1, degree + 1))
    transform[0, 0] = 1.0
    transform[1:, 1:] = to_mono
    return basis, transform


def local_basis(layout: LocalModelLayout) -> LocalBasis:
    """Build the :class:`LocalBasis` of a layout (fixed per layout)."""
    _, x = window_offsets(layout.half_window)
    num, num_t = _with_constant(x, layout.num_degree)
    tra, tra_t = _with_constant(x, layout.transient_degree)
    den, den_t = _vanishing_basis(x, layout.den_degree)
    return LocalBasis(num, tra, den, num_t, tra_t, den_t)


class StructuredWindows:
    """The local problems of a batch of windows without forming ``A``.

    Every column of ``A`` (eq. Kvector) is a basis polynomial ``w(r)`` times a
    base sequence on the window: ``U(k+r+fM)`` (system, band ``f``), ``1``
    (transient), ``-Y_l(k+r)`` (denominator). The Gram ``A^H A``, ``A^H b``
    and ``b^H b`` of all windows are therefore weighted sliding sums of
    products of base sequences, computed as a few matrix products
    (:meth:`normal_equations`), and the residual ``b - A theta`` and
    ``A^H r`` are polynomial evaluations times windows (:meth:`residual`,
    :meth:`adjoint`). The parameters are in the basis of :func:`local_basis`
    and in the *internal* column order :attr:`order` (``layout`` columns,
    with the window-centre columns of the system and transients last).

    Parameters
    ----------
    U : ndarray of shape (P, n_u N), complex
        Inputs concatenated (see :func:`band_indices`).
    Y : ndarray of shape (P, M), complex
    slow_bins : ndarray of shape (B,), int, in ``0..M-1``
    layout : LocalModelLayout
    basis : LocalBasis, optional
    """

    def __init__(self, U, Y, slow_bins, layout: LocalModelLayout, basis=None):
        self.layout = layout
        self.basis = local_basis(layout) if basis is None else basis
        self._data = (U, Y, slow_bins)
        self.n_windows = slow_bins.size
        self._groups = self._column_groups()
        self.order = np.concatenate([g[2] for g in self._groups])
        position = np.empty(layout.n_params, dtype=int)
        position[self.order] = np.arange(layout.n_params)
        self._positions = [position[g[2]] for g in self._groups]
        bounds = np.cumsum([0] + [g[2].size for g in self._groups])
        self._spans = [
            slice(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)
        ]

    @cached_property
    def u_win(self) -> np.ndarray:
        """Inputs on the windows, ``U_i(k+r+fM)``, shape (P, n_bands, B, 2n+1)."""
        U, Y, slow_bins = self._data
        r, _ = window_offsets(self.layout.half_window)
        idx = band_indices(slow_bins[:, None] + r, self.layout, Y.shape[1])
        return U[:, np.moveaxis(idx, -1, 0)]

    @cached_property
    def y_win(self) -> np.ndarray:
        """Outputs on the windows, ``Y_l(k+r)``, shape (P, B, 2n+1)."""
        _, Y, slow_bins = self._data
        r, _ = window_offsets(self.layout.half_window)
        return Y[:, (slow_bins[:, None] + r) % Y.shape[1]]

    def _column_groups(self):
        """(kind, index, layout columns) of each group, centre columns last."""
        lay = self.layout
        F, Rg, Rt = lay.n_bands, lay.num_degree, lay.transient_degree
        groups = []
        for f in range(F):
            groups.append(("num", f, np.arange(1, Rg + 1) * F + f))
        for p in range(lay.n_experiments):
            start = lay.transient_column(p)
            groups.append(("tra", p, np.arange(start + 1, start + Rt + 1)))
        den = lay.den_columns
        groups.append(("den", 0, np.arange(den.start, den.stop)))
        for f in range(F):
            groups.append(("num0", f, np.array([f])))
        for p in range(lay.n_experiments):
            groups.append(("tra0", p, np.array([lay.transient_column(p)])))
        return groups

    def _weights(self, kind: str) -> np.ndarray:
        b = self.basis
        return {
            "num": b.num[:, 1:],
            "num0": b.num[:, :1],
            "tra": b.transient[:, 1:],
            "tra0": b.transient[:, :1],
            "den": b.den,
            "rhs": np.ones((b.num.shape[0], 1)),
        }[kind]

    def _base(self, kind: str, index: int):
        """Base sequences on the windows, (P, B, L), or ``("const", p)``."""
        if kind in ("num", "num0"):
            return self.u_win[:, index]
        if kind == "den":
            return -self.y_win
        if kind == "rhs":
            return self.y_win
        return ("const", index)

    @staticmethod
    def _pair_series(base_a, base_b):
        """``sum_p conj(a_p) b_p`` on the windows, ``"ones"`` or None (zero)."""
        const_a = isinstance(base_a, tuple)
        const_b = isinstance(base_b, tuple)
        if const_a and const_b:
            return "ones" if base_a[1] == base_b[1] else None
        if const_a:
            return base_b[base_a[1]]
        if const_b:
            return np.conj(base_a[base_b[1]])
        if base_a is base_b:
            return np.sum(base_a.real**2 + base_a.imag**2, axis=0)
        out = np.conj(base_a[0]) * base_b[0]
        for p in range(1, base_a.shape[0]):
            out += np.conj(base_a[p]) * base_b[p]
        return out

    def _block(self, base_a, base_b, w_a, w_b):
        """``sum_r conj(w_a base_a) w_b base_b``, shape (B, m_a, m_b)."""
        B = self.n_windows
        kernel = (w_a[:, :, None] * w_b[:, None, :]).reshape(w_a.shape[0], -1)
        series = self._pair_series(base_a, base_b)
        shape = (B, w_a.shape[1], w_b.shape[1])
        if series is None:
            return np.zeros(shape)
        if isinstance(series, str):
            return np.broadcast_to(np.sum(kernel, axis=0).reshape(shape[1:]), shape)
        return _weighted_sums(series, kernel).reshape(shape)

    def normal_equations(self):
        """Gram matrices, ``A^H b`` and ``b^H b`` of every window.

        Returns
        -------
        gram : ndarray of shape (B, n_params, n_params), complex
            In the internal column order; only the lower triangle is filled
            (what :func:`numpy.linalg.cholesky` reads).
        rhs : ndarray of shape (B, n_params), complex
        bb : ndarray of shape (B,), float
        """
        p = self.layout.n_params
        B = self.n_windows
        gram = np.empty((B, p, p), dtype=complex)
        rhs = np.empty((B, p), dtype=complex)
        groups = [(k, i) for k, i, _ in self._groups]
        spans = self._spans
        bases = [self._base(k, i) for k, i in groups]
        weights = [self._weights(k) for k, _ in groups]
        ones = self._weights("rhs")
        for c in range(len(groups)):
            if weights[c].shape[1] == 0:
                continue
            for a in range(c + 1):
                if weights[a].shape[1] == 0:
                    continue
                gram[:, spans[c], spans[a]] = self._block(
                    bases[c], bases[a], weights[c], weights[a]
                )
            rhs[:, spans[c]] = self._block(bases[c], self.y_win, weights[c], ones)[
                :, :, 0
            ]
        bb = np.sum(self.y_win.real**2 + self.y_win.imag**2, axis=(0, 2))
        return gram, rhs, bb

    def _polynomials(self, theta: np.ndarray):
        """Values on the window of each group's polynomial, by group."""
        values = {}
        for (kind, index, _), span in zip(self._groups, self._spans, strict=True):
            w = self._weights(kind)
            if w.shape[1] == 0:
                continue
            part = _times_real(theta[:, span], w.T)  # (B, L)
            key = (kind.rstrip("0"), index)
            values[key] = values.get(key, 0) + part
        return values

    def residual(self, theta: np.ndarray) -> np.ndarray:
        """``b - A theta`` of every window.

        Parameters
        ----------
        theta : ndarray of shape (B, n_params), complex
            Internal basis and order.

        Returns
        -------
        ndarray of shape (P, B, 2n+1), complex
        """
        values = self._polynomials(theta)
        model = 0
        for f in range(self.layout.n_bands):
            if ("num", f) in values:
                model = model + values[("num", f)] * self.u_win[:, f]
        if ("den", 0) in values:
            model = model - values[("den", 0)] * self.y_win
        res = self.y_win - model
        for p in range(self.layout.n_experiments):
            if ("tra", p) in values:
                res[p] -= values[("tra", p)]
        return res

    def adjoint(self, res: np.ndarray) -> np.ndarray:
        """``A^H res`` of every window, internal order.

        Parameters
        ----------
        res : ndarray of shape (P, B, 2n+1), complex

        Returns
        -------
        ndarray of shape (B, n_params), complex
        """
        out = np.empty((self.n_windows, self.layout.n_params), dtype=complex)
        for (kind, index, _), span in zip(self._groups, self._spans, strict=True):
            w = self._weights(kind)
            if w.shape[1] == 0:
                continue
            base = self._base(kind, index)
            if isinstance(base, tuple):
                weighted = res[index]
            else:
                weighted = np.conj(base[0]) * res[0]
                for p in range(1, base.shape[0]):
                    weighted += np.conj(base[p]) * res[p]
            out[:, span] = _times_real(weighted, w)
        return out

    def column_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """Basis polynomial and base sequence of every column, internal order.

        Returns
        -------
        weights : ndarray of shape (2n+1, n_params), float
            ``w(r)`` of each column on the window.
        col_base : ndarray of shape (n_params,), int
            The base sequence each column multiplies: ``b`` for the input band
            ``b`` (:func:`band_indices`), ``n_bands+p`` for the transient
            constant of experiment ``p``, ``n_bands+P`` for ``-Y_l(k+r)``
            (denominator).
        """
        lay = self.layout
        F, P = lay.n_bands, lay.n_experiments
        code = {"num": lambda i: i, "tra": lambda i: F + i, "den": lambda i: F + P}
        weights, col_base = [], []
        for kind, index, _ in self._groups:
            w = self._weights(kind)
            weights.append(w)
            col_base += [code[kind.rstrip("0")](index)] * w.shape[1]
        return np.concatenate(weights, axis=1), np.array(col_base, dtype=np.int64)

    def to_layout(self, theta: np.ndarray) -> np.ndarray:
        """Map internal-basis parameters to monomial coefficients, layout order.

        Parameters
        ----------
        theta : ndarray of shape (B, n_params), complex
            Internal basis and order.

        Returns
        -------
        ndarray of shape (B, n_params), complex
        """
        return _times_real(theta, self.to_layout_matrix)

    @cached_property
    def to_layout_matrix(self) -> np.ndarray:
        """Real ``T`` of shape (n_params, n_params) with ``theta_layout =
        theta_internal @ T`` (a column permutation, then per-group changes of
        basis; it depends on the layout only)."""
        lay, b = self.layout, self.basis
        T = np.zeros((lay.n_params, lay.n_params))
        T[np.arange(lay.n_params), self.order] = 1.0
        F = lay.n_bands
        for f in range(F):
            cols = np.arange(lay.num_degree + 1) * F + f
            T[:, cols] = T[:, cols] @ b.num_to_monomial.T
        for p in range(lay.n_experiments):
            start = lay.transient_column(p)
            cols = np.arange(start, start + lay.transient_degree + 1)
            T[:, cols] = T[:, cols] @ b.transient_to_monomial.T
        cols = lay.den_columns
        T[:, cols] = T[:, cols] @ b.den_to_monomial.T
        return T


def _weighted_sums(series: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``sum_r series[b, r] kernel[r, j]`` as real matrix products."""
    if np.iscomplexobj(series):
        return _times_real(series, kernel)
    return series @ kernel


def _times_real(values: np.ndarray, real: np.ndarray) -> np.ndarray:
    """Complex ``values @ real`` as one real matrix product without copies.

    The complex rows are read as interleaved ``(re, im)`` floats and multiplied
    by ``real (x) I_2``, whose output rows are again interleaved ``(re, im)``.
    """
    values = np.ascontiguousarray(values, dtype=complex)
    interleaved = np.zeros((2 * real.shape[0], 2 * real.shape[1]))
    interleaved[::2, ::2] = real
    interleaved[1::2, 1::2] = real
    out = values.view(float) @ interleaved
    return out.view(complex)
