"""The local-model kernel shared by LRM and LPM: all windows, in chunks.

``fit_local_models`` takes the DFTs of the records, builds the regressor of
eq. (Kvector) for a chunk of slow bins at a time (bounded memory), solves the
closed form eq. (linearSolution), and returns the FRF in the ``F`` aliased
bands with its Lemma 2 variance. ``one_sided_fast_grid`` maps the slow-bin
results to the fast grid ``k = 0..N//2`` using conjugate symmetry.

The estimators use the streaming form: ``iter_local_fit_rows`` solves the same
problems chunk by chunk from the one-sided DFTs of the real records
(``OneSidedSpectra``), each chunk on compact spectra that hold only its
windows' bins, and ``fast_grid_targets`` says which fast bins a chunk fills;
nothing of the size of the grid is allocated besides the outputs.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, replace

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import fft as sp_fft
from scipy.linalg import solve_toeplitz

from ._blas_threads import blas_controller as _blas_controller  # noqa: F401 (as before)
from ._blas_threads import single_threaded_blas as _single_threaded_blas
from ._compiled import LANES, chunk_quantum
from .solvers import (
    CHUNK_BYTES,
    lemma2_variance,
    noise_variance,
    qr_chunk_size,
    resolve_backend,
    _solve_normal_rows,
    solve_local_least_squares,
)
from .windows import (
    LocalModelLayout,
    band_indices,
    local_regressor,
    window_offsets,
)

__all__ = [
    "SOLVERS",
    "dft",
    "LocalModelFit",
    "OneSidedSpectra",
    "fit_local_models",
    "fit_one_sided",
    "iter_local_fits",
    "iter_local_fit_rows",
    "fast_grid_targets",
    "default_chunk_size",
    "experiments_needed",
    "half_slow_bins",
    "nearly_dependent_windows",
    "normalise_spectra",
    "one_sided_fast_grid",
    "power_of_two_exponent",
    "rescale_local_fit",
    "scale_by_power_of_two",
    "window_excitation",
]

#: Solvers of :func:`fit_local_models`.
SOLVERS = ("auto", "normal", "qr")

#: A window whose input energy in some band is below this fraction of the
#: average is declared not excited (exact zeros up to DFT round-off).
EXCITATION_TOL = 1e-12

#: Signals whose largest magnitude is within ``2**-ORDINARY_EXPONENT`` ..
#: ``2**ORDINARY_EXPONENT`` are used as they are; others are normalised by a
#: power of two before the DFT (see :func:`power_of_two_exponent`). The
#: estimators square DFT values and multiply squares (Gram matrices, variances):
#: with a margin of 64 binary orders for the record length and the window sums
#: this stays far from overflow and underflow.
ORDINARY_EXPONENT = 64


@dataclass
class LocalModelFit:
    """Per-slow-bin results of the local models.

    Attributes
    ----------
    slow_bins : ndarray of shape (B,)
    theta : ndarray of shape (B, n_params), complex
    system : ndarray of shape (B, n_bands), complex
        ``G(k+fM)`` for each window centre ``k`` and band ``f`` (``n_bands =
        F``); with ``n_u`` inputs ``G_i(k+fM)`` at band ``b = i F + f`` of
        ``n_bands = F n_u`` (see :func:`lrmfrf.windows.band_indices`).
    system_var : ndarray of shape (B, n_bands), float
    transient : ndarray of shape (B, P), complex
        Transient value at the window centre (in units of ``Y_l``).
    noise_var : ndarray of shape (B,), float
    rss : ndarray of shape (B,), float
    well_posed : ndarray of shape (B,), bool
    excited : ndarray of shape (B,), bool
    leverage : ndarray of shape (B, n_equations) or None
    system_cov : ndarray of shape (B, n_bands, n_bands), complex, or None
        Lemma 2 covariance ``E[dG_b conj(dG_c)]`` of the band values (when
        requested with ``return_cov``).
    """

    layout: LocalModelLayout
    slow_bins: np.ndarray
    theta: np.ndarray
    system: np.ndarray
    system_var: np.ndarray
    transient: np.ndarray
    noise_var: np.ndarray
    rss: np.ndarray
    well_posed: np.ndarray
    excited: np.ndarray
    leverage: np.ndarray | None = None
    system_cov: np.ndarray | None = None


def dft(x: np.ndarray) -> np.ndarray:
    """Unnormalised DFT along the last axis, the package's convention.

    ``X(k) = sum_n x(n) exp(-2j pi k n / N)`` (eq. DFT3 of the paper, the same
    as :func:`numpy.fft.fft`), computed with :mod:`scipy.fft`, about 3x faster
    on real input of 1.2e6 samples.

    Parameters
    ----------
    x : ndarray of shape (..., N)

    Returns
    -------
    ndarray of shape (..., N), complex
    """
    return sp_fft.fft(x, axis=-1)


def power_of_two_exponent(x: np.ndarray) -> int:
    """Binary exponent that normalises a signal, or 0 for an ordinary one.

    The FRF is a ratio of output to input, so the estimators may scale the
    input and the output by any constants and undo it on the results. Scaling
    by a power of two ``2**-e`` is exact (no rounding, only the exponent
    changes), so the estimate at any finite scale equals the estimate at the
    normalised one. Ordinary data (largest magnitude within
    ``2**±ORDINARY_EXPONENT``) get ``e = 0``: nothing is scaled and the results
    are bit for bit those of the unscaled computation.

    Parameters
    ----------
    x : ndarray
        A finite signal (any shape); for a complex array (a DFT) the largest
        real or imaginary part counts.

    Returns
    -------
    int
        ``e`` such that the largest magnitude of ``x * 2**-e`` is in
        ``[0.5, 1)``, or 0 when ``x`` is ordinary or all zero.

    Examples
    --------
    >>> import numpy as np
    >>> power_of_two_exponent(np.array([3.0, -1.0]))
    0
    >>> power_of_two_exponent(np.array([3.0, -1.0]) * 2.0**200)
    202
    """
    if x.size == 0:
        return 0
    if np.iscomplexobj(x):  # views of the parts, no |x| temporary
        parts = (x.real, x.imag)
    else:
        parts = (x,)
    peak = max(max(float(np.max(p)), -float(np.min(p))) for p in parts)
    if not (0.0 < peak < np.inf):
        return 0
    exponent = int(np.frexp(peak)[1])
    return 0 if abs(exponent) <= ORDINARY_EXPONENT else exponent


def scale_by_power_of_two(x, exponent: int):
    """``x * 2**exponent``, exact, for real or complex arrays.

    Returns ``x`` itself (no copy) when ``exponent == 0``. Values beyond the
    float range become inf (or underflow towards 0), silently: e.g. the
    variance of an FRF of 1e200 is 1e400, which no float holds.

    Parameters
    ----------
    x : ndarray or None
    exponent : int

    Returns
    -------
    ndarray or None
    """
    if exponent == 0 or x is None:
        return x
    x = np.asarray(x)
    with np.errstate(over="ignore", under="ignore"):
        if np.iscomplexobj(x):
            out = np.empty_like(x)
            out.real = np.ldexp(x.real, exponent)
            out.imag = np.ldexp(x.imag, exponent)
            return out
        return np.ldexp(x, exponent)


def normalise_spectra(U: np.ndarray, Y: np.ndarray):
    """DFTs of the inputs and outputs normalised by powers of two.

    Parameters
    ----------
    U : ndarray of shape (P, N), complex
    Y : ndarray of shape (P, M), complex

    Returns
    -------
    U, Y : ndarray
        ``U * 2**-u_exponent`` and ``Y * 2**-y_exponent``: the arrays
        themselves (no copy) for ordinary data.
    u_exponent, y_exponent : int
        From :func:`power_of_two_exponent`; undo with
        :func:`rescale_local_fit`.
    """
    u_exponent = power_of_two_exponent(U)
    y_exponent = power_of_two_exponent(Y)
    U = scale_by_power_of_two(U, -u_exponent)
    Y = scale_by_power_of_two(Y, -y_exponent)
    return U, Y, u_exponent, y_exponent


def rescale_local_fit(
    local_fit: LocalModelFit, u_exponent: int, y_exponent: int
) -> LocalModelFit:
    """Undo the normalisation of the records on every scale-carrying result.

    A fit on ``u * 2**-u_exponent`` and ``y * 2**-y_exponent`` becomes the fit
    on ``u`` and ``y``: system numerators and values scale as ``y/u``,
    transients as ``y``, variances and residuals as their squares; the
    denominator coefficients and the leverages are dimensionless.

    Parameters
    ----------
    local_fit : LocalModelFit
        Fit on the normalised records.
    u_exponent, y_exponent : int
        The exponents of :func:`power_of_two_exponent` used for the input and
        the output.

    Returns
    -------
    LocalModelFit
        ``local_fit`` itself when both exponents are 0, else a rescaled copy.
    """
    if u_exponent == 0 and y_exponent == 0:
        return local_fit
    system_exponent = y_exponent - u_exponent
    return replace(
        local_fit,
        theta=_rescaled_theta(local_fit.theta, local_fit.layout, u_exponent,
                              y_exponent),
        system=scale_by_power_of_two(local_fit.system, system_exponent),
        system_var=scale_by_power_of_two(local_fit.system_var, 2 * system_exponent),
        transient=scale_by_power_of_two(local_fit.transient, y_exponent),
        noise_var=scale_by_power_of_two(local_fit.noise_var, 2 * y_exponent),
        rss=scale_by_power_of_two(local_fit.rss, 2 * y_exponent),
        system_cov=scale_by_power_of_two(local_fit.system_cov, 2 * system_exponent),
    )


def _rescaled_theta(theta, layout, u_exponent: int, y_exponent: int):
    """A copy of the parameters ``theta`` (B, n_params) of records normalised
    by ``2**-u_exponent``, ``2**-y_exponent`` in the records' units (as
    :func:`rescale_local_fit`; negative exponents the other way)."""
    theta = theta.copy()
    n_sys, n_tr = layout.n_system, layout.n_transient
    theta[:, :n_sys] = scale_by_power_of_two(theta[:, :n_sys],
                                             y_exponent - u_exponent)
    transient_cols = slice(n_sys, n_sys + n_tr)
    theta[:, transient_cols] = scale_by_power_of_two(
        theta[:, transient_cols], y_exponent
    )
    return theta


def half_slow_bins(n_slow: int) -> np.ndarray:
    """Slow bins ``0..M//2``: enough for real signals (conjugate symmetry)."""
    return np.arange(n_slow // 2 + 1)


def window_excitation(U: np.ndarray, slow_bins: np.ndarray, layout) -> np.ndarray:
    """Relative input energy of each band in each window.

    Returns
    -------
    ndarray of shape (B, n_bands)
        ``sum_{p,r} |U_{p,i}(k+r+fM)|^2`` divided by its average over all
        windows and bands of input ``i`` (band ``b = i F + f``).
    """
    slow_bins = np.asarray(slow_bins, dtype=int)
    reference = _excitation_reference(
        _mean_input_energy(U, layout.n_inputs), layout
    )
    n_slow = U.shape[1] // layout.n_bands
    return _relative_excitation(U, n_slow, slow_bins, layout, reference)


def _relative_excitation(U, n_slow, bins, layout, reference) -> np.ndarray:
    """:func:`_window_energy` over ``reference`` (0 where that is 0)."""
    energy = _window_energy(U, n_slow, bins, layout)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(reference > 0, energy / reference, 0.0)


#: Relative margin of the shortcut of :func:`_excited_windows`: far above
#: the rounding of a window's sum of ``L`` energies and its division
#: (``(L + 1) 2**-53``, 1e-11 for ``L = 10**5``).
_EXCITED_MARGIN = 1e-9


def _excited_windows(U, n_slow, bins, layout, reference) -> np.ndarray:
    """``(_relative_excitation(...) > EXCITATION_TOL).all(axis=1)``: the same
    booleans, shape (B,).

    For consecutive windows every window of band ``b`` sums ``L`` energies
    of the band's series, each at least its least value ``m``; the computed
    sum is then at least ``L m (1 - 2**-53)**(L-1)`` and its ratio to the
    reference at least ``L m / reference (1 - 2**-53)**L``. A band with ``L m
    > EXCITATION_TOL reference (1 + 1e-9)`` (and ``m`` far from the
    subnormals) is therefore excited in every window, and its window sums are
    not computed; the others are summed and compared as
    :func:`_relative_excitation` does. On a multisine every band clears it
    (its least bin energy is a fair fraction of the mean, against ``1e-12``):
    the sliding sums were most of the excitation test's time.
    """
    series = _energy_series(U, n_slow, bins, layout)
    if series is None:  # not consecutive: as _relative_excitation
        return (_relative_excitation(U, n_slow, bins, layout, reference)
                > EXCITATION_TOL).all(axis=1)
    L = layout.window
    B = bins.size
    least = series.min(axis=1)
    with np.errstate(invalid="ignore", over="ignore"):
        clear = ((least >= _LEAST_NORMAL_SUM) & (reference > 0)
                 & (L * least > EXCITATION_TOL * reference
                    * (1 + _EXCITED_MARGIN)))
    excited = np.ones(B, dtype=bool)
    for b in np.flatnonzero(~clear):
        energy = sliding_window_view(series[b], L).sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            relative = np.where(reference[b] > 0, energy / reference[b], 0.0)
        excited &= relative > EXCITATION_TOL
    return excited


#: Least band energy for the shortcut of :func:`_excited_windows`: its
#: partial sums are then normal floats (relative rounding ``2**-53``).
_LEAST_NORMAL_SUM = 2.0**-900


def fit_local_models(
    U: np.ndarray,
    Y: np.ndarray,
    layout: LocalModelLayout,
    *,
    slow_bins: np.ndarray | None = None,
    chunk_size: int | None = None,
    rank_tol: float | None = None,
    return_leverage: bool = False,
    solver: str = "auto",
    refine_steps: int = 1,
    backend: str = "auto",
    return_cov: bool = False,
) -> LocalModelFit:
    """Closed-form local rational models beyond the Nyquist frequency.

    Parameters
    ----------
    U : ndarray of shape (P, n_u N), complex
        Unnormalised DFT (``np.fft.fft``) of the fast inputs, the ``n_u``
        inputs of each experiment concatenated (``(P, N)`` for one input; see
        :func:`lrmfrf.windows.band_indices`).
    Y : ndarray of shape (P, M), complex
        Unnormalised DFT of the slow outputs of one output channel,
        ``N = F M``.
    layout : LocalModelLayout
    slow_bins : ndarray of shape (B,), optional
        Window centres in ``0..M-1``; default ``0..M//2``.
    chunk_size : int, optional
        Windows solved at once; the default bounds a chunk's largest arrays
        to about 64 MiB. The result does not depend on it.
    rank_tol : float, optional
        Passed to :func:`lrmfrf.solvers.solve_local_least_squares`.
    return_leverage : bool, default=False
        Keep the hat-matrix diagonals (for leave-one-out criteria). Needs the
        QR solver.
    solver : {"auto", "normal", "qr"}, default="auto"
        ``"normal"``: structured normal equations with iterative refinement
        (:func:`lrmfrf.solvers.solve_local_normal_equations`, several times
        faster, same results to about 1e-12 on well-posed windows);
        ``"qr"``: equilibrated Householder QR of each window's regressor;
        ``"auto"``: ``"normal"``, or ``"qr"`` when ``return_leverage``.
    refine_steps : int, default=1
        Iterative-refinement steps of the ``"normal"`` solver.
    backend : {"auto", "numpy", "numba"}, default="auto"
        Implementation of the ``"normal"`` solver (see
        :func:`lrmfrf.solvers.solve_local_normal_equations`): ``"auto"`` uses
        the compiled kernel when numba is installed, ``LRMFRF_DISABLE_NUMBA``
        is not set and there are enough windows to pay for it
        (:data:`lrmfrf.solvers.COMPILED_MIN_WORK`). Ignored by ``"qr"``.
    return_cov : bool, default=False
        Also return the Lemma 2 covariance of the band values
        (``LocalModelFit.system_cov``).

    Returns
    -------
    LocalModelFit

    Notes
    -----
    ``U`` and ``Y`` beyond ``2**±ORDINARY_EXPONENT`` are normalised by powers
    of two (exact) and the results scaled back (:func:`normalise_spectra`,
    :func:`rescale_local_fit`), so any finite scale gives the same FRF.
    """
    U, Y, u_exponent, y_exponent = normalise_spectra(U, Y)
    M = Y.shape[1]
    if slow_bins is None:
        slow_bins = half_slow_bins(M)
    slow_bins = np.asarray(slow_bins, dtype=int)
    solver = _check_solver(solver, return_leverage)
    backend = resolve_backend(backend, slow_bins.size, layout.n_params)
    if chunk_size is None:
        # the compiled kernel keeps no batched temporaries (and batches its QR
        # fallback itself): one call for all windows
        compiled = solver == "normal" and backend == "numba"
        chunk_size = slow_bins.size if compiled else default_chunk_size(layout, solver)
    chunk_size = max(1, chunk_size)
    options = _ChunkOptions(
        solver, backend, refine_steps, rank_tol, return_leverage, return_cov
    )
    reference = _excitation_reference(
        _mean_input_energy(U, layout.n_inputs), layout
    )
    parts = []
    with _single_threaded_blas() if solver == "normal" else contextlib.nullcontext():
        for start in range(0, slow_bins.size, chunk_size):
            bins = slow_bins[start : start + chunk_size]
            parts.append(_fit_chunk(U, Y, bins, layout, reference, options))
    fit = _joined_fits(parts, slow_bins)
    return rescale_local_fit(fit, u_exponent, y_exponent)


@dataclass(frozen=True)
class _ChunkOptions:
    """Solver settings shared by the chunks of one fit."""

    solver: str
    backend: str
    refine_steps: int
    rank_tol: float | None
    return_leverage: bool
    return_cov: bool
    eiv: bool = False


def _fit_chunk(U, Y, bins, layout, reference, options: _ChunkOptions):
    """The closed form and its Lemma 2 results on one chunk of windows.

    ``U`` (P, n_u N') and ``Y`` (P, M') are the spectra the windows ``bins``
    read (the full DFTs, or the compact ones of :meth:`OneSidedSpectra.
    window_spectra`); ``reference`` is the mean input energy of
    :func:`_mean_input_energy` of the full records. Returns a
    :class:`LocalModelFit` of the chunk (``slow_bins`` as given).
    """
    return _fit_chunk_rows(U, Y[:, None], bins, layout, reference, options)[0]


def _fit_chunk_rows(U, Y, bins, layout, reference, options: _ChunkOptions):
    """:func:`_fit_chunk` of every output row of ``Y`` (P, n_rows, M'): a
    list of :class:`LocalModelFit`, one per row (the compiled kernel solves
    the rows together, sharing the input and transient block)."""
    nb = layout.n_bands
    # Identifiability of G is decided by the input and transient columns.
    kwargs = {"rank_columns": layout.n_system + layout.n_transient}
    if options.return_cov and not options.eiv:  # (eiv: see _chunk_fit)
        kwargs["cov_columns"] = nb
    if options.rank_tol is not None:
        kwargs["rank_tol"] = options.rank_tol
    theta_rows = eiv_raw = None
    if options.solver == "normal":
        solutions, theta_rows, eiv_raw = _solve_normal_rows(
            U, Y, bins, layout, refine_steps=options.refine_steps,
            backend=options.backend, eiv=options.eiv, **kwargs
        )
    else:
        solutions = []
        for o in range(Y.shape[1]):
            A, b = local_regressor(U, Y[:, o], bins, layout)
            solutions.append(solve_local_least_squares(
                A, b, return_leverage=options.return_leverage, **kwargs
            ))
            del A, b
    excited = _excited_windows(U, Y.shape[-1], bins, layout, reference)
    fits = [_chunk_fit(sol, bins, layout, excited, options) for sol in solutions]
    if options.eiv:
        # the terms computed with the solve (None without them) and the rows'
        # theta, each with a leading row axis (theta: None from the QR solver)
        return fits, (eiv_raw, theta_rows)
    return fits


def _chunk_fit(sol, bins, layout, excited, options: _ChunkOptions):
    """The :class:`LocalModelFit` of one output row from its solution.

    With ``options.eiv`` its ``system_var`` and ``system_cov`` are None: the
    caller (:func:`lrmfrf.uncertainty.iter_calibrated_fit_rows`) replaces
    them by the errors-in-variables ones, and Lemma 2's (``F^2 n_bands^2``
    per window for the covariance: 36 values a window and row on 2x2, F = 3)
    would only be computed to be dropped."""
    F, nb = layout.F, layout.n_bands
    well_posed = sol.well_posed & excited
    noise_var = noise_variance(sol.rss, layout.dof)
    system_cov = system_var = None
    if options.return_cov and not options.eiv:
        system_cov = F**2 * sol.lead_cov * noise_var[:, None, None]
    theta, rss = sol.theta, sol.rss
    system = F * theta[:, :nb]
    if not options.eiv:
        system_var = lemma2_variance(sol.gram_inv_diag[:, :nb], noise_var, F)
    transient_cols = [layout.transient_column(p) for p in range(layout.n_experiments)]
    transient = theta[:, transient_cols]
    bad = np.flatnonzero(~well_posed)
    for arr in (theta, system, system_var, transient, noise_var, rss, system_cov):
        if arr is not None:
            arr[bad] = np.nan
    return LocalModelFit(
        layout=layout,
        slow_bins=bins,
        theta=theta,
        system=system,
        system_var=system_var,
        transient=transient,
        noise_var=noise_var,
        rss=rss,
        well_posed=well_posed,
        excited=excited,
        leverage=sol.leverage if options.return_leverage else None,
        system_cov=system_cov,
    )


def _joined_fits(parts: list[LocalModelFit], slow_bins: np.ndarray) -> LocalModelFit:
    """One fit from the fits of consecutive chunks (the single chunk itself),
    filled into arrays allocated once."""
    if len(parts) == 1:
        return replace(parts[0], slow_bins=slow_bins)
    fields = {}
    B = slow_bins.size
    for name in _PER_WINDOW_FIELDS:
        first = getattr(parts[0], name)
        if first is None:
            fields[name] = None
            continue
        out = np.empty((B,) + first.shape[1:], dtype=first.dtype)
        start = 0
        for part in parts:
            values = getattr(part, name)
            out[start : start + values.shape[0]] = values
            start += values.shape[0]
        fields[name] = out
    return LocalModelFit(layout=parts[0].layout, slow_bins=slow_bins, **fields)


#: The per-window arrays of :class:`LocalModelFit` (all but layout, slow_bins).
_PER_WINDOW_FIELDS = (
    "theta", "system", "system_var", "transient", "noise_var", "rss",
    "well_posed", "excited", "leverage", "system_cov",
)


def _excitation_reference(mean_energy: np.ndarray, layout) -> np.ndarray:
    """Window energy of a band at its input's average: the denominator of the
    relative excitation, shape (n_bands,).

    ``mean_energy`` (n_u,) is ``mean_j sum_p |U_{p,i}(j)|^2`` over the ``N``
    fast bins of each input (:func:`_mean_input_energy`).
    """
    return layout.window * np.repeat(mean_energy, layout.F)


def _mean_input_energy(U: np.ndarray, n_inputs: int) -> np.ndarray:
    """``mean_j sum_p |U_{p,i}(j)|^2`` over the fast bins, per input.

    Parameters
    ----------
    U : ndarray of shape (P, n_u N), complex
        Full DFTs, inputs concatenated.
    n_inputs : int

    Returns
    -------
    ndarray of shape (n_u,)
    """
    parts = U.reshape(U.shape[0], n_inputs, -1)
    return np.array([
        np.sum(parts[:, i].real ** 2 + parts[:, i].imag ** 2) / parts.shape[2]
        for i in range(n_inputs)
    ])


def _window_energy(U: np.ndarray, n_slow: int, bins: np.ndarray, layout):
    """``sum_{p,r} |U_{p,i}(k+r+fM)|^2`` per window ``k`` and band ``b = i F +
    f``, shape (B, n_bands) (``U`` of shape (P, n_u N) with ``N = F n_slow``).

    Consecutive windows that do not wrap around the record (every chunk of
    :func:`iter_local_fits`) are summed with a sliding window over each
    band's energy series; others gather each window's bins.
    """
    n, L = layout.half_window, layout.window
    B = bins.size
    series = _energy_series(U, n_slow, bins, layout)
    if series is not None:
        # (each band's sums on its own 1-D series: the same values as ever)
        out = np.empty((B, layout.n_bands))
        for b in range(layout.n_bands):
            out[:, b] = sliding_window_view(series[b], L).sum(axis=1)
        return out
    out = np.zeros((B, layout.n_bands))
    r, _ = window_offsets(n)
    idx = band_indices(bins[:, None] + r, layout, n_slow)  # (B, L, n_bands)
    for p in range(U.shape[0]):
        values = U[p][idx]
        out += np.sum(values.real**2 + values.imag**2, axis=1)
    return out


def _energy_series(U: np.ndarray, n_slow: int, bins: np.ndarray, layout):
    """``sum_p |U_{p,i}(k+fM)|^2`` over the bins that consecutive windows
    ``bins`` read, per band ``b = i F + f``: shape (n_bands, B + 2n), or None
    when the windows are not consecutive or wrap around the record.

    Compact spectra (:meth:`OneSidedSpectra.window_spectra`) hold the bands
    back to back and are squared and summed at once; each value is the same
    sum over the experiments either way."""
    n, F = layout.half_window, layout.F
    B = bins.size
    first = bins[0] - n if B else 0
    consecutive = (
        B > 0 and first >= 0 and bins[-1] + n < n_slow
        and np.array_equal(bins, np.arange(bins[0], bins[0] + B))
    )
    if not consecutive:
        return None
    width = B + 2 * n
    if first == 0 and width == n_slow and U.shape[1] == layout.n_bands * width:
        return np.sum(U.real**2 + U.imag**2, axis=0).reshape(layout.n_bands, width)
    N = F * n_slow
    out = np.empty((layout.n_bands, width))
    for b in range(layout.n_bands):
        lo = (b // F) * N + (b % F) * n_slow + first
        series = U[:, lo : lo + width]
        out[b] = np.sum(series.real**2 + series.imag**2, axis=0)
    return out


#: Near dependence of the experiments (``docs/method.md`` section 4): in a
#: window whose local problem needs several experiments, an eigenvalue of the
#: experiments' input Gram matrix (see :func:`nearly_dependent_windows`) below
#: this fraction of the largest counts as a dependent experiment. For two
#: experiments that is an input differing from a multiple of the other's by
#: less than about ``2 sqrt(NEAR_DEPENDENCE_TOL)`` (2 %) of its amplitude in the
#: window. On a 3x2 block of ``random_stage(3, mimo=True)`` (F = 3, P = 2, the
#: second input the first plus ``eps`` times white noise, 3 inputs x 10 noise
#: runs) the default std was 0.53-0.87x the RMS error for ``eps = 1e-3 ..
#: 0.02`` at 40-80 dB, with a median error 2.9-36x that of independent inputs
#: (at 60 dB 0.67-1.9 against 0.16); at ``eps = 0.03 .. 0.1``, not flagged,
#: 0.81-0.92x and 1.9-4.3x (``benchmarks/near_dependent.py --snr``).
NEAR_DEPENDENCE_TOL = 1e-4


def experiments_needed(layout: LocalModelLayout) -> int:
    """The fewest experiments with independent inputs for which a window
    holds as many equations as parameters (``k (2n+1) >= (R_g+1) F n_u +
    k (R_t+1) + R_e``); ``n_experiments + 1`` when no number does."""
    spare = layout.window - (layout.transient_degree + 1)
    fixed = layout.n_system + layout.den_degree
    if spare <= 0:
        return layout.n_experiments + 1
    return max(1, -(-fixed // spare))


def nearly_dependent_windows(spectra: OneSidedSpectra, layout: LocalModelLayout,
                             tol: float = NEAR_DEPENDENCE_TOL, *,
                             chunk_size: int | None = None):
    """Windows whose experiments are too close to linearly dependent for
    their local problem, or None when no window can be.

    A window needs :func:`experiments_needed` experiments with independent
    inputs; exactly dependent ones are refused before the fit
    (:meth:`lrmfrf._validation.Records.independent_experiments`). Nearly
    dependent ones (a repeated excitation measured with a noisy input
    sensor) leave the local problem ill-conditioned: its FRF is dominated by
    the noise, and biased by it, far beyond its linearised std. This counts,
    per window ``k``, the eigenvalues above ``tol`` times the largest of the
    experiments' Gram matrix ``C_pq = sum_{i,f,r} U_{p,i}(k+r+fM)
    conj(U_{q,i}(k+r+fM)) / E_{i,f}`` with each experiment scaled to unit
    energy in the window, and flags the windows where that count is below
    the number needed. ``E_{i,f}`` is the energy of input ``i`` over the
    experiments in aliased band ``f`` of the whole record: the units of the
    inputs and the overall levels of their bands do not matter, as they do
    not for the local problem. For two experiments the count is below two
    when the inputs differ from a multiple of each other by less than about
    ``2 sqrt(tol)`` of their amplitude in the window. An experiment that
    replays another's (non-periodic) record with a delay of whole slow
    samples (:func:`_delayed_copies`, to the same ``2 sqrt(tol)`` on the
    samples they share) counts as no experiment in the windows where both
    have input: the delay turns the phase across the window and
    decorrelates the window sums, but at each bin the copy gives the
    original's equations again.

    Nothing is computed (None) with one experiment or when one experiment
    gives a window enough equations (SISO and LPM at the default settings):
    near dependence then only averages the noise. Otherwise the cost is a
    few passes over the input spectra, windows in chunks of bounded memory
    (about 3 ms for 2 x 2, P = 2, N = 1.2e5, plus about 4 ms of
    :func:`_delayed_copies`; under 1 % of the fit), and a Gershgorin bound
    per window; the eigenvalues are computed only at windows the bound does
    not clear.

    Parameters
    ----------
    spectra : OneSidedSpectra
    layout : LocalModelLayout
    tol : float, default=NEAR_DEPENDENCE_TOL
    chunk_size : int, optional
        Windows computed at once; the default holds about 16 MiB of input
        values (all windows of ordinary records). The result does not
        depend on it.

    Returns
    -------
    ndarray of shape (M//2+1,), bool, or None
        True at the windows (slow bins ``0..M//2``) to mark invalid. Windows
        with no input energy at all are left to the excitation test; an
        experiment without input in a window (below ``1e-12`` of the others'
        energy there, e.g. a band-limited experiment next to a broadband one)
        counts as dependent there, as it adds no equation on the FRF.
    """
    P = layout.n_experiments
    need = experiments_needed(layout)
    if P == 1 or need <= 1 or need > P:
        return None
    N, F = spectra.n_samples, spectra.F
    M = N // F
    B = M // 2 + 1
    n, L = layout.half_window, layout.window
    U = spectra.inputs  # (P, n_u, N//2+1)
    n_u = U.shape[1]
    # input i's values in aliased band f scaled by that band's energy over the
    # experiments: the units of the inputs and the levels of their bands do
    # not matter (the local problem is invariant to them)
    scale = np.sqrt(_inverse_band_energy(U, N, F))[:, :, None]  # (n_u, F, 1)
    pairs = [(p, q) for p in range(P) for q in range(p, P)]
    # an experiment that replays another's record with a delay of whole slow
    # samples adds no independent experiment in any window where both have
    # input (its window sums decorrelate as the delay turns the phase)
    copies = _delayed_copies(spectra, tol)
    flagged = np.zeros(B, dtype=bool)
    # windows in chunks: about 2**20 values (16 MiB) of the inputs at a time
    size = chunk_size or max(256, 2**20 // (P * n_u * F))
    for start in range(0, B, size):
        stop = min(B, start + size)
        lo, hi = start - n, stop + n  # the slow bins the windows read
        values = np.empty((P, n_u, F, hi - lo), dtype=complex)
        for f in range(F):  # fast bins lo + fM .. hi - 1 + fM (mod N)
            _periodic_range(U, lo + f * M, hi + f * M, N, values[:, :, f])
        values *= scale
        # per slow bin, the sums over inputs and bands of U_p conj(U_q)
        per_bin = np.empty((len(pairs), hi - lo), dtype=complex)
        parts = values.view(np.float64)  # real and imaginary parts, interleaved
        for s, (p, q) in enumerate(pairs):
            if p == q:  # real: the sums of the squared real and imaginary parts
                squares = np.einsum("ifw,ifw->w", parts[p], parts[p])
                per_bin[s] = squares[0::2] + squares[1::2]
            else:
                np.einsum("ifw,ifw->w", values[p], values[q].conj(), out=per_bin[s])
        del values
        total = np.zeros((len(pairs), hi - lo + 1), dtype=complex)
        np.cumsum(per_bin, axis=1, out=total[:, 1:])
        sums = total[:, L:] - total[:, :-L]  # (pairs, stop - start)
        flagged[start:stop] = _dependent_windows(sums, pairs, P, need, tol,
                                                 copies)
    return flagged


#: Order of the linear-prediction filter that whitens the records before
#: :func:`_delayed_copies` compares them.
_WHITENING_ORDER = 16

#: :func:`_delayed_copies` looks for delays of at most ``N // 8`` fast
#: samples (copies sharing at least 7/8 of the record).
_LONGEST_DELAY = 8


def _delayed_copies(spectra: OneSidedSpectra, tol: float = NEAR_DEPENDENCE_TOL):
    """Pairs ``(p, q)`` of experiments whose input records are, but for the
    first or last ``d F`` fast samples, the same record delayed by ``d`` whole
    slow samples (``0 < d F <= N / 8``; within about ``2 sqrt(tol)``, as the
    near dependence).

    At every slow bin such a copy's aliased input vector is the original's
    times the phase ``exp(-2j pi k d / M)``, plus the leakage of the samples
    only one of them holds, which is smooth over the bins and which the
    transient absorbs: the copy gives the local problems the original's
    equations again. The per-bin rank sees the leakage and the window sums
    of :func:`nearly_dependent_windows` a phase that turns across the window,
    so neither catches it. Per pair, the lag ``d F`` with the largest
    cross-correlation of the records (their means removed and whitened by
    one linear-prediction filter of their mean spectrum; from the one-sided
    spectra) is found, and the records are compared on the samples they
    share at that lag (at least 7/8): a pair is a copy when one differs
    from a multiple of the other there by less than ``4 tol`` of its energy
    (sine of their angle below ``2 sqrt(tol)``). A circular shift (zero
    mismatch on all samples) is refused before
    (:meth:`lrmfrf._validation.Records.independent_experiments`); a shift by
    ``d = 0`` is the near dependence of the window sums. Ordinary independent
    excitations have a mismatch near 1 (above 0.84 for white noise,
    multisines, orthogonal and zippered ones, short records; review30).

    Cost (2 x 2, P = 2, N = 1.2e5): two transforms of length ``N`` (the
    autocorrelation and the filter's gain), per pair one pass over the
    spectra and one transform of length ``M`` (the correlation at the lags,
    all multiples of ``F``); the whitened records only for the pairs
    compared. About 4 ms.
    """
    U = spectra.inputs
    P, n_u = U.shape[:2]
    N, F = spectra.n_samples, spectra.F
    M = N // F
    order = min(_WHITENING_ORDER, N // 8)
    if P < 2 or M < 2 or order < 1:
        return []
    # delays of at most N / _LONGEST_DELAY: a copy that shares less of the
    # record brings enough of its own (1.1-2.6x the error of independent
    # inputs at 1/8 and 1/4 of the record delayed; 1.5-12x at 0.5-10 %)
    shift = np.arange(1, M) * F
    lags = np.concatenate([shift[shift <= N // _LONGEST_DELAY],
                           shift[shift >= N - N // _LONGEST_DELAY]])
    if not lags.size:
        return []
    # each experiment's power spectrum (summed over the inputs)
    parts = np.ascontiguousarray(U).view(np.float64)  # real, imaginary
    squares = np.einsum("pij,pij->pj", parts, parts)
    power = squares[:, 0::2] + squares[:, 1::2]  # (P, N//2+1)
    # Whitened by one FIR filter of the records' mean spectrum (linear
    # prediction of order `order`): a component common to the experiments
    # that dominates their energy (an offset, a periodic set-point, a
    # resonance of a coloured excitation) must not make independent
    # excitations look alike. Filtered circularly, a record's whitened
    # values differ from the linear filter's in its first `order` samples
    # only, which the comparison skips.
    total = power.sum(axis=0)
    total[0] = 0.0  # the records' means
    autocorrelation = sp_fft.irfft(total, n=N)[: order + 1]
    if not autocorrelation[0] > 0.0:
        return []
    autocorrelation[0] *= 1.0 + 1e-9  # a floor: pure sines stay regular
    predictor = solve_toeplitz(autocorrelation[:order], autocorrelation[1:])
    whitening = sp_fft.rfft(np.concatenate([[1.0], -predictor]), n=N)
    # the whitened spectra's products are the records' times the filter's
    # gain |h|^2 (the whitened spectra themselves only for the records
    # compared, below); 0 at DC: the means removed
    gain = whitening.real**2 + whitening.imag**2
    gain[0] = 0.0
    # energies of the whitened records (Parseval on the one-sided spectra)
    weights = np.full(gain.size, 2.0)
    weights[0] = 1.0
    if N % 2 == 0:
        weights[-1] = 1.0
    energy = power @ (gain * weights) / N
    records = {}

    def record(p):  # (n_u, N), whitened
        if p not in records:
            white = U[p] * whitening
            white[:, 0] = 0.0
            records[p] = sp_fft.irfft(white, n=N, axis=-1)
        return records[p]

    copies = []
    for p in range(P):
        for q in range(p + 1, P):
            if not energy[p] * energy[q] > 0.0:
                continue
            cross = np.einsum("ij,ij->j", U[p], U[q].conj())
            cross *= gain
            # sum_t u_p(t) u_q(t-lag) at the lags (multiples of F)
            correlation = _correlation_at_multiples(cross, N, F)[lags // F]
            peak = int(np.argmax(np.abs(correlation)))
            # a copy sharing 7/8 of the samples correlates above about 7/8
            # of the energy at its lag; independent records far below (the
            # records are compared only above a quarter)
            if abs(correlation[peak]) < 0.25 * np.sqrt(energy[p] * energy[q]):
                continue
            lag = int(lags[peak])
            if lag <= N // 2:  # u_p(t) ~ u_q(t - lag), t >= lag
                a = record(p)[:, lag + order:]
                b = record(q)[:, order:N - lag]
            else:  # u_q(t) ~ u_p(t - (N - lag))
                a = record(q)[:, N - lag + order:]
                b = record(p)[:, order:lag]
            a = a - a.mean(axis=1, keepdims=True)
            b = b - b.mean(axis=1, keepdims=True)
            product = float(np.sum(a * a)) * float(np.sum(b * b))
            if product <= 0.0:
                continue
            mismatch = 1.0 - float(np.sum(a * b)) ** 2 / product
            if mismatch < 4.0 * tol:
                copies.append((p, q))
    return copies


def _correlation_at_multiples(cross, N, F):
    """``c(dF)``, ``d = 0 .. N/F - 1``, of the circular correlation ``c(t) =
    irfft(cross, n=N)[t]`` from its one-sided spectrum ``cross``
    (``N//2+1``): ``exp(2j pi j d F / N)`` has period ``M = N/F`` in ``j``,
    so the full spectrum folded onto ``M`` bins (``D_k = sum_f C(k + fM)``)
    and transformed at length ``M`` gives them, ``F`` times cheaper than at
    length ``N``. The full transform when ``F`` does not divide ``N``."""
    if F <= 1 or N % F:
        return sp_fft.irfft(cross, n=N)[::F]
    M = N // F
    H = M // 2 + 1
    full_half = N // 2  # bins 0 .. N//2 are held, the rest are mirrored
    # as irfft: the imaginary parts of DC and (N even) the Nyquist bin ignored
    cross = cross.copy()
    cross[0] = cross[0].real
    if N % 2 == 0:
        cross[-1] = cross[-1].real
    folded = np.zeros(H, dtype=complex)
    for f in range(F):
        # bins j = k + fM, k = 0 .. H-1: held for j <= N/2, else the
        # conjugates of N - j
        lo, hi = f * M, f * M + H
        held = min(hi, full_half + 1)
        if held > lo:
            folded[: held - lo] += cross[lo:held]
        if hi > held:
            start = max(lo, held)  # j = start .. hi-1 -> N - j
            folded[start - lo:] += cross[N - start : N - hi : -1].conj()
    return sp_fft.irfft(folded, n=M) / F


def _aliased_rank(spectrum_of, experiments, n_inputs: int, N: int, F: int,
                  n_bins: int = 256) -> int | None:
    """The typical rank over slow bins of the experiments' aliased inputs.

    ``spectrum_of(p)`` is experiment ``p``'s one-sided input DFT ``(n_u,
    N//2+1)``. At slow bin ``k`` an experiment gives the vector of ``U(k +
    f M)``, ``f < F``, of every input (each experiment scaled to a largest
    vector norm of 1: amplitudes do not matter); the rank of the ``P x F
    n_u`` matrix of these vectors is taken at up to ``n_bins`` bins spread
    over ``0 .. M/2`` (singular values below ``1e-6`` of the bin's largest
    count as zero), and the median is returned over the bins whose largest
    singular value is above ``1e-6`` of the largest of all and which have at
    least ``P`` excited entries (at the others an input that does not excite
    every band would make different experiments look dependent; the fit
    reports those bins itself) and at which every experiment has input (above
    ``1e-6`` of its largest vector norm: experiments that excite interleaved
    bins, e.g. zippered multisines, share no bin and are independent over a
    window). None when no bin qualifies or an experiment has no input at
    all.
    """
    M = N // F
    K = M // 2 + 1
    bins = np.unique(np.linspace(0, K - 1, min(K, n_bins)).round().astype(int))
    fast = bins[:, None] + M * np.arange(F)[None, :]  # (bins, F)
    mirrored = fast > N // 2  # the one-sided DFT holds their conjugates
    source = np.where(mirrored, N - fast, fast)
    vectors = np.empty((bins.size, len(experiments), n_inputs, F), dtype=complex)
    for column, p in enumerate(experiments):
        picked = np.asarray(spectrum_of(p))[:, source]  # (n_u, bins, F)
        picked[:, mirrored] = picked[:, mirrored].conj()
        vectors[:, column] = picked.transpose(1, 0, 2)
    vectors = vectors.reshape(bins.size, len(experiments), n_inputs * F)
    scale = np.max(np.linalg.norm(vectors, axis=2), axis=0)  # per experiment
    if not np.all((scale > 0) & np.isfinite(scale)):
        return None
    vectors /= scale[None, :, None]
    singular = np.linalg.svd(vectors, compute_uv=False)  # (bins, P), descending
    largest = singular[:, 0]
    # bins with input, and with at least P excited (band, input) entries: at
    # the others even different experiments share a direction (an input
    # without energy in some bands, which the fit reports per bin instead)
    entries = np.linalg.norm(vectors, axis=1)  # (bins, F n_u)
    excited_entries = np.sum(entries > 1e-6 * entries.max(axis=1, keepdims=True),
                             axis=1)
    # and at which every experiment has input: where one has none (inputs on
    # interleaved bins, e.g. zippered multisines) the others' vectors say
    # nothing of its dependence, and its windows see it independently
    present = np.all(np.linalg.norm(vectors, axis=2) > 1e-6, axis=1)
    usable = ((largest > 1e-6 * largest.max())
              & (excited_entries >= len(experiments)) & present)
    if not np.any(usable):
        return None
    ranks = np.sum(singular > 1e-6 * largest[:, None], axis=1)[usable]
    return int(np.median(ranks))


def _inverse_band_energy(U, N, F):
    """``1 / sum_{p,j} |U_{p,i}(j + fM)|^2`` over the full DFT's aliased band
    ``f`` (0 for a band without energy), from the one-sided spectra ``U``
    (P, n_u, N//2+1): shape (n_u, F)."""
    M, H = N // F, U.shape[-1]
    energy = np.zeros((U.shape[1], F))
    for i in range(U.shape[1]):
        for f in range(F):
            # band f: the bins k = fM .. (f+1)M - 1, k <= N//2 directly and
            # the others as the mirrors N - k of one-sided bins
            ranges = [(f * M, min((f + 1) * M, H)),
                      (max(N - (f + 1) * M + 1, 1), min(N - f * M, N - H) + 1)]
            for a, b in ranges:
                if b > a:
                    part = U[:, i, a:b]
                    energy[i, f] += (np.einsum("ph,ph->", part.real, part.real)
                                     + np.einsum("ph,ph->", part.imag, part.imag))
    inverse = np.zeros_like(energy)
    np.divide(1.0, energy, out=inverse, where=energy > 0)
    return inverse


def _dependent_windows(sums, pairs, P, need, tol, copies=()):
    """From the window sums of the scaled ``U_p conj(U_q)`` (one row per pair
    of ``pairs``): the windows with fewer than ``need`` eigenvalues of the
    experiments' normalised Gram matrix above ``tol`` times the largest,
    with each delayed copy ``q`` of a pair ``(p, q)`` of ``copies``
    (:func:`_delayed_copies`) left out of that matrix in the windows where
    both experiments have input (a copy of several counted once; a copy the
    window sums already see as dependent is not discounted twice)."""
    B = sums.shape[1]
    # normalised to unit energy per experiment and window (1-D arrays over
    # the windows: the P x P matrices are built only where the bound fails)
    index = {pair: s for s, pair in enumerate(pairs)}
    diag = np.stack([sums[index[p, p]].real for p in range(P)])  # (P, B)
    present = diag > 1e-12 * diag.max(axis=0)
    norm = np.zeros_like(diag)
    np.divide(1.0, np.sqrt(np.abs(diag)), out=norm, where=present)
    # Gershgorin: every eigenvalue within 1 +- the largest off-diagonal row sum
    rows = np.zeros((P, B))
    for (p, q), s in index.items():
        if p != q:
            size = np.abs(sums[s]) * norm[p] * norm[q]
            rows[p] += size
            rows[q] += size
    radius = rows.max(axis=0)
    clear = present.all(axis=0) & (1 - radius > tol * (1 + radius))
    flagged = np.zeros(B, dtype=bool)
    # per window, the delayed copies left out of the count
    dropped = np.zeros((P, B), dtype=bool)
    for p, q in copies:
        dropped[q] |= present[p] & present[q]
    if copies:
        # (a principal submatrix of a clear matrix is clear: the others count)
        flagged[clear] = P - dropped[:, clear].sum(axis=0) < need
    check = np.flatnonzero(~clear & present.any(axis=0))
    if check.size:
        # a copy's row and column zeroed: the other eigenvalues are those of
        # the experiments without it (whether or not the window sums already
        # see it as dependent: a small delay turns the phase little across a
        # window, and subtracting it from the count then discounted it twice)
        kept = norm[:, check] * ~dropped[:, check]
        gram = np.empty((check.size, P, P), dtype=complex)
        for (p, q), s in index.items():
            gram[:, p, q] = sums[s, check] * kept[p] * kept[q]
            gram[:, q, p] = np.conj(gram[:, p, q])
        eig = np.linalg.eigvalsh(gram)  # ascending
        count = np.sum(eig > tol * eig[:, -1:], axis=1)
        flagged[check] = count < need
    return flagged


@dataclass(frozen=True)
class OneSidedSpectra:
    """One-sided DFTs of real records: all the local models read, in half the
    memory of the full DFTs.

    The DFT of a real record is conjugate-symmetric, ``X(N-j) = conj(X(j))``,
    so bins ``0..N//2`` (a real FFT) hold it all; the windows read any bin
    ``j mod N`` through :meth:`window_spectra`. The values are bit for bit
    those of :func:`dft` (the real FFT returns the same numbers as scipy's
    complex FFT of a real record, whose upper half is the exact conjugate).

    Attributes
    ----------
    inputs : ndarray of shape (P, n_u, N//2+1), complex
        One-sided DFTs of the fast inputs.
    outputs : ndarray of shape (P, n_y, M//2+1), complex
        One-sided DFTs of the slow outputs.
    n_samples : int
        ``N``.
    F : int
        Downsampling factor, ``M = N / F``.
    """

    inputs: np.ndarray
    outputs: np.ndarray
    n_samples: int
    F: int

    @classmethod
    def from_records(cls, u: np.ndarray, y: np.ndarray, F: int) -> OneSidedSpectra:
        """DFTs of real records ``u`` (P, n_u, N) and ``y`` (P, n_y, N/F).

        Computed with :func:`numpy.fft.rfft`: the same pocketfft algorithm
        and values as scipy's (checked bit for bit in the tests), but it does
        not keep the plan of each length cached for the life of the process
        (about ``8 N`` bytes, 0.09 GiB at ``N = 1.2e7``).
        """
        return cls(
            np.fft.rfft(u, axis=-1), np.fft.rfft(y, axis=-1), u.shape[-1], int(F)
        )

    @property
    def n_slow(self) -> int:
        """``M``."""
        return self.n_samples // self.F

    @property
    def nbytes(self) -> int:
        """Bytes held (both spectra)."""
        return self.inputs.nbytes + self.outputs.nbytes

    def full_inputs(self) -> np.ndarray:
        """Full input DFTs, inputs concatenated: (P, n_u N), as :func:`dft`."""
        P, n_u, _ = self.inputs.shape
        full = _full_spectrum(self.inputs, self.n_samples)
        return full.reshape(P, n_u * self.n_samples)

    def full_outputs(self, output: int) -> np.ndarray:
        """Full DFT of one output channel of every experiment: (P, M)."""
        return _full_spectrum(self.outputs[:, output], self.n_slow)

    def window_spectra(self, start: int, stop: int, half_window: int, output):
        """Compact spectra of the windows centred on slow bins ``start..stop-1``.

        The windows read slow bins ``k+r`` and fast bins ``k+r+fM`` (mod ``N``)
        for ``|r| <= n``; the compact problem holds exactly those values with
        a slow length ``M' = stop - start + 2n`` laid out so that the local
        problem of window ``k`` is that of bin ``k - start + n`` of the compact
        spectra, read without wrapping (:func:`lrmfrf.windows.band_indices`
        with ``M'`` and ``N' = F M'``).

        ``output`` is one output channel, or a list of them.

        Returns
        -------
        U : ndarray of shape (P, n_u F M'), complex
        Y : ndarray of shape (P, M'), or (P, len(output), M') for a list,
            complex
        bins : ndarray of shape (stop - start,), int
            The compact window centres ``n .. n + stop - start - 1``.
        """
        N, M, F = self.n_samples, self.n_slow, self.F
        lo, hi = start - half_window, stop + half_window  # slow bins (M',)
        P, n_u, _ = self.inputs.shape
        # band f reads fast bins lo + fM .. hi - 1 + fM (mod N): a few runs
        # of consecutive bins, copied with slices
        U = np.empty((P, n_u, F, hi - lo), dtype=complex)
        for f in range(F):
            _periodic_range(self.inputs, lo + f * M, hi + f * M, N, U[:, :, f])
        U = U.reshape(P, -1)
        if np.ndim(output):
            Y = np.empty((P, len(output), hi - lo), dtype=complex)
            for i, o in enumerate(output):
                _periodic_range(self.outputs[:, o], lo, hi, M, Y[:, i])
        else:
            Y = np.empty((P, hi - lo), dtype=complex)
            _periodic_range(self.outputs[:, output], lo, hi, M, Y)
        bins = np.arange(stop - start) + half_window
        return U, Y, bins


def _full_spectrum(half: np.ndarray, length: int) -> np.ndarray:
    """Full DFT (..., length) from its one-sided part (..., length//2+1)."""
    full = np.empty(half.shape[:-1] + (length,), dtype=complex)
    h = length // 2 + 1
    full[..., :h] = half
    np.conjugate(half[..., 1 : length - h + 1][..., ::-1], out=full[..., h:])
    return full


def _periodic_values(half: np.ndarray, idx: np.ndarray, length: int) -> np.ndarray:
    """DFT values at bins ``idx`` in ``0..length-1`` from the one-sided part
    ``half`` (..., length//2+1): ``conj(half[length - j])`` above the middle."""
    mirrored = idx > length // 2
    values = half[..., np.where(mirrored, length - idx, idx)]
    np.conjugate(values, out=values, where=mirrored)
    return values


def _periodic_range(half: np.ndarray, lo: int, hi: int, length: int,
                    out: np.ndarray) -> None:
    """:func:`_periodic_values` at the consecutive bins ``lo..hi-1`` (mod
    ``length``) into ``out`` (..., hi - lo): runs of bins up to the middle
    copied as they are, runs above it from the mirrored bins in reverse order
    and conjugated (the same values)."""
    mid = length // 2
    pos, j = 0, lo
    while j < hi:
        jm = j % length
        if jm <= mid:
            size = min(hi - j, mid + 1 - jm)
            out[..., pos : pos + size] = half[..., jm : jm + size]
        else:  # conj(half[length - jm]), conj(half[length - jm - 1]), ...
            size = min(hi - j, length - jm)
            part = out[..., pos : pos + size]
            part[...] = half[..., length - jm - size + 1 : length - jm + 1][..., ::-1]
            np.conjugate(part, out=part)
        pos += size
        j += size


def _one_sided_mean_energy(half: np.ndarray, length: int) -> np.ndarray:
    """:func:`_mean_input_energy` from one-sided DFTs (P, n_u, length//2+1)."""
    P, n_u, h = half.shape
    mirrored_end = length - h + 1  # bins 1..mirrored_end-1 occur twice
    total = np.zeros(n_u)
    block = 2**18
    for start in range(0, h, block):
        part = half[:, :, start : start + block]
        energy = np.sum(part.real**2 + part.imag**2, axis=0)  # (n_u, b)
        j = np.arange(start, start + part.shape[2])
        twice = (j >= 1) & (j < mirrored_end)
        total += energy.sum(axis=1) + energy[:, twice].sum(axis=1)
    return total / length


def iter_local_fits(
    spectra: OneSidedSpectra,
    layout: LocalModelLayout,
    *,
    output: int = 0,
    chunk_size: int | None = None,
    backend: str = "auto",
    refine_steps: int = 1,
    return_cov: bool = False,
):
    """Closed-form local models of slow bins ``0..M//2``, chunk by chunk.

    The streaming form of :func:`fit_local_models` for real records: each
    chunk reads compact spectra (:meth:`OneSidedSpectra.window_spectra`), so
    nothing of the size of the grid is allocated, and the caller keeps only
    what it needs of each chunk. The results are those of
    ``fit_local_models(spectra.full_inputs(), spectra.full_outputs(output),
    layout, solver="normal", ...)`` at the same bins (each window's problem
    holds the same values; the compiled kernel solves every window alone, so
    chunking does not change it, and the numpy path uses the same chunks).
    :func:`iter_local_fit_rows` does several output rows at once.

    Parameters
    ----------
    spectra : OneSidedSpectra
    layout : LocalModelLayout
    output : int, default=0
        Output channel (one local problem per output row).
    chunk_size : int, optional
        Windows per chunk; default :func:`default_chunk_size` for the numpy
        path and :func:`stream_chunk_size` for the compiled kernel.
    backend : {"auto", "numpy", "numba"}, default="auto"
        Resolved once for all ``M//2+1`` windows, as in
        :func:`fit_local_models`.
    refine_steps : int, default=1
    return_cov : bool, default=False

    Yields
    ------
    start : int
        First slow bin of the chunk.
    fit : LocalModelFit
        The chunk's results, ``slow_bins = start .. start + B_chunk - 1``.
    """
    for start, fits in iter_local_fit_rows(
        spectra, layout, outputs=[output], chunk_size=chunk_size,
        backend=backend, refine_steps=refine_steps, return_cov=return_cov,
    ):
        yield start, fits[0]


def iter_local_fit_rows(
    spectra: OneSidedSpectra,
    layout: LocalModelLayout,
    *,
    outputs=None,
    chunk_size: int | None = None,
    backend: str = "auto",
    refine_steps: int = 1,
    return_cov: bool = False,
):
    """:func:`iter_local_fits` of several output rows, chunk by chunk.

    Each row is its own local problem (its own denominator), with the same
    results as :func:`iter_local_fits` of that row; the compiled kernel
    solves the rows of a window together and builds and factors the Gram
    block of the input and transient columns once for all of them.

    Parameters
    ----------
    spectra : OneSidedSpectra
    layout : LocalModelLayout
    outputs : sequence of int, optional
        Output channels; default all of them.
    chunk_size : int, optional
        Windows per chunk; default :func:`default_chunk_size` for the numpy
        path and :func:`stream_chunk_size` for the compiled kernel (divided
        among the rows).
    backend, refine_steps, return_cov
        As in :func:`iter_local_fits`.

    Yields
    ------
    start : int
        First slow bin of the chunk.
    fits : list of LocalModelFit
        The chunk's results of each row of ``outputs``.
    """
    for start, fits, _ in _iter_fit_rows(
        spectra, layout, outputs=outputs, chunk_size=chunk_size, backend=backend,
        refine_steps=refine_steps, return_cov=return_cov,
    ):
        yield start, fits


def _iter_fit_rows(
    spectra: OneSidedSpectra,
    layout: LocalModelLayout,
    *,
    outputs=None,
    chunk_size: int | None = None,
    backend: str = "auto",
    refine_steps: int = 1,
    return_cov: bool = False,
    eiv: bool = False,
    exponents: tuple | None = None,
):
    """:func:`iter_local_fit_rows`, also yielding each chunk's normalised
    spectra and, with ``eiv=True`` and the compiled kernel, the
    errors-in-variables terms computed with the solve.

    ``exponents``: ``(u_exponent, y_exponents)`` of the normalisation when
    the caller has them (:func:`power_of_two_exponent` of the inputs and of
    each output row of ``outputs``), else computed here.

    Yields
    ------
    start : int
    fits : list of LocalModelFit
        One per row of ``outputs``. With ``eiv=True`` their ``system_var`` and
        ``system_cov`` are None: the caller replaces Lemma 2's band terms by
        the errors-in-variables ones (:mod:`lrmfrf.uncertainty`).
    extra : tuple or None
        ``(U, Y, bins, raws, theta)`` with ``eiv=True``: the chunk's spectra
        (inputs scaled by ``2**-u_exponent``, each output row by its own
        exponent, as the solve saw them), its window bins, the ``eiv_raw``
        terms of :class:`lrmfrf.solvers.LocalSolution` of all rows with a
        leading row axis (None on the numpy path) and the normalised
        ``theta`` of all rows, (n_rows, B, n_params), the memory of the
        fits' ``theta`` where no exponent rescales them; None otherwise.
    """
    if outputs is None:
        outputs = range(spectra.outputs.shape[1])
    outputs = [int(o) for o in outputs]
    M = spectra.n_slow
    n_bins = M // 2 + 1
    backend = resolve_backend(backend, n_bins, layout.n_params)
    if chunk_size is None:
        if backend == "numba":
            chunk_size = stream_chunk_size(layout, len(outputs))
        else:
            chunk_size = default_chunk_size(layout, "normal")
    chunk_size = max(1, chunk_size)
    # the exponents normalise_spectra would take on the full DFTs (the same
    # largest |real| and |imag| parts), applied to each chunk's copy
    if exponents is None:
        u_exponent = power_of_two_exponent(spectra.inputs)
        y_exponents = [power_of_two_exponent(spectra.outputs[:, o])
                       for o in outputs]
    else:
        u_exponent, y_exponents = exponents
    mean_energy = _one_sided_mean_energy(spectra.inputs, spectra.n_samples)
    reference = _excitation_reference(
        scale_by_power_of_two(mean_energy, -2 * u_exponent), layout
    )
    options = _ChunkOptions("normal", backend, refine_steps, None, False, return_cov,
                            eiv)
    with _single_threaded_blas():  # left when the generator ends or is closed
        for start in range(0, n_bins, chunk_size):
            stop = min(n_bins, start + chunk_size)
            U, Y, bins = spectra.window_spectra(
                start, stop, layout.half_window, outputs
            )
            U = scale_by_power_of_two(U, -u_exponent)
            for i, exponent in enumerate(y_exponents):
                if exponent:
                    Y[:, i] = scale_by_power_of_two(Y[:, i], -exponent)
            fits = _fit_chunk_rows(U, Y, bins, layout, reference, options)
            extra = None
            if eiv:
                fits, (raws, theta_rows) = fits
                extra = (U, Y, bins, raws, theta_rows)
            del U, Y
            yield start, [
                rescale_local_fit(
                    replace(fit, slow_bins=np.arange(start, stop)), u_exponent,
                    exponent,
                )
                for fit, exponent in zip(fits, y_exponents, strict=True)
            ], extra
            del extra


def fit_one_sided(
    spectra: OneSidedSpectra,
    layout: LocalModelLayout,
    *,
    output: int = 0,
    return_cov: bool = False,
    **kwargs,
) -> LocalModelFit:
    """All chunks of :func:`iter_local_fits` as one :class:`LocalModelFit`.

    Equal to ``fit_local_models(spectra.full_inputs(),
    spectra.full_outputs(output), layout, return_cov=return_cov)`` without
    forming the full DFTs. ``kwargs`` go to :func:`iter_local_fits`.
    """
    parts = [
        fit for _, fit in iter_local_fits(
            spectra, layout, output=output, return_cov=return_cov, **kwargs
        )
    ]
    return _joined_fits(parts, half_slow_bins(spectra.n_slow))


def stream_chunk_size(layout: LocalModelLayout, n_rows: int = 1) -> int:
    """Windows per chunk of :func:`iter_local_fits` with the compiled kernel.

    Bounds a chunk's arrays (compact spectra, parameters, Lemma 2 blocks,
    window energies and the caller's per-chunk copies) of ``n_rows`` output
    rows to about ``CHUNK_BYTES / 2``: the kernel solves each window alone,
    so the chunk only sets how much is held at once. A multiple of the
    kernel's lanes times its threads (:func:`lrmfrf._compiled.chunk_quantum`),
    so that only the last chunk has a partly filled lane group and every
    thread gets as many groups of a chunk.

    When the budget holds fewer windows than that quantum (large MIMO layouts,
    many threads), the chunk is one quantum as long as that is at most
    :data:`MAX_STREAM_FLOOR` windows, so that no thread idles (one lane group
    per chunk left one of two threads idle and doubled a 4x4, P = 4, F = 5
    fit's time), and otherwise the budget's or that floor's windows in whole
    lane groups: the chunk does not grow with the thread count beyond it.
    """
    p, nb, P = layout.n_params, layout.n_bands, layout.n_experiments
    n_centre = nb + P
    per_window = 8 * (
        4 * p  # theta (complex) and the Lemma 2 diagonal, twice
        + 2 * n_centre**2 + 6 * nb * nb  # centre block, lead and system_cov
        + 8 * nb + 4 * P  # band values, variances, transients
        + 3 * layout.window * nb  # window energies (values and indices)
    )
    budget = CHUNK_BYTES // 2 // (per_window * max(1, n_rows))
    quantum = chunk_quantum()
    if budget >= quantum:
        return budget - budget % quantum
    size = max(budget, min(quantum, MAX_STREAM_FLOOR))
    return max(LANES, size - size % LANES)


#: Largest chunk (windows) :func:`stream_chunk_size` takes beyond the memory
#: budget, to give every kernel thread a lane group.
MAX_STREAM_FLOOR = 1024


def fast_grid_targets(start: int, stop: int, n_samples: int, F: int):
    """Fast bins ``0..N//2`` that :func:`one_sided_fast_grid` fills from the
    slow bins ``start..stop-1``.

    Fast bin ``j`` takes ``values[k, f]`` (``j = k + fM``) or, mirrored,
    ``conj(values[k, f])`` with ``N - j = k + fM``; each ``j`` has exactly
    one source.

    Returns
    -------
    fast : ndarray of shape (T,), int
        The fast bins ``j``.
    slow : ndarray of shape (T,), int
        Their source slow bin relative to ``start`` (``k - start``).
    band : ndarray of shape (T,), int
        The source band ``f``.
    mirrored : ndarray of shape (T,), bool
        Whether the value is conjugated.
    """
    M = n_samples // F
    half = n_samples // 2
    k = np.arange(start, stop)
    f = np.arange(F)[:, None]
    direct = k + f * M  # values[k, f] at j = k + fM
    mirror = n_samples - direct  # mirrored: j % M = M - k > M//2
    mirror_ok = (k > 0) & (M - k > M // 2) & (mirror <= half)
    direct_ok = direct <= half
    kk = np.broadcast_to(k - start, direct.shape)
    ff = np.broadcast_to(f, direct.shape)
    fast = np.concatenate([direct[direct_ok], mirror[mirror_ok]])
    slow = np.concatenate([kk[direct_ok], kk[mirror_ok]])
    band = np.concatenate([ff[direct_ok], ff[mirror_ok]])
    mirrored = np.zeros(fast.size, dtype=bool)
    mirrored[np.count_nonzero(direct_ok):] = True
    return fast, slow, band, mirrored


def _fast_grid_runs(start: int, stop: int, n_samples: int, F: int):
    """:func:`fast_grid_targets` as runs of consecutive bins: the same fast
    bins, sources and conjugation, for writing with slices.

    For each band ``f`` the direct bins ``j = k + fM`` of the slow bins
    ``k`` of ``start..stop-1`` that it keeps are one run of consecutive
    ``k`` and ``j``, and so are the mirrored bins ``j = N - k - fM``, in the
    opposite order.

    Returns
    -------
    list of tuple
        ``(f, k0, k1, j0, mirrored)``: slow bins ``start + k0 .. start + k1 -
        1`` of band ``f`` fill fast bins ``j0 .. j0 + k1 - k0 - 1``, in the
        same order (``mirrored`` False) or reversed and conjugated (True,
        ``j0 = N - (start + k1 - 1) - fM``).
    """
    M = n_samples // F
    half = n_samples // 2
    runs = []
    for f in range(F):
        k1 = min(stop, half - f * M + 1)  # direct: k + fM <= N//2
        if k1 > start:
            runs.append((f, 0, k1 - start, start + f * M, False))
    for f in range(F):
        # mirrored: k > 0, M - k > M//2 and N - k - fM <= N//2
        k0 = max(start, 1, n_samples - half - f * M)
        k1 = min(stop, M - M // 2)
        if k1 > k0:
            runs.append((f, k0 - start, k1 - start, n_samples - (k1 - 1) - f * M,
                         True))
    return runs


def default_chunk_size(layout: LocalModelLayout, solver: str = "qr") -> int:
    """Windows per chunk that keep a chunk's largest arrays near 64 MiB."""
    if solver != "normal":
        return qr_chunk_size(layout)
    p, L = layout.n_params, layout.window
    per_window = 16 * (
        3 * p * p + 6 * L * (layout.n_bands + 2) * layout.n_experiments
    )
    return max(1, CHUNK_BYTES // per_window)


def _check_solver(solver: str, return_leverage: bool) -> str:
    if solver not in SOLVERS:
        raise ValueError(
            f"`solver` must be one of {SOLVERS}. Got {solver!r} instead. Use "
            "'auto' unless you are comparing solvers."
        )
    if solver == "normal" and return_leverage:
        raise ValueError(
            "return_leverage=True needs the QR solver; got solver='normal'. Use "
            "solver='auto' or 'qr'."
        )
    if solver == "auto":
        return "qr" if return_leverage else "normal"
    return solver


def one_sided_fast_grid(values: np.ndarray, n_samples: int, F: int, *, conj: bool):
    """Map per-slow-bin band values (slow bins ``0..M//2``) to fast bins 0..N//2.

    Fast bin ``j = k + fM`` with ``k <= M//2`` is ``values[k, f]``; otherwise it
    is the mirror ``N - j = (M-k) + (F-1-f) M`` of a solved bin, and
    ``G(j) = conj(G(N-j))`` (``conj=True``, for the FRF) or the same value
    (``conj=False``, for variances).

    Parameters
    ----------
    values : ndarray of shape (M//2+1, F)
    n_samples : int
        ``N``.
    F : int
    conj : bool

    Returns
    -------
    ndarray of shape (N//2+1,)
    """
    M = n_samples // F
    j = np.arange(n_samples // 2 + 1)
    k, f = j % M, j // M
    mirrored = k > M // 2
    k_src = np.where(mirrored, M - k, k)
    f_src = np.where(mirrored, F - 1 - f, f)
    out = values[k_src, f_src]
    if conj:
        out = np.where(mirrored, np.conj(out), out)
    return out
