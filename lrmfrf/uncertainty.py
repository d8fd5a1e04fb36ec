"""Covariance of the local-model FRF estimates: Lemma 2 and calibrated routes.

The closed form eq. (linearSolution) solves, per window, ``b = A theta + eps``
where the rows of ``A`` (eq. Kvector) hold ``x^s U(k+r+fM)``, ``x^s`` and
``-x^s Y_l(k+r)``. With the true parameters the equation error of row ``r`` is
exactly ``eps_r = e(x_r) V_l(k+r)``: the output noise times the local
denominator ``e(x) = 1 + sum_s e_s x^s`` (``e(0) = 1``). The window-centre band
values are ``G(k+fM) = F theta_f`` and, to first order in the noise,

    G_hat(k+fM) - G(k+fM) = F s_f^H eps,    s_f = A (A^H A)^-1 i_f,

(the proof of Lemma 2 of the paper). The routes below differ in what they
assume about ``eps``:

``"lemma2"``
    The paper's eq. (Variance): ``eps`` white with the variance of the
    residual over ``q`` degrees of freedom, ``F^2 (A^H A)^-1 ||r||^2 / q``.
``"eiv"``
    Errors in variables: ``eps_r = e(x_r) V_r`` is heteroscedastic with
    variance ``|e(x_r)|^2 sigma^2``; the sandwich
    ``F^2 sigma^2 S^H diag(|e(x_r)|^2) S`` with the estimated denominator, and
    ``sigma^2`` from the residual over its expected size,
    ``||r||^2 / sum_r |e(x_r)|^2 (1 - h_r)`` (``h_r`` the leverages), which is
    unbiased for that noise model to first order. It equals ``"lemma2"`` when
    ``den_degree == 0`` (``e == 1``, ``sum_r (1 - h_r) = q``).
``"hc"``
    Heteroscedasticity-consistent (HC2) sandwich with the residuals
    themselves, ``F^2 S^H diag(|r_r|^2 / (1 - h_r)) S``.
``"eiv_dof"``
    ``"eiv"`` with the degrees of freedom that the noisy denominator
    columns absorb removed from the residual's expected size:
    ``||r||^2 = sigma^2 (sum_r |e|^2 (1 - h_r) - sigma^2 a)``, ``a =
    tr([(A^H A)^-1]_den D)`` with ``D`` the noise Gram of the denominator
    columns (``R_e`` dof on pure noise, none without noise).
``"eiv_pooled"``
    ``"eiv"`` with ``sigma^2`` pooled over the ``2n+1`` neighbouring windows
    (the noise spectrum is smooth over a window, so its estimate may borrow
    the residuals of the neighbours): more degrees of freedom, the same
    expectation.
``"eiv_robust"``
    Bias-aware (``benchmarks/coverage_bias_study.py``, route
    ``switch2+nbr_c4``): the ``"eiv"`` sandwich with ``sigma^2`` the median
    of the ``2n+1`` neighbouring windows' own levels ``||r||^2 / sum_r
    |e(x_r)|^2 (1 - h_r)`` divided by the median of ``chi^2_2q / 2q``,
    except where the window's own level exceeds twice that median (model
    misfit: the window keeps its own level); plus, on the variance, the mean
    squared disagreement ``d`` between the window's band value and the local
    models of the windows centred at ``k - 1`` and ``k + 1`` evaluated at
    ``k``, wherever ``d`` over the ``"eiv"`` variance exceeds 4 times its
    median over the record (:func:`robust_band_covariance`). Measured in the
    study (``python benchmarks/coverage_bias_study.py --F 2 3 5 --snr 30 45
    70``: 10 random stages and ``wafer_stage()``, ``M = 400``, 30 runs):
    2-std coverage 96.3-97.0 % and median ratio to the Monte-Carlo std
    1.00-1.04 in 7 of 9 cells (F = 2, 3, 5 at 30, 45, 70 dB); F = 2 at 30 dB
    covers 95.8 %, F = 5 at 70 dB covers 97.1 % at ratio 1.068 (``"eiv"``:
    93.9-95.2 %). Whole record only (not streamed; the eiv terms compiled,
    the neighbour term in numpy).

References
----------
M. van Haren, L. Blanken, K. Classens, T. Oomen, "Local Rational Modeling for
Identification Beyond the Nyquist Frequency: Applied to a Prototype Wafer
Stage", 2024 (Lemma 2, eq. Variance). R. Pintelon and J. Schoukens, System
Identification: A Frequency Domain Approach, 2nd ed., Wiley, 2012 (Appendix
7.B, the residual noise estimate). J. G. MacKinnon and H. White, "Some
heteroskedasticity-consistent covariance matrix estimators with improved
finite sample properties", J. Econometrics 29 (1985) (HC2).
"""

from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass, replace

import numpy as np

from . import _compiled_uncertainty
from .local_models import (
    _iter_fit_rows,
    _single_threaded_blas,
    iter_local_fit_rows,
    iter_local_fits,
    power_of_two_exponent,
    scale_by_power_of_two,
)
from .solvers import (
    CHOLESKY_FALLBACK_TOL,
    RANK_TOL,
    _kernel_tables,
    _kernel_weighted_tables,
    qr_chunk_size,
    resolve_backend,
)
from .windows import LocalModelLayout, band_indices, local_regressor, window_offsets

__all__ = [
    "STD_METHODS",
    "DEFAULT_STD_METHOD",
    "calibrated_local_fit",
    "calibrated_refined_fit",
    "iter_calibrated_fits",
    "eiv_terms",
    "eiv_terms_rows",
    "cross_row_covariance",
    "check_std_method",
    "VarianceTerms",
    "variance_terms",
    "band_covariance",
    "pooled_noise_variance",
    "robust_noise_variance",
    "neighbour_disagreement",
    "neighbour_bias_term",
    "robust_band_covariance",
    "ExperimentNoiseLevels",
    "experiment_noise_levels",
    "unequal_noise_rows",
    "experiment_noise_weights",
]

#: Routes of :func:`band_covariance`.
STD_METHODS = ("lemma2", "eiv", "hc", "eiv_pooled", "eiv_dof", "eiv_robust")

#: ``"eiv_robust"``: a window keeps its own noise level where it exceeds this
#: multiple of its neighbours' median level (``switch2`` of the study).
ROBUST_SWITCH = 2.0

#: ``"eiv_robust"``: the neighbour disagreement is added where its ratio to the
#: ``"eiv"`` variance exceeds this multiple of its median (``nbr_c4``).
ROBUST_NBR_THRESHOLD = 4.0

#: The route of ``frf_std_`` by default (``benchmarks/generalisation_std.py``):
#: the errors-in-variables sandwich, compiled and streamed (:func:`eiv_terms`,
#: :func:`iter_calibrated_fits`).
DEFAULT_STD_METHOD = "eiv"


@dataclass
class VarianceTerms:
    """Per-window ingredients of every covariance route.

    All arrays are NaN at windows that are not well posed.

    Attributes
    ----------
    gram_lead : ndarray of shape (B, n_bands, n_bands), complex
        ``S^H S = [(A^H A)^-1]`` at the window-centre band columns.
    eiv_lead : ndarray of shape (B, n_bands, n_bands), complex
        ``S^H diag(|e(x_r)|^2) S``.
    hc_lead : ndarray of shape (B, n_bands, n_bands), complex
        ``S^H diag(|r_r|^2 / (1 - h_r)) S``.
    rss : ndarray of shape (B,)
        ``||r||^2`` of the closed form.
    absorbed : ndarray of shape (B,)
        ``tr([(A^H A)^-1]_den D)``, ``D_st = sum_r x_r^(s+t) |e(x_r)|^2``:
        times ``sigma^2``, the residual degrees of freedom the noisy
        denominator columns absorb (``R_e`` on pure noise).
    eiv_trace : ndarray of shape (B,)
        ``sum_r |e(x_r)|^2 (1 - h_r)``: ``E ||r||^2 / sigma^2`` under the
        errors-in-variables noise model, to first order.
    dof : int
        ``q``.
    """

    gram_lead: np.ndarray
    eiv_lead: np.ndarray
    hc_lead: np.ndarray
    rss: np.ndarray
    eiv_trace: np.ndarray
    absorbed: np.ndarray
    dof: int


def variance_terms(
    U: np.ndarray,
    Y: np.ndarray,
    layout: LocalModelLayout,
    theta: np.ndarray,
    slow_bins: np.ndarray,
    *,
    chunk_size: int | None = None,
    with_hc: bool = True,
) -> VarianceTerms:
    """Compute the :class:`VarianceTerms` of the closed-form local models.

    Parameters
    ----------
    U : ndarray of shape (P, n_u N), complex
        DFT of the fast inputs (as for
        :func:`lrmfrf.local_models.fit_local_models`).
    Y : ndarray of shape (P, M), complex
        DFT of one slow output channel.
    layout : LocalModelLayout
    theta : ndarray of shape (B, n_params), complex
        Closed-form parameters (``LocalModelFit.theta``, monomial, layout
        order); NaN rows give NaN terms.
    slow_bins : ndarray of shape (B,), int
        Window centres of ``theta``.
    chunk_size : int, optional
        Windows per batch (bounds the memory of the regressors).
    with_hc : bool, default True
        Compute ``hc_lead`` and ``absorbed`` (the routes "hc" and "eiv_dof";
        NaN otherwise).

    Returns
    -------
    VarianceTerms
    """
    slow_bins = np.asarray(slow_bins, dtype=int)
    chunk = qr_chunk_size(layout) if chunk_size is None else max(1, chunk_size)
    # many small matrix products: threaded BLAS only costs on a busy machine
    with _single_threaded_blas():
        parts = [
            _terms_of_chunk(U, Y, layout, theta[s : s + chunk],
                            slow_bins[s : s + chunk], with_hc)
            for s in range(0, slow_bins.size, chunk)
        ]
    joined = [np.concatenate(arrays) for arrays in zip(*parts, strict=True)]
    return VarianceTerms(*joined, dof=layout.dof)


def _terms_of_chunk(U, Y, layout, theta, slow_bins, with_hc):
    good, theta0, residual, A_eq, norms, gram_inv, AG, S = _window_fit(
        U, Y, layout, theta, slow_bins)
    leverage = np.sum((AG * A_eq.conj()).real, axis=2)
    e_weight = np.abs(_denominator_on_window(theta0, layout)) ** 2
    P = layout.n_experiments
    e_weight = np.tile(e_weight, (1, P))  # rows are experiment-major
    rss = np.sum(np.abs(residual) ** 2, axis=1)
    S_h = np.ascontiguousarray(np.conj(np.swapaxes(S, 1, 2)))
    gram_lead = S_h @ S
    eiv_lead = (S_h * e_weight[:, None, :]) @ S
    if with_hc:
        hc_weight = np.abs(residual) ** 2 / np.maximum(1.0 - leverage, 1e-12)
        hc_lead = (S_h * hc_weight[:, None, :]) @ S
    else:
        hc_lead = np.full_like(gram_lead, np.nan)
    eiv_trace = np.sum(e_weight * (1.0 - leverage), axis=1)
    # 0 <= 1 - h_r <= 1 and sum_r (1 - h_r) = q bound the trace by q min w and
    # q max w; round-off in 1 - h times a large |e|^2 can leave those bounds
    # (even the sign) on noise-free, nearly interpolated windows
    q = max(layout.dof, 0)
    eiv_trace = np.clip(eiv_trace, q * e_weight.min(axis=1), q * e_weight.max(axis=1))
    absorbed = np.full(rss.shape, np.nan)
    if with_hc:  # the study's extras: also the absorbed dof of "eiv_dof"
        den = layout.den_columns
        _, x = window_offsets(layout.half_window)
        powers = np.tile(x[:, None] ** np.arange(1, layout.den_degree + 1), (P, 1))
        noise_gram = np.einsum("ls,bl,lt->bst", powers, e_weight, powers)
        den_inv = gram_inv[:, den, den] / (norms[:, den, None] * norms[:, None, den])
        absorbed = np.real(np.einsum("bst,bts->b", den_inv, noise_gram))
    out = [gram_lead, eiv_lead, hc_lead, rss, eiv_trace, absorbed]
    for arr in out:
        arr[~good] = np.nan
    return out


def cross_row_covariance(
    U: np.ndarray,
    Ys,
    layout: LocalModelLayout,
    thetas,
    slow_bins: np.ndarray,
    *,
    method: str = "eiv",
    chunk_size: int | None = None,
    weights=None,
) -> np.ndarray:
    r"""Covariance of the window-centre band values between output rows.

    Each output row ``o`` has its own local problem ``b_o = A_o theta_o +
    eps_o`` (its own denominator ``e_o``) on the same windows, with
    ``eps_o = e_o(x_r) V_o(k+r)``. Noise that is correlated between the
    outputs (e.g. fed back through a controller), ``E[V_o conj(V_p)] =
    c_op`` over a window, makes the rows' band values correlated:

    .. math:: E[dG_{o,b} \overline{dG_{p,c}}] = F^2 c_{op}
              [S_o^H D_{op} S_p]_{bc},\quad
              D_{op} = \mathrm{diag}(e_o(x_r) \overline{e_p(x_r)}),

    with ``S_o = A_o (A_o^H A_o)^-1`` at the band columns, and ``c_op`` from
    the residuals of the two rows, whose expected product is ``E[r_p^H r_o]
    = c_op tr((I - H_o) D_op (I - H_p))`` (``H`` the hat matrices):

    .. math:: c_{op} = r_p^H r_o / \mathrm{tr}((I - H_o) D_{op} (I - H_p)).

    For ``o == p`` this is route ``"eiv"`` (``tr((I - H) D) = sum_r |e_r|^2
    (1 - h_r)``); ``method="lemma2"`` takes ``D = I`` (``c_oo = ||r||^2 /
    q``, Lemma 2). Without a denominator both are the same.

    Parameters
    ----------
    U : ndarray of shape (P, n_u N), complex
        The input spectra of the fit (as :func:`variance_terms`).
    Ys : sequence of ndarray of shape (P, M), complex
        The output spectra of each row; or ``(U_o, Y_o)`` pairs (``U`` then
        None): each row's regressors from its own spectra. Rows fitted on
        weighted experiments (:func:`experiment_noise_weights`) are best
        given by ``weights`` with the records' spectra and ``local_fit_``'s
        parameters; as pairs of weighted copies ``(U w, Y w)`` their
        ``thetas`` must hold the weighted fit's transient (``local_fit_``'s
        scaled by ``w``), else the residuals carry the mismatch.
    layout : LocalModelLayout
    thetas : sequence of ndarray of shape (B, n_params), complex
        The closed-form parameters of each row (NaN rows: NaN).
    slow_bins : ndarray of shape (B,), int
    method : {"eiv", "lemma2"}, default "eiv"
    chunk_size : int, optional
        Windows per batch.
    weights : sequence of (ndarray of shape (P,) or None), optional
        Per row (a list, not a 2-D array: from the ``(P, n_y)`` array of
        :func:`experiment_noise_weights` pass ``[w[:, o] for o in
        range(n_y)]``), the experiments' weights of a row fitted on weighted
        experiments (finite, positive): its equations of
        experiment ``p`` are multiplied by ``weights[o][p]`` window by
        window (no weighted copy of the spectra), and ``thetas[o]`` holds
        the parameters with the transient unweighted (the records' units,
        as ``local_fit_``). The same local problem as the pair
        ``(U * w, Y * w)`` with the transient weighted (a rescaling of the
        transient columns: the same hat matrix and band columns of ``S``).

    Returns
    -------
    ndarray of shape (B, n_y, n_bands, n_y, n_bands), complex
        ``J[k, o, b, p, c] = E[dG_o,b conj(dG_p,c)]``; Hermitian in ``(o, b),
        (p, c)``. NaN at windows where a row's parameters are not finite.
    """
    if method not in ("eiv", "lemma2"):
        raise ValueError(f"`method` must be 'eiv' or 'lemma2'; got {method!r}.")
    if U is None and not all(isinstance(Y, (tuple, list)) and len(Y) == 2
                             for Y in Ys):
        raise ValueError(
            "With `U` None every entry of `Ys` must be a (U_o, Y_o) pair, the "
            "row's own input and output spectra; got "
            f"{[np.shape(Y) for Y in Ys]}. Pass the input spectra as `U` with "
            "plain output spectra, or pairs."
        )
    pairs = [(U, Y) if U is not None else tuple(Y) for Y in Ys]
    n_y, nb = len(pairs), layout.n_bands
    weights = _row_weights(weights, n_y, layout.n_experiments)
    slow_bins = np.asarray(slow_bins, dtype=int)
    # every row's regressor, hat matrix and solution operator of a chunk are
    # held at once: the QR solver's chunk over 2 n_y keeps them near a few
    # CHUNK_BYTES (3x2, P = 2, N = 1.2e5: peak 1152 -> 473 MiB, faster too)
    chunk = (max(1, qr_chunk_size(layout) // (2 * n_y)) if chunk_size is None
             else max(1, chunk_size))
    out = np.full((slow_bins.size, n_y, nb, n_y, nb), np.nan, dtype=complex)
    with _single_threaded_blas():
        for start in range(0, slow_bins.size, chunk):
            bins = slow_bins[start:start + chunk]
            rows = [_row_projection(Uo, Yo, layout, theta[start:start + chunk],
                                    bins, method, w)
                    for (Uo, Yo), theta, w in zip(pairs, thetas, weights,
                                                  strict=True)]
            good = np.logical_and.reduce([row[0] for row in rows])
            for o in range(n_y):
                _, S_o, H_o, r_o, e_o = rows[o]
                for p in range(o, n_y):
                    _, S_p, H_p, r_p, e_p = rows[p]
                    D = e_o * e_p.conj()  # (B, L)
                    # tr((I - H_o) D (I - H_p))
                    trace = (D.sum(axis=1)
                             - np.einsum("brr,br->b", H_o, D)
                             - np.einsum("br,brr->b", D, H_p)
                             + np.einsum("bsr,br,brs->b", H_o, D, H_p))
                    with np.errstate(invalid="ignore", divide="ignore"):
                        level = np.sum(r_p.conj() * r_o, axis=1) / trace
                    S_oh = np.conj(np.swapaxes(S_o, 1, 2))
                    block = layout.F**2 * level[:, None, None] * (
                        (S_oh * D[:, None, :]) @ S_p)
                    block[~good] = np.nan
                    out[start:start + chunk, o, :, p, :] = block
                    if p != o:
                        out[start:start + chunk, p, :, o, :] = np.conj(
                            np.swapaxes(block, 1, 2))
    _shrink_to_semidefinite(out.reshape(slow_bins.size, n_y * nb, n_y * nb), nb)
    return out


def _row_weights(weights, n_y: int, P: int) -> list:
    """:func:`cross_row_covariance`'s ``weights`` checked: one entry per
    output row, None or the row's ``P`` experiment weights (finite, > 0).

    A 2-D array is refused: :func:`experiment_noise_weights` gives ``(P,
    n_y)`` and a list of rows would read ``(n_y, P)``; with ``P == n_y`` one
    would be taken for the other without an error."""
    if weights is None:
        return [None] * n_y
    if isinstance(weights, np.ndarray) and weights.ndim != 1:
        raise ValueError(
            f"`weights` must be a sequence with one entry per output row (None "
            f"or the row's {P} experiment weights), not an array of shape "
            f"{weights.shape}; for experiment_noise_weights' (P, n_y) array "
            "pass [w[:, o] for o in range(n_y)]."
        )
    if len(weights) != n_y:
        raise ValueError(f"`weights` must give one entry per output row ({n_y}); "
                         f"got {len(weights)}.")
    checked = []
    for o, w in enumerate(weights):
        if w is not None:
            try:  # (ragged or non-numeric entries: the message below)
                given = np.asarray(w)
            except ValueError:
                given = np.asarray(w, dtype=object)
            # real numbers only: a complex weight cast to float would lose its
            # imaginary part with no more than a ComplexWarning
            real = given.dtype.kind in "iuf"
            w = given.astype(float) if real else given
            if given.dtype.kind == "O":  # e.g. Fraction or Decimal entries
                try:
                    w, real = given.astype(float), True
                except (TypeError, ValueError):  # complex, ragged
                    pass
            if (not real or w.shape != (P,)
                    or not np.all(np.isfinite(w) & (w > 0))):
                raise ValueError(
                    f"`weights[{o}]` must be None or {P} finite positive "
                    f"(real) experiment weights, shape ({P},); got {given!r}."
                )
        checked.append(w)
    return checked


def _shrink_to_semidefinite(joint: np.ndarray, block: int) -> None:
    """Scale the off-diagonal blocks of the windows' joint covariances (B, n,
    n), in place, by the largest ``lambda <= 1`` that keeps them positive
    semidefinite (:func:`cross_row_covariance`: each level ``c_op`` is
    unbiased, but the estimated correlation of a window can exceed 1 in
    magnitude where the rows' residuals are nearly proportional)."""
    finite = np.isfinite(joint).all(axis=(1, 2))
    if not finite.any():
        return
    with np.errstate(invalid="ignore"):
        eig = np.linalg.eigvalsh(joint[finite])
    bad = np.flatnonzero(finite)[eig[:, 0] < -1e-12 * np.abs(eig).max(axis=1)]
    n = joint.shape[1]
    own = np.kron(np.eye(n // block, dtype=bool), np.ones((block, block), bool))
    for k in bad:
        diagonal = np.where(own, joint[k], 0.0)
        off = joint[k] - diagonal
        try:  # O v = mu D v: D + lambda O >= 0 for lambda <= -1 / min mu
            root = np.linalg.cholesky(diagonal)
        except np.linalg.LinAlgError:
            continue
        inverse = np.linalg.inv(root)
        mu = np.linalg.eigvalsh(inverse @ off @ inverse.conj().T)[0]
        if mu < -1.0:
            joint[k] = diagonal + off * (-1.0 / mu)


def _row_projection(U, Y, layout, theta, slow_bins, method, weights=None):
    """What :func:`cross_row_covariance` needs of one row's windows: where
    they are finite, ``S = A (A^H A)^-1`` at the band columns, the hat matrix,
    the residual and the equation weights ``e(x_r)`` (ones for Lemma 2);
    ``weights`` (P,): each experiment's equations multiplied by its weight."""
    good, theta0, residual, A_eq, _, _, AG, S = _window_fit(
        U, Y, layout, theta, slow_bins, weights)
    hat = AG @ np.conj(np.swapaxes(A_eq, 1, 2))
    if method == "lemma2":
        e = np.ones(residual.shape, dtype=complex)
    else:  # rows are experiment-major
        e = np.tile(_denominator_on_window(theta0, layout),
                    (1, layout.n_experiments))
    return good, S, hat, residual, e


def _window_fit(U, Y, layout, theta, slow_bins, weights=None):
    """The windows' regressors at the fitted ``theta``: ``good`` (finite
    parameters), ``theta0`` (zero where not), the residual ``b - A theta0``,
    :func:`_window_solution`'s ``A_eq, norms, gram_inv, AG`` and ``S = A (A^H
    A)^-1`` at the band columns (shared by the std terms and the cross-row
    covariance). ``weights`` (P,): experiment ``p``'s equations (rows of
    ``A`` and ``b``, experiment-major) multiplied by ``weights[p]``."""
    nb = layout.n_bands
    A, b = local_regressor(U, Y, slow_bins, layout)
    if weights is not None:
        rows = np.repeat(np.asarray(weights, dtype=float), A.shape[1] // U.shape[0])
        A = A * rows[:, None]
        b = b * rows
    good = np.all(np.isfinite(theta), axis=1)
    theta0 = np.where(good[:, None], theta, 0.0)
    residual = b - np.einsum("blp,bp->bl", A, theta0)
    A_eq, norms, gram_inv, AG = _window_solution(A, good)
    S = np.ascontiguousarray(AG[:, :, :nb] / norms[:, None, :nb])
    return good, theta0, residual, A_eq, norms, gram_inv, AG, S


def _window_solution(A: np.ndarray, good: np.ndarray):
    """The least-squares solution operator of each window's ``A``.

    Returns ``A_eq`` (the columns scaled to unit norm), ``norms`` (B, p),
    ``gram_inv = (A_eq^H A_eq)^+`` and ``AG = A_eq gram_inv``: ``S = A (A^H
    A)^+ = AG / norms`` (columnwise) and the hat matrix ``H = AG A_eq^H``.
    Windows not ``good`` get an identity Gram. From the Householder QR of
    ``A_eq`` (:func:`_solution_operator`), as the QR solver's own terms
    (:func:`_dense_eiv_terms`), with round-off ``eps cond(A)``: the inverse
    of the Gram matrix it replaced lost ``eps cond(A)^2`` (the std of a noisy
    N = 1.2e4 record moved by up to 1e-8 relative, median 2e-12; on
    noise-free windows, where the truncated SVD takes over, it had given
    leverages of -174..222).
    """
    norms = np.linalg.norm(A, axis=1)
    zero_column = ~(norms > np.finfo(float).tiny)
    norms = np.where(zero_column, 1.0, norms)
    A_eq = A / norms[:, None, :]
    Q, R = np.linalg.qr(A_eq)
    p = A.shape[2]
    R = np.where(good[:, None, None], R, np.eye(p))
    idx = np.arange(p)
    # an exactly-zero column: a unit pivot (the window is not certified below)
    R[:, idx, idx] = np.where(R[:, idx, idx] == 0, 1.0, R[:, idx, idx])
    R_inv = np.linalg.inv(R)
    gram_inv, AG = _solution_operator(A_eq, zero_column, good, Q, R_inv)
    return A_eq, norms, gram_inv, AG


def _solution_operator(A_eq, zero_column, good, Q, R_inv, svd_windows=None,
                       svd=None, *, gram=True):
    """``(A_eq^H A_eq)^+`` and ``A_eq (A_eq^H A_eq)^+`` of each window from
    the QR factors ``A_eq = Q R`` (``R_inv`` the inverse of ``R``).

    Windows whose ``R`` certifies that the truncated SVD drops no singular
    value, ``||R^-1||_F^2 RANK_TOL^2 p < 1/4`` (then ``s_min >= 1 /
    ||R^-1||_F > 2 RANK_TOL sqrt(p) >= 2 RANK_TOL s_max``, the columns having
    unit norm, none zero): ``R^-1 R^-H`` and ``Q R^-H``. The other ``good``
    windows: the truncated SVD's ``V diag(1/s^2) V^H`` and ``U diag(1/s) V^H``
    (singular values above ``RANK_TOL`` times the largest), with
    ``svd = (U, s, Vh)`` given for the windows ``svd_windows`` (bool mask; the
    QR solver's, whose ``R_inv`` there is not used). ``gram=False``: the
    first is None (not computed)."""
    p = A_eq.shape[2]
    size = np.sum(R_inv.real**2 + R_inv.imag**2, axis=(1, 2))
    with np.errstate(invalid="ignore"):
        certified = ~zero_column.any(axis=1) & (size * (RANK_TOL**2 * p) < 0.25)
    given = np.zeros(good.shape, dtype=bool) if svd_windows is None else svd_windows
    other = good & ~certified & ~given
    by_qr = ~(given | other)
    if by_qr.all():  # (usually, on noisy data: no copies)
        R_inv_h = np.ascontiguousarray(np.conj(np.swapaxes(R_inv, 1, 2)))
        return (R_inv @ R_inv_h if gram else None), Q @ R_inv_h
    gram_inv = np.empty_like(R_inv) if gram else None
    AG = np.empty_like(Q)
    if by_qr.any():
        R_inv_h = np.ascontiguousarray(np.conj(np.swapaxes(R_inv[by_qr], 1, 2)))
        AG[by_qr] = Q[by_qr] @ R_inv_h
        if gram:
            gram_inv[by_qr] = R_inv[by_qr] @ R_inv_h
    for windows, factors in ((given, svd), (other, None)):
        if not windows.any():
            continue
        if factors is None:
            U, inv_s, Vh = _truncated_svd(A_eq[windows])
        else:
            U, s, Vh = factors
            keep = s > RANK_TOL * s[:, :1]
            inv_s = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
        if gram:
            gram_inv[windows] = _pseudo_inverse_gram(inv_s, Vh)
        AG[windows] = (U * inv_s[:, None, :]) @ Vh
    return gram_inv, AG


def _truncated_svd(A_eq: np.ndarray):
    """``(U, inv_s, Vh)``: the thin SVD ``A_eq = U diag(s) Vh`` with ``inv_s``
    ``1 / s`` at the singular values above ``RANK_TOL`` times the largest and 0
    at the others (as :func:`lrmfrf.solvers.solve_local_least_squares`)."""
    U, s, Vh = np.linalg.svd(A_eq, full_matrices=False)
    keep = s > RANK_TOL * s[:, :1]
    return U, np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0), Vh


def _pseudo_inverse_gram(inv_s: np.ndarray, Vh: np.ndarray) -> np.ndarray:
    """``(A^H A)^+ = V diag(inv_s^2) V^H`` from :func:`_truncated_svd` of
    ``A``."""
    # as a stacked matmul: the three-operand einsum does not use BLAS and was
    # ~5x slower
    V_scaled = np.ascontiguousarray(
        np.conj(np.swapaxes(Vh, 1, 2)) * inv_s[:, None, :] ** 2)
    return V_scaled @ Vh


def _dense_eiv_terms(theta, A_eq, norms, zero_column, well_posed, deficient, Q,
                     R_inv, svd, layout):
    """The dense route's errors-in-variables terms (:func:`_terms_of_chunk`'s
    ``eiv_lead`` and ``eiv_trace``) of windows solved by the QR solver, from
    its factors (:func:`lrmfrf.solvers._solve_dense`): the same solution
    operator (:func:`_solution_operator`: ``Q R^-H`` where ``R`` certifies
    full rank, else the truncated SVD, the solver's own for the windows it
    solved by it) without building and factoring the windows again.

    Returns
    -------
    tuple
        ``(lead, trace, done)``: ``S^H diag(w) S``, ``sum_r w_r (1 - h_r)``
        (within ``q min w .. q max w``) and ``done``, the well-posed windows
        (NaN elsewhere).
    """
    B = theta.shape[0]
    nb = layout.n_bands
    lead = np.full((B, nb, nb), np.nan, dtype=complex)
    trace = np.full(B, np.nan)
    given = deficient if svd is not None else None
    if well_posed.all():  # (no copies: every window of a noise-free record)
        _, AG = _solution_operator(A_eq, zero_column, well_posed, Q, R_inv,
                                   given, svd, gram=False)
        lead, trace = _eiv_lead_trace(theta, A_eq, norms, AG, layout)
    elif well_posed.any():
        sel = np.flatnonzero(well_posed)
        _, AG = _solution_operator(A_eq[sel], zero_column[sel],
                                   np.ones(sel.size, dtype=bool), Q[sel],
                                   R_inv[sel], None if given is None else given[sel],
                                   svd, gram=False)
        lead[sel], trace[sel] = _eiv_lead_trace(
            theta[sel], A_eq[sel], norms[sel], AG, layout)
    return lead, trace, well_posed.copy()


def _eiv_lead_trace(theta, A_eq, norms, AG, layout):
    """``eiv_lead`` and ``eiv_trace`` of :func:`_terms_of_chunk` from the
    windows' solution operator ``AG`` (:func:`_window_solution`)."""
    nb = layout.n_bands
    S = np.ascontiguousarray(AG[:, :, :nb] / norms[:, None, :nb])
    leverage = np.sum((AG * A_eq.conj()).real, axis=2)
    e_weight = np.abs(_denominator_on_window(theta, layout)) ** 2
    e_weight = np.tile(e_weight, (1, layout.n_experiments))  # experiment-major
    S_h = np.ascontiguousarray(np.conj(np.swapaxes(S, 1, 2)))
    eiv_lead = (S_h * e_weight[:, None, :]) @ S
    eiv_trace = np.sum(e_weight * (1.0 - leverage), axis=1)
    # 0 <= 1 - h_r <= 1 and sum_r (1 - h_r) = q bound the trace by q min w and
    # q max w; round-off in 1 - h times a large |e|^2 can leave those bounds
    # (even the sign) on noise-free, nearly interpolated windows
    q = max(layout.dof, 0)
    eiv_trace = np.clip(eiv_trace, q * e_weight.min(axis=1),
                        q * e_weight.max(axis=1))
    return eiv_lead, eiv_trace


def _denominator_on_window(theta: np.ndarray, layout: LocalModelLayout) -> np.ndarray:
    """``e(x_r) = 1 + sum_s e_s x_r^s`` on the window, shape (B, 2n+1)."""
    _, x = window_offsets(layout.half_window)
    coefficients = theta[:, layout.den_columns]  # e_1..e_Re
    powers = x[:, None] ** np.arange(1, layout.den_degree + 1)  # (L, Re)
    return 1.0 + coefficients @ powers.T


def pooled_noise_variance(
    residual_power: np.ndarray, expected: np.ndarray, slow_bins: np.ndarray,
    n_slow: int, half_width: int,
) -> np.ndarray:
    """Pool ``sum ||r||^2 / sum E||r||^2 / sigma^2`` over neighbouring windows.

    Parameters
    ----------
    residual_power, expected : ndarray of shape (B,)
        ``||r||^2`` and its expectation over ``sigma^2`` of each window (NaN:
        not used).
    slow_bins : ndarray of shape (B,)
        Window centres; must be ``0..M//2`` (the other windows are their
        mirrors, with the same residual power).
    n_slow : int
        ``M``.
    half_width : int
        Windows ``k - half_width .. k + half_width`` are pooled.

    Returns
    -------
    ndarray of shape (B,)
        NaN where the window itself is NaN.
    """
    num_full = _slow_bin_values(residual_power, slow_bins, n_slow)
    den_full = _slow_bin_values(expected, slow_bins, n_slow)
    usable = np.isfinite(num_full) & np.isfinite(den_full)
    num_full = np.where(usable, num_full, 0.0)
    den_full = np.where(usable, den_full, 0.0)
    offsets = np.arange(-half_width, half_width + 1)
    window = (slow_bins[:, None] + offsets) % n_slow
    with np.errstate(invalid="ignore", divide="ignore"):
        pooled = num_full[window].sum(axis=1) / den_full[window].sum(axis=1)
    pooled[~(np.isfinite(residual_power) & np.isfinite(expected))] = np.nan
    return pooled


def _slow_bin_values(values: np.ndarray, slow_bins: np.ndarray, n_slow: int):
    """``values`` (B,) of windows ``0..M//2`` on all ``M`` slow bins (window
    ``M - k`` is the mirror of window ``k``: the same residual), NaN where a
    window is missing."""
    M = n_slow
    k = np.arange(M)
    position = np.full(M // 2 + 1, -1)
    position[slow_bins] = np.arange(slow_bins.size)
    idx = position[np.minimum(k, M - k)]
    return np.where(idx >= 0, values[np.maximum(idx, 0)], np.nan)


def robust_noise_variance(
    residual_power: np.ndarray, expected: np.ndarray, slow_bins: np.ndarray,
    n_slow: int, half_width: int, dof: int, *, switch: float = ROBUST_SWITCH,
) -> np.ndarray:
    """Noise level of ``"eiv_robust"``: the neighbours' median, or the own.

    Per window the own level is ``s_k = residual_power / expected``
    (``"eiv"``). The robust level is the median of ``s_j`` over the windows
    ``j = k - half_width .. k + half_width`` (mirrors beyond ``0`` and
    ``M//2``; NaN windows left out) divided by the median of ``chi^2_2q /
    2q`` (``q = dof``; the median of a level estimated on ``q`` complex dof
    sits below its mean), except where ``s_k > switch`` times it (model
    misfit in the window), where ``s_k`` is kept.

    Parameters
    ----------
    residual_power, expected : ndarray of shape (B,)
        ``||r||^2`` and its expectation over ``sigma^2`` (NaN: not used).
    slow_bins : ndarray of shape (B,)
        Window centres, within ``0..M//2``.
    n_slow : int
        ``M``.
    half_width : int
        Neighbours on each side.
    dof : int
        ``q`` of each window's level (> 0).
    switch : float, default :data:`ROBUST_SWITCH`
        ``inf``: always the neighbours' median.

    Returns
    -------
    ndarray of shape (B,)
        NaN where the window's own level is NaN.
    """
    from scipy.stats import chi2

    if dof <= 0:
        raise ValueError(f"`dof` must be positive; got {dof}.")
    with np.errstate(invalid="ignore", divide="ignore"):
        own = residual_power / expected
    full = _slow_bin_values(own, slow_bins, n_slow)
    offsets = np.arange(-half_width, half_width + 1)
    near = full[(slow_bins[:, None] + offsets) % n_slow]
    with warnings.catch_warnings():  # all neighbours NaN: NaN, as intended
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(near, axis=1)
    median /= chi2.median(2 * dof) / (2 * dof)
    with np.errstate(invalid="ignore"):
        level = np.where(own > switch * median, own, median)
    level[~np.isfinite(own)] = np.nan
    return level


def _band_values_at(theta: np.ndarray, layout: LocalModelLayout, x: float):
    """The local models' band values ``F N(x) / e(x)`` at scaled offset ``x``,
    shape (B, n_bands)."""
    nb = layout.n_bands
    num = sum(theta[:, s * nb:(s + 1) * nb] * x**s
              for s in range(layout.num_degree + 1))
    den = 1.0 + sum(theta[:, layout.den_columns][:, s - 1] * x**s
                    for s in range(1, layout.den_degree + 1))
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN windows
        return layout.F * num / np.asarray(den)[..., None]


def neighbour_disagreement(local_fit) -> np.ndarray:
    """Mean squared disagreement of each band value with the neighbouring
    windows' local models.

    At window ``k``: the mean over the windows ``k - 1`` and ``k + 1`` of
    ``|G_k - G_(k-+1)(offset +-1)|^2``, ``G_j(offset)`` the local model of
    window ``j`` (numerator over denominator, no transient) at slow bin ``k``.
    Windows ``0`` and ``M//2`` use their one neighbour inside ``0..M//2``;
    a NaN (not well posed) neighbour is left out; NaN where the window itself
    is NaN, ``0`` where it has no usable neighbour.

    Parameters
    ----------
    local_fit : lrmfrf.local_models.LocalModelFit
        Closed form on the windows ``0..M//2`` (consecutive).

    Returns
    -------
    ndarray of shape (B, n_bands), float
    """
    lay = local_fit.layout
    bins = np.asarray(local_fit.slow_bins)
    B = bins.size
    if B < 2 or np.any(np.diff(bins) != 1):
        raise ValueError(
            "std_method='eiv_robust' needs the fit of consecutive windows (the "
            "whole record, slow bins 0..M//2); got non-consecutive slow bins."
        )
    n = lay.half_window
    plus = _band_values_at(local_fit.theta, lay, 1.0 / n)  # window k at k+1
    minus = _band_values_at(local_fit.theta, lay, -1.0 / n)  # window k at k-1
    G0 = local_fit.system
    sq = np.full((2,) + G0.shape, np.nan)
    sq[0, 1:] = np.abs(G0[1:] - plus[:-1]) ** 2  # left neighbour
    sq[1, :-1] = np.abs(G0[:-1] - minus[1:]) ** 2  # right neighbour
    count = np.isfinite(sq).sum(axis=0)
    d = np.where(count > 0, np.nansum(sq, axis=0) / np.maximum(count, 1), 0.0)
    d[~np.isfinite(G0)] = np.nan
    return d


def neighbour_bias_term(
    d: np.ndarray, v: np.ndarray, threshold: float = ROBUST_NBR_THRESHOLD,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """``d`` where ``d / v`` exceeds ``threshold`` times its median, else 0.

    The median of ``d / v`` over the record's finite entries (within
    ``mask``) sets its scale on pure noise; entries well above it carry a
    model misfit that the noise variance ``v`` does not hold.

    Parameters
    ----------
    d, v : ndarray, same shape
        Neighbour disagreement (:func:`neighbour_disagreement`) and the
        ``"eiv"`` variance of one record.
    threshold : float, default :data:`ROBUST_NBR_THRESHOLD`
    mask : ndarray of bool, optional
        Entries the median is taken over (default: all finite ones).

    Returns
    -------
    ndarray
        The term to add to the variance (``0`` where ``d / v`` is not finite).
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        z = d / v
    finite = np.isfinite(z) if mask is None else np.isfinite(z) & mask
    if not finite.any():
        return np.zeros_like(z)
    median = np.median(z[finite])
    with np.errstate(invalid="ignore"):
        add = np.where(z > threshold * median, d, 0.0)
    return np.where(np.isfinite(add), add, 0.0)


def robust_band_covariance(lead, trace, local_fit, n_slow: int) -> np.ndarray:
    """Band covariance of ``std_method="eiv_robust"`` (module docstring).

    Parameters
    ----------
    lead, trace : ndarray
        ``eiv_lead`` (B, n_bands, n_bands) and ``eiv_trace`` (B,) of the
        windows (:func:`eiv_terms`).
    local_fit : lrmfrf.local_models.LocalModelFit
        Closed form on the windows ``0..M//2`` (its ``theta``, ``system``,
        ``rss``).
    n_slow : int
        ``M``.

    Returns
    -------
    ndarray of shape (B, n_bands, n_bands), complex
        ``F^2 sigma_robust^2 S^H diag(|e|^2) S`` plus the neighbour term on
        the diagonal; NaN where the window is not well posed.
    """
    layout = local_fit.layout
    s2 = robust_noise_variance(local_fit.rss, trace, local_fit.slow_bins, n_slow,
                               layout.half_window, layout.dof)
    cov = layout.F**2 * lead * s2[:, None, None]
    eiv = _eiv_covariance(lead, trace, local_fit.rss, layout)
    v = np.real(np.diagonal(eiv, axis1=1, axis2=2))
    ok = local_fit.well_posed[:, None] & np.isfinite(v)
    add = neighbour_bias_term(neighbour_disagreement(local_fit), v,
                              mask=ok)
    idx = np.arange(layout.n_bands)
    cov[:, idx, idx] += add
    return cov


def band_covariance(
    terms: VarianceTerms,
    layout: LocalModelLayout,
    method: str = "eiv",
    *,
    slow_bins: np.ndarray | None = None,
    n_slow: int | None = None,
    noise_variance: np.ndarray | None = None,
) -> np.ndarray:
    """Covariance ``E[dG_b conj(dG_c)]`` of the window-centre band values.

    Parameters
    ----------
    terms : VarianceTerms
    layout : LocalModelLayout
    method : {"lemma2", "eiv", "hc", "eiv_pooled", "eiv_dof", "eiv_robust"}, \
default "eiv"
        See the module docstring. ``"eiv_robust"`` raises: its neighbour
        term needs the local models (:func:`robust_band_covariance`).
    slow_bins, n_slow : optional
        Window centres (``0..M//2``) and ``M``; needed by ``"eiv_pooled"``.
    noise_variance : ndarray of shape (B,), optional
        A known variance of ``V_l(k)`` instead of the residual estimate
        (``"eiv"``: ``sigma^2``; ``"lemma2"``: the variance of ``eps``);
        for studies of the routes.

    Returns
    -------
    ndarray of shape (B, n_bands, n_bands), complex
    """
    F2 = layout.F**2
    with np.errstate(invalid="ignore", divide="ignore"):
        if method == "lemma2":
            s2 = terms.rss / terms.dof if noise_variance is None else noise_variance
            return F2 * terms.gram_lead * s2[:, None, None]
        if method == "hc":
            return F2 * terms.hc_lead
        if method == "eiv":
            s2 = terms.rss / terms.eiv_trace
        elif method == "eiv_dof":
            # rss = s2 (trace - s2 absorbed): the root that tends to rss/trace
            t, a = terms.eiv_trace, terms.absorbed
            disc = np.maximum(t**2 - 4 * a * terms.rss, 0.25 * t**2)
            s2 = 2 * terms.rss / (t + np.sqrt(disc))
        elif method == "eiv_robust":
            raise ValueError(
                "band_covariance cannot compute method='eiv_robust': its "
                "neighbour term needs the local models, which VarianceTerms "
                "does not hold. Use robust_band_covariance(terms.eiv_lead, "
                "terms.eiv_trace, local_fit, n_slow) or calibrated_local_fit."
            )
        elif method == "eiv_pooled":
            if slow_bins is None or n_slow is None:
                raise ValueError("method='eiv_pooled' needs slow_bins and n_slow.")
            s2 = pooled_noise_variance(terms.rss, terms.eiv_trace, slow_bins, n_slow,
                                       layout.half_window)
        else:
            raise ValueError(
                f"`method` must be one of {STD_METHODS}; got {method!r} instead."
            )
        if noise_variance is not None:
            s2 = noise_variance
        return F2 * terms.eiv_lead * s2[:, None, None]


def check_std_method(value, name: str = "std_method") -> str:
    """Check an estimator's ``std_method`` (a route of :data:`STD_METHODS`)."""
    if not isinstance(value, str) or value not in STD_METHODS:
        raise ValueError(
            f"`{name}` must be one of {STD_METHODS}; got {value!r} instead. Use "
            f"{DEFAULT_STD_METHOD!r} (the default, calibrated) or 'lemma2' for "
            "the paper's eq. (Variance)."
        )
    return value


def _weighted_tables(layout: LocalModelLayout) -> dict:
    """Row-weighted moment tables (for ``A^H diag(w) A``) in the column order
    of :func:`lrmfrf.solvers._kernel_tables` (the denominator columns last)."""
    return _kernel_weighted_tables(layout)


def eiv_terms(
    U: np.ndarray,
    Y: np.ndarray,
    layout: LocalModelLayout,
    theta: np.ndarray,
    slow_bins: np.ndarray,
    *,
    backend: str = "auto",
) -> tuple[np.ndarray, np.ndarray]:
    """``eiv_lead`` and ``eiv_trace`` of :class:`VarianceTerms`, fast.

    The compiled kernel (:func:`lrmfrf._compiled_uncertainty.eiv_windows`)
    when the backend resolves to ``"numba"``; windows whose Gram matrix fails
    its pivot check there, and every window with ``backend="numpy"``, go
    through :func:`variance_terms` (the dense regressor). Both give the same
    terms up to round-off. :func:`eiv_terms_rows` does several output rows at
    once.

    Parameters
    ----------
    U : ndarray of shape (P, n_u N), complex
    Y : ndarray of shape (P, M), complex
    layout : LocalModelLayout
    theta : ndarray of shape (B, n_params), complex
        Closed-form parameters; only the denominator columns are read (NaN
        rows give NaN terms).
    slow_bins : ndarray of shape (B,), int
    backend : {"auto", "numpy", "numba"}, default "auto"

    Returns
    -------
    eiv_lead : ndarray of shape (B, n_bands, n_bands), complex
    eiv_trace : ndarray of shape (B,)
    """
    lead, trace = eiv_terms_rows(U, Y[:, None], layout, theta[None], slow_bins,
                                 backend=backend)
    return lead[0], trace[0]


def eiv_terms_rows(
    U: np.ndarray,
    Y: np.ndarray,
    layout: LocalModelLayout,
    theta: np.ndarray,
    slow_bins: np.ndarray,
    *,
    backend: str = "auto",
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`eiv_terms` of several output rows of the same windows.

    The compiled kernel computes what does not depend on the output row (the
    factor of the input and transient block of ``A^H A`` and the Gram of its
    inverse) once per window for all rows (see
    :mod:`lrmfrf._compiled_uncertainty`); each row's terms equal
    :func:`eiv_terms` of that row up to round-off.

    Parameters
    ----------
    U : ndarray of shape (P, n_u N), complex
    Y : ndarray of shape (P, n_rows, M), complex
        Output rows (each its own local problem, its own denominator).
    layout : LocalModelLayout
    theta : ndarray of shape (n_rows, B, n_params), complex
        Closed-form parameters of each row; only the denominator columns are
        read (NaN rows give NaN terms).
    slow_bins : ndarray of shape (B,), int
    backend : {"auto", "numpy", "numba"}, default "auto"

    Returns
    -------
    eiv_lead : ndarray of shape (n_rows, B, n_bands, n_bands), complex
    eiv_trace : ndarray of shape (n_rows, B)
    """
    slow_bins = np.asarray(slow_bins, dtype=int)
    theta = np.asarray(theta)
    n_rows, B = Y.shape[1], slow_bins.size
    if theta.shape[:2] != (n_rows, B):
        raise ValueError(
            f"`theta` must have shape (n_rows, B, n_params) = ({n_rows}, {B}, "
            f"{layout.n_params}); got {theta.shape} instead."
        )
    backend = resolve_backend(backend, B, layout.n_params, eiv=True)
    if backend != "numba":
        parts = [variance_terms(U, Y[:, o], layout, theta[o], slow_bins,
                                with_hc=False) for o in range(n_rows)]
        return (np.stack([terms.eiv_lead for terms in parts]),
                np.stack([terms.eiv_trace for terms in parts]))
    return _eiv_terms_compiled(U, Y, layout, theta, slow_bins)


def _eiv_terms_compiled(U, Y, layout, theta, slow_bins, raws=None, *,
                        raw_rows=None):
    """The compiled route of :func:`eiv_terms_rows` (``backend="numba"``).

    ``raws``: optional per-row ``eiv_raw`` of
    :class:`lrmfrf.solvers.LocalSolution` (the kernel's terms computed with
    the solve of ``theta``; windows not ``valid`` there, i.e. re-solved by
    QR, are computed here again); without them every window is computed
    here. ``raw_rows``: the same terms with a leading row axis (the kernel's
    own arrays, used and changed in place instead of stacked anew), and
    after them optionally the dense terms the QR solve computed for the
    windows it re-solved, ``(lead, trace, done)`` with a leading row axis
    (:func:`lrmfrf.solvers._with_qr_fallback`): windows that need the dense
    route here take those instead of building and factoring the window
    again (every window of a noise-free record with an over-parameterised
    denominator)."""
    n_rows, B = theta.shape[:2]
    good = _all_last(np.isfinite(theta))
    nb = layout.n_bands
    dense = None
    if raw_rows is not None:
        lead, hw_trace, w_sum, w_min, w_max, valid, *dense = raw_rows
        dense = dense[0] if dense else None
        todo = good & ~valid
        ok = np.ones((n_rows, B), dtype=bool)
    elif raws is None or any(raw is None for raw in raws):
        todo = np.ones((n_rows, B), dtype=bool)
        lead = np.empty((n_rows, B, nb, nb), dtype=complex)
        hw_trace, w_sum, w_min, w_max = (np.empty((n_rows, B)) for _ in range(4))
        ok = np.ones((n_rows, B), dtype=bool)
    else:
        lead, hw_trace, w_sum, w_min, w_max, valid = (
            np.stack(part) for part in zip(*raws, strict=True)
        )
        todo = good & ~valid
        ok = np.ones((n_rows, B), dtype=bool)
    # the windows still without terms: all rows' windows in one kernel pass
    # (each window is computed alone, so a subset gives the same terms)
    windows = np.flatnonzero(todo.any(axis=0))
    if windows.size:
        sub = theta[:, windows]
        sub_good = good[:, windows]
        den = np.where(sub_good[:, :, None], sub[:, :, layout.den_columns], 0.0)
        _, x = window_offsets(layout.half_window)
        powers = x[:, None] ** np.arange(1, layout.den_degree + 1)
        weights, col_base, tables, _ = _kernel_tables(layout)
        parts = _compiled_uncertainty.eiv_windows(
            U.reshape(U.shape[0], layout.n_inputs, -1), Y, slow_bins[windows],
            den, powers, weights, col_base, nb, nb + layout.n_experiments,
            tables=tables, weighted_tables=_weighted_tables(layout),
            fallback_tol=CHOLESKY_FALLBACK_TOL,
        )
        pick = todo[:, windows]
        for full, part in zip((lead, hw_trace, w_sum, w_min, w_max, ok), parts,
                              strict=True):
            target = full[:, windows]
            target[pick] = part[pick]
            full[:, windows] = target
    # as variance_terms: the trace within q min w .. q max w
    q = max(layout.dof, 0)
    trace = np.clip(w_sum - hw_trace, q * w_min, q * w_max)
    # windows whose pivot check failed, or whose band block (S^H diag(w) S,
    # positive semi-definite) has a negative diagonal: round-off of a nearly
    # singular G (e.g. a rank-deficient denominator block on noise-free data)
    # dominates there; the dense route factors the regressor by QR (the
    # truncated SVD where R does not certify full rank)
    negative = _any_last(np.real(np.diagonal(lead, axis1=-2, axis2=-1)) < 0)
    redo = good & (~ok | negative)
    if dense is not None:  # the QR solve's, from its own factors
        dense_lead, dense_trace, done = dense
        ready = redo & done
        lead[ready] = dense_lead[ready]
        trace[ready] = dense_trace[ready]
        redo &= ~done
    chunk = qr_chunk_size(layout)
    # (the section reads and sets the BLAS thread counts: only when needed)
    with _single_threaded_blas() if redo.any() else contextlib.nullcontext():
        for o, windows in enumerate(redo):
            windows = np.flatnonzero(windows)
            for start in range(0, windows.size, chunk):
                part = windows[start : start + chunk]
                terms = _terms_of_chunk(U, Y[:, o], layout, theta[o, part],
                                        slow_bins[part], False)
                lead[o, part] = terms[1]
                trace[o, part] = terms[4]
    lead[~good] = np.nan
    trace[~good] = np.nan
    return lead, trace


def _all_last(flags: np.ndarray) -> np.ndarray:
    """``flags.all(axis=-1)``; one pass over the whole array first (the
    reduction along a short last axis is several times slower, and it is
    usually all True)."""
    if flags.all():
        return np.ones(flags.shape[:-1], dtype=bool)
    return flags.all(axis=-1)


def _any_last(flags: np.ndarray) -> np.ndarray:
    """``flags.any(axis=-1)``, as :func:`_all_last` (usually all False)."""
    if not flags.any():
        return np.zeros(flags.shape[:-1], dtype=bool)
    return flags.any(axis=-1)


def _eiv_covariance(lead, trace, rss, layout, exponent=0, out=None):
    """``F^2 sigma^2 S^H diag(w) S`` with ``sigma^2 = ||r||^2 / trace``, times
    ``2**exponent`` (exact; :func:`lrmfrf.local_models.scale_by_power_of_two`).

    ``out`` (may be ``lead`` itself) receives the result in place of new
    arrays: the same operations in the same order, so the same values, without
    the temporaries (``n_bands^2`` complex values a window: 36 on 2x2, F = 3).
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 = rss / trace
    if out is None:
        return scale_by_power_of_two(layout.F**2 * lead * s2[:, None, None],
                                     exponent)
    np.multiply(layout.F**2, lead, out=out)
    np.multiply(out, s2[:, None, None], out=out)
    if exponent:
        with np.errstate(over="ignore", under="ignore"):
            np.ldexp(out.real, exponent, out=out.real)
            np.ldexp(out.imag, exponent, out=out.imag)
    return out


def _with_covariance(local_fit, cov, keep_cov=None):
    """``local_fit`` with the band covariance ``cov`` (NaN where not well
    posed) as ``system_var`` and, when present (or ``keep_cov``),
    ``system_cov``."""
    if keep_cov is None:
        keep_cov = local_fit.system_cov is not None
    cov[~local_fit.well_posed] = np.nan
    var = np.real(np.diagonal(cov, axis1=1, axis2=2)).copy()
    return replace(local_fit, system_var=var, system_cov=cov if keep_cov else None)


def keeps_lemma2(method: str, layout: LocalModelLayout) -> bool:
    """Whether route ``method`` gives Lemma 2's variance on ``layout`` (then it
    computes no terms beyond the closed form's)."""
    return (method == "lemma2" or layout.dof <= 0
            or (method == "eiv" and layout.den_degree == 0))


def iter_calibrated_fits(
    spectra,
    layout: LocalModelLayout,
    method: str,
    *,
    output: int = 0,
    backend: str = "auto",
    return_cov: bool = False,
):
    """:func:`lrmfrf.local_models.iter_local_fits` with the variance of route
    ``method``, chunk by chunk (bounded memory).

    Parameters
    ----------
    spectra : lrmfrf.local_models.OneSidedSpectra
    layout : LocalModelLayout
    method : {"lemma2", "eiv"}
        Routes that stream (the others need :func:`calibrated_local_fit`).
    output : int, default 0
    backend : {"auto", "numpy", "numba"}, default "auto"
    return_cov : bool, default False

    Yields
    ------
    start : int
    fit : LocalModelFit
        As :func:`~lrmfrf.local_models.iter_local_fits`, with ``system_var``
        (and ``system_cov``) of route ``method``; equal to
        ``calibrated_local_fit`` on the full spectra up to round-off.
    """
    if method not in ("lemma2", "eiv"):
        raise ValueError(
            f"`method` {method!r} does not stream; use 'lemma2' or 'eiv', or "
            "calibrated_local_fit on the whole fit."
        )
    fits = iter_local_fits(spectra, layout, output=output, backend=backend,
                           return_cov=return_cov)
    if keeps_lemma2(method, layout):
        yield from fits
        return
    backend = resolve_backend(backend, spectra.n_slow // 2 + 1, layout.n_params,
                              eiv=True)
    # the normalisation of iter_local_fits: the terms are computed on the
    # normalised chunk and the covariance scaled back as the system's square
    u_exponent = power_of_two_exponent(spectra.inputs)
    y_exponent = power_of_two_exponent(spectra.outputs[:, output])
    try:
        for start, fit in fits:
            stop = start + fit.slow_bins.size
            U, Y, bins = spectra.window_spectra(start, stop, layout.half_window,
                                                output)
            U = scale_by_power_of_two(U, -u_exponent)
            Y = scale_by_power_of_two(Y, -y_exponent)
            # the terms read only the (dimensionless) denominator of theta
            lead, trace = eiv_terms(U, Y, layout, fit.theta, bins, backend=backend)
            del U, Y
            rss = scale_by_power_of_two(fit.rss, -2 * y_exponent)
            cov = _eiv_covariance(lead, trace, rss, layout)
            cov = scale_by_power_of_two(cov, 2 * (y_exponent - u_exponent))
            yield start, _with_covariance(fit, cov)
    finally:
        # ``fits`` (a local) holds a single-threaded-BLAS section while
        # suspended: an exception above would keep it, and BLAS on one
        # thread, as long as its traceback (as fit, 894792c)
        fits.close()


def iter_calibrated_fit_rows(
    spectra,
    layout: LocalModelLayout,
    method: str,
    *,
    backend: str = "auto",
    return_cov: bool = False,
):
    """:func:`lrmfrf.local_models.iter_local_fit_rows` (all output rows of a
    chunk solved together) with the variance of route ``method``.

    Yields
    ------
    start : int
    fits : list of LocalModelFit
        One per output row, as :func:`iter_calibrated_fits` of that row.
    """
    if method not in ("lemma2", "eiv"):
        raise ValueError(
            f"`method` {method!r} does not stream; use 'lemma2' or 'eiv', or "
            "calibrated_local_fit on the whole fit."
        )
    if keeps_lemma2(method, layout):
        yield from iter_local_fit_rows(spectra, layout, backend=backend,
                                       return_cov=return_cov)
        return
    n_y = spectra.outputs.shape[1]
    backend = resolve_backend(backend, spectra.n_slow // 2 + 1, layout.n_params,
                              eiv=True)
    # the normalisation of iter_local_fit_rows, row by row
    u_exponent = power_of_two_exponent(spectra.inputs)
    y_exponents = [power_of_two_exponent(spectra.outputs[:, o]) for o in range(n_y)]
    # the compiled kernel computes the terms with the solve (same window data
    # and factor of A^H A); the chunk's normalised spectra come along for the
    # windows re-solved by QR
    rescaled = u_exponent != 0 or any(y_exponents)
    for start, fits, (U, Y, bins, raws, thetas) in _iter_fit_rows(
        spectra, layout, backend=backend, return_cov=return_cov, eiv=True,
        exponents=(u_exponent, y_exponents),
    ):
        if thetas is None or rescaled:  # (else the fits' theta: its memory)
            thetas = np.stack([fit.theta for fit in fits])
        if backend == "numba":
            leads, traces = _eiv_terms_compiled(U, Y, layout, thetas, bins,
                                                raw_rows=raws)
        else:  # the terms of all rows in one pass (shared input block)
            leads, traces = eiv_terms_rows(U, Y, layout, thetas, bins,
                                           backend=backend)
        del U, Y
        out = []
        for fit, y_exponent, lead, trace in zip(fits, y_exponents, leads, traces,
                                                strict=True):
            rss = scale_by_power_of_two(fit.rss, -2 * y_exponent)
            # (in place: the row's lead is not used again)
            cov = _eiv_covariance(lead, trace, rss, layout,
                                  2 * (y_exponent - u_exponent), out=lead)
            # (the chunk's fits come without Lemma 2's variances: eiv=True)
            out.append(_with_covariance(fit, cov, keep_cov=return_cov))
        yield start, out


def calibrated_local_fit(U, Y, layout: LocalModelLayout, local_fit, method: str):
    """The closed-form fit with the band (co)variances of route ``method``.

    Parameters
    ----------
    U : ndarray of shape (P, n_u N), complex
    Y : ndarray of shape (P, M), complex
        The spectra the closed form was fitted on.
    layout : LocalModelLayout
    local_fit : lrmfrf.local_models.LocalModelFit
        Closed form on ``U``, ``Y`` (its ``system_var`` and ``system_cov``
        are Lemma 2's).
    method : str
        A route of :data:`STD_METHODS`.

    Returns
    -------
    LocalModelFit
        ``local_fit`` itself for ``"lemma2"``, for ``"eiv"`` without a
        denominator (where it is Lemma 2), or for zero residual degrees of
        freedom (the variance is then NaN by any route); otherwise a copy with
        ``system_var`` and ``system_cov`` (when present) replaced. The noise
        variance and the parameters are unchanged.
    """
    if keeps_lemma2(method, layout):
        return local_fit  # (eiv with e(x) = 1: the sandwich is Lemma 2, LPM)
    if method == "eiv":  # compiled (numba) where available
        lead, trace = eiv_terms(U, Y, layout, local_fit.theta,
                                local_fit.slow_bins)
        return _with_covariance(
            local_fit, _eiv_covariance(lead, trace, local_fit.rss, layout)
        )
    if method == "eiv_robust":  # whole record: the neighbouring windows
        lead, trace = eiv_terms(U, Y, layout, local_fit.theta,
                                local_fit.slow_bins)
        return _with_covariance(
            local_fit, robust_band_covariance(lead, trace, local_fit, Y.shape[1])
        )
    terms = variance_terms(U, Y, layout, local_fit.theta, local_fit.slow_bins,
                           with_hc=method in ("hc", "eiv_dof"))
    cov = band_covariance(terms, layout, method, slow_bins=local_fit.slow_bins,
                          n_slow=Y.shape[1])
    cov[~local_fit.well_posed] = np.nan
    var = np.real(np.diagonal(cov, axis1=1, axis2=2)).copy()
    return replace(
        local_fit,
        system_var=var,
        system_cov=None if local_fit.system_cov is None else cov,
    )


def calibrated_refined_fit(U, Y, layout: LocalModelLayout, closed_fit, refined_fit,
                           method: str):
    """A refined fit's linearised covariance with the ``"eiv"`` noise level.

    The refined (SK/LM) estimate keeps the shape of its linearised
    covariance (at the final estimate), but its noise variance ``J / q`` is
    low: the refined fit absorbs part of the noise (about 0.66x the
    Monte-Carlo std after LM). With ``method="eiv"`` the covariance is scaled
    per window by ``sigma^2 / noise_var``, ``sigma^2 = ||r||^2 / sum_r
    |e(x_r)|^2 (1 - h_r)`` of the closed form on the same window (the noise
    estimate of the ``"eiv"`` route, see :func:`eiv_terms`); the other
    routes leave the refined fit as it is.

    Parameters
    ----------
    U, Y : ndarray
        The (normalised) spectra of the fit.
    layout : LocalModelLayout
    closed_fit, refined_fit : LocalModelFit
        The closed form and its refinement on the same windows.
    method : str
        A route of :data:`STD_METHODS` other than ``"eiv_robust"``.

    Returns
    -------
    LocalModelFit
        ``refined_fit`` itself, or a copy with ``system_var`` and
        ``system_cov`` scaled.

    Raises
    ------
    ValueError
        For a ``method`` that is not a route, and for ``"eiv_robust"``: it is
        defined on the closed form's neighbouring local models only (returning
        the refinement's own std under its name would be a silent wrong std).
    """
    check_std_method(method, "method")
    if method == "eiv_robust":
        raise ValueError(
            "calibrated_refined_fit cannot compute method='eiv_robust': the "
            "route is defined on the closed form's local models only. Use "
            "method='eiv' for a refined fit, or calibrated_local_fit for the "
            "closed form."
        )
    if method != "eiv" or keeps_lemma2(method, layout):
        return refined_fit
    _, trace = eiv_terms(U, Y, layout, closed_fit.theta, closed_fit.slow_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = closed_fit.rss / trace / refined_fit.noise_var
    cov = refined_fit.system_cov
    return replace(
        refined_fit,
        system_var=refined_fit.system_var * factor[:, None],
        system_cov=None if cov is None else cov * factor[:, None, None],
    )


#: :func:`experiment_noise_weights`: experiments' noise variances within this
#: ratio of each other are treated as equal (measured:
#: ``benchmarks/unequal_noise.py``; the pooled ``"eiv"`` std is then within
#: about 10 % of the Monte-Carlo std on every entry).
EQUAL_NOISE_RATIO = 1.5

#: :func:`experiment_noise_weights`: the levels must also differ by this many
#: standard deviations of their difference if they were equal
#: (:class:`ExperimentNoiseLevels` ``cov``: the exact variance of the
#: residual energies' quadratic forms, the residual rows' correlation
#: included). Chosen on equal-noise records of random stages (SISO open and
#: closed loop, 2 x 2; P = 2-4; 3-60 residual dof per window; 25-70 dB; the
#: 385 records of ``benchmarks/noise_level_false_alarms.py --records 400
#: --set tune``): the largest difference was 3.6 of them (a normal-like spread, no heavy
#: tail at few dof; the log ratio has one: a level estimate near zero).
#: Re-checked when ``cov`` took in the division by each window's estimated
#: level (lvl31, the differences about 5 % more sd of it): on the 288
#: records of ``--records 300 --set tune`` the largest is 3.78 (2.96 before),
#: so 3.75 (the next step of the benchmark's grid) would flag one; 4.0 kept
#: (``--set check``: false alarms 0.3 % as before, one record at 4.7 sd;
#: detection of a 2x noise std 53 % -> 58 %, of 4x 75 % -> 80 %). The
#: spread of earlier versions (Satterthwaite, the residual rows taken as
#: independent, though the residual projector has rank dof) was 1.5x (53
#: residual dof per window) to 11x (5 dof) too low and flagged most
#: equal-noise records below about 20 dof even at 6 of it (review30).
EQUAL_NOISE_Z = 4.0

#: :func:`experiment_noise_weights`: re-estimations of the levels on the
#: weighted fit; a row without convergence by then is not weighted.
#: (``benchmarks/unequal_noise.py``, variance ratio 100: one record of 120
#: needed 10, the contraction about 0.6 per step.)
NOISE_WEIGHT_ITERATIONS = 16

#: :func:`experiment_noise_weights`: the re-estimation stops when no weight
#: changes by more than this fraction.
WEIGHT_TOL = 0.005

#: :func:`experiment_noise_weights`: no weighting with fewer residual
#: degrees of freedom per window than this many per experiment (a guard:
#: with the level test of review30 equal noise is not flagged there; with
#: one residual dof a window's normalised energies equal its gains and the
#: ratio is exactly 1. Earlier, random first-order layouts with equal noise
#: and one residual dof per window were weighted by factors of 1e3).
MIN_NOISE_LEVEL_DOF = 1

#: :func:`experiment_noise_levels`: a window whose residual is below this
#: fraction of its measured values (in norm) is fitted to round-off (noise-free
#: data: about 1e-15) and carries no noise level; measurement noise 200 dB
#: below the output would still count.
EXACT_RESIDUAL = 1e-10

#: :func:`experiment_noise_levels`: at most this many (non-overlapping) windows.
NOISE_LEVEL_WINDOWS = 16


@dataclass
class ExperimentNoiseLevels:
    """Relative noise variances of the experiments, per output row.

    Attributes
    ----------
    ratio : ndarray of shape (P, n_y)
        Each experiment's noise variance over the mean of the experiments'
        (per output row; 1 for equal levels).
    dof : ndarray of shape (P, n_y)
        Effective complex degrees of freedom of each level's estimate at
        equal levels: ``1 / cov[p, p]`` (its relative variance); 0 where
        there is no estimate.
    clamped : ndarray of shape (n_y,), bool, optional
        Rows whose smallest level estimate sat at its lower bound (1e-3 of
        the largest): the levels are not a noise estimate there.
    cov : ndarray of shape (P, P, n_y), optional
        Covariance of the level estimates (``ratio`` before its
        normalisation, about 1 at equal levels, of the fit, weighted or not)
        if the fit's experiments had equal noise levels: exact for Gaussian
        noise given the fits' residual projectors and the windows' levels,
        the residual rows' correlation included, and the division of each
        window's energies by its own estimated level (:func:`_noise_levels_of_row`;
        exact for white equation noise, 0.99-1.03x in variance on synthetic
        windows; on two SISO library fits the level differences spread
        0.96x and 0.87x of it in std, ``tests/test_noise_weight_guard.py``).
    """

    ratio: np.ndarray
    dof: np.ndarray
    clamped: np.ndarray | None = None
    cov: np.ndarray | None = None


def experiment_noise_levels(spectra, layout: LocalModelLayout, *,
                            weights: np.ndarray | None = None,
                            max_windows: int = NOISE_LEVEL_WINDOWS):
    """Estimate each experiment's relative output-noise variance per row.

    The experiments of an output row share one local model, and the
    ``"eiv"`` std assumes they share one noise variance. This fits the
    closed form (QR, numpy) on up to ``max_windows`` non-overlapping
    windows away from DC and the slow Nyquist bin and compares the
    residual energy of each experiment's equations with its expectation:
    with ``R = I - Q Q^H`` the residual projector and ``w_s = |e(x_s)|^2``,
    ``E ||r_p||^2 = sigma^2 sum_j c_j sum_{r in p, s in j} |R_rs|^2 w_s``
    (first order, the errors-in-variables noise model of :mod:`this module
    <lrmfrf.uncertainty>` with experiment ``j``'s noise variance ``c_j
    sigma^2``). Each window's energies are normalised by its own pooled
    level (the noise spectrum may be coloured; a frequency-independent
    ratio between the experiments is assumed) and the linear equations for
    ``c``, summed over the windows, are solved. The covariance of ``c`` at
    equal levels (the test of :func:`unequal_noise_rows`) is built from
    that of Gaussian quadratic forms: ``C_pq = cov(||r_p||^2, ||r_q||^2) =
    sigma^4 tr(R D_p R W R D_q R W)`` (``W = diag(w)``, ``D_p`` experiment
    ``p``'s rows), per window ``J C J^T / (1 + v)`` for the division by the
    window's level (``J = I - m 1^T / g``, ``m = M 1``, ``g = 1^T M 1``, ``v
    = 1^T C 1 / g^2``).
    The columns the output rows share (system and transient) are factored
    once per weighting, each row adds its denominator columns (about 17 ms
    for 2 x 2, P = 2, 16 windows, of which the covariance about 7 ms).

    Parameters
    ----------
    spectra : lrmfrf.local_models.OneSidedSpectra
    layout : LocalModelLayout
    weights : ndarray of shape (P, n_y), optional
        Fit each row on the experiments weighted by these factors (their
        inputs and outputs scaled alike: the weighted least squares whose
        equation rows of experiment ``p`` are scaled by ``weights[p, o]``);
        the levels returned are still those of the records.
    max_windows : int, default NOISE_LEVEL_WINDOWS

    Returns
    -------
    ExperimentNoiseLevels or None
        None with one experiment, without residual degrees of freedom, or
        when no window fits in the record.
    """
    P, n_y = spectra.outputs.shape[:2]
    n, L, M = layout.half_window, layout.window, spectra.n_slow
    if P < 2 or layout.dof <= 0:
        return None
    # windows that do not overlap each other or their conjugate mirrors
    centres = np.arange(n + 1, M // 2 - n, L)
    if centres.size == 0:
        return None
    if centres.size > max_windows:
        pick = np.linspace(0, centres.size - 1, max_windows).round().astype(int)
        centres = centres[pick]
    parts = [spectra.window_spectra(k, k + 1, n, list(range(n_y)))
             for k in centres]
    shared, den, b = _noise_level_regressors(parts, layout)
    ratio = np.ones((P, n_y))
    dof = np.zeros((P, n_y))
    clamped = np.zeros(n_y, dtype=bool)
    cov = np.zeros((P, P, n_y))
    bases = {}  # the shared columns' factorisation, per weighting of the rows
    with _single_threaded_blas():
        for o in range(n_y):
            A_d, b_o, key = den[o], b[o], None
            if weights is not None:
                rows = np.repeat(weights[:, o], L)
                A_d, b_o, key = A_d * rows[:, None], b_o * rows, weights[:, o].tobytes()
            if key not in bases:
                bases[key] = _SharedColumns.of(
                    shared if weights is None else shared * rows[:, None])
            levels = _noise_levels_of_row(bases[key], A_d, b_o, layout)
            if levels is not None:
                ratio[:, o], clamped[o], cov[..., o] = levels
                with np.errstate(divide="ignore"):
                    dof[:, o] = 1.0 / np.diagonal(cov[..., o])
                if weights is not None:  # the records' levels
                    ratio[:, o] /= weights[:, o] ** 2
                    ratio[:, o] /= ratio[:, o].mean()
    return ExperimentNoiseLevels(ratio, dof, clamped, cov)


def _noise_level_regressors(parts, layout):
    """The local regressors of single windows (:func:`lrmfrf.windows.
    local_regressor`, the same values) for every output row at once.

    ``parts`` are ``spectra.window_spectra(k, k + 1, n, outputs)`` of the
    windows. Returns the columns the rows share (system and transient,
    ``(B, P L, n_system + n_transient)``), the denominator columns ``(n_y,
    B, P L, R_e)`` and the measured values ``(n_y, B, P L)``."""
    U = np.stack([part[0] for part in parts])  # (B, P, n_u F L)
    Y = np.stack([part[1] for part in parts])  # (B, P, n_y, L)
    B, P, n_y, L = Y.shape
    r, x = window_offsets(layout.half_window)
    # the compact spectra of one window: slow bins 0..L-1, centre n
    fast = band_indices(r + layout.half_window, layout, L)  # (L, n_bands)
    u_win = U[:, :, fast]  # (B, P, L, n_bands)
    powers_g = x[:, None] ** np.arange(layout.num_degree + 1)  # (L, Rg+1)
    system = powers_g[None, None, :, :, None] * u_win[:, :, :, None, :]
    shared = np.empty((B, P * L, layout.n_system + layout.n_transient),
                      dtype=system.dtype)
    shared[..., : layout.n_system] = system.reshape(B, P * L, layout.n_system)
    powers_t = x[:, None] ** np.arange(layout.transient_degree + 1)  # (L, Rt+1)
    transient = np.einsum("pq,ls->plqs", np.eye(P), powers_t)
    shared[..., layout.n_system :] = transient.reshape(P * L, layout.n_transient)
    powers_e = x[:, None] ** np.arange(1, layout.den_degree + 1)  # (L, Re)
    y_win = np.moveaxis(Y, 2, 0)  # (n_y, B, P, L)
    den = -(y_win[..., None] * powers_e).reshape(n_y, B, P * L, layout.den_degree)
    return shared, den, y_win.reshape(n_y, B, P * L)


@dataclass
class _SharedColumns:
    """QR of the (column-equilibrated) columns the output rows share, and
    the complement of its projector."""

    ok: np.ndarray  # (B,) columns nonzero and finite
    Q: np.ndarray  # (B, P L, k1)
    QH: np.ndarray  # (B, k1, P L), Q^H
    diag: np.ndarray  # (B, k1) |R_ii|
    complement: np.ndarray  # (B, P L, P L): I - Q Q^H

    @classmethod
    def of(cls, A):
        norms = np.linalg.norm(A, axis=1)
        ok = np.all(norms > np.finfo(float).tiny, axis=1)
        A_eq = A / np.where(norms > 0, norms, 1.0)[:, None, :]
        ok &= np.all(np.isfinite(A_eq), axis=(1, 2))
        Q, R = np.linalg.qr(A_eq)
        QH = np.conj(np.swapaxes(Q, 1, 2))
        return cls(ok, Q, QH, np.abs(np.diagonal(R, axis1=1, axis2=2)),
                   np.eye(Q.shape[1]) - Q @ QH)


def _noise_levels_of_row(shared, A, b, layout):
    """``(ratio, clamped, cov)`` of one output row from the windows' denominator
    columns ``A`` ``(B, P L, R_e)`` and measured values ``b`` ``(B, P L)``
    (the other columns in ``shared``, a :class:`_SharedColumns`).

    The closed-form fit of every window: the QR of all its columns is that of
    the shared ones (``Q_1 R_11``) followed by the denominator columns
    orthogonalised against ``Q_1`` (twice: orthogonal to round-off) and
    factored (``Q_2 R_22``); ``R_22`` and ``Q_2^H b`` give the denominator
    coefficients, and the residual projector is ``(I - Q_1 Q_1^H) - Q_2
    Q_2^H`` (the first term computed once for the rows)."""
    P, L = layout.n_experiments, layout.window
    norms = np.linalg.norm(A, axis=1)
    ok = shared.ok & np.all(norms > np.finfo(float).tiny, axis=1)
    A_eq = A / np.where(norms > 0, norms, 1.0)[:, None, :]
    ok &= np.all(np.isfinite(A_eq), axis=(1, 2)) & np.all(np.isfinite(b), axis=1)
    # the denominator columns and b orthogonalised against Q_1 (twice)
    k2 = A_eq.shape[2]
    X = np.concatenate([A_eq, b[:, :, None]], axis=2)
    Q1, Q1H = shared.Q, shared.QH
    X -= Q1 @ (Q1H @ X)
    X -= Q1 @ (Q1H @ X)
    Q2, R2 = np.linalg.qr(X[:, :, :k2])
    diag = np.concatenate([shared.diag, np.abs(np.diagonal(R2, axis1=1, axis2=2))],
                          axis=1)
    ok &= diag.min(axis=1) > RANK_TOL * diag.max(axis=1)
    if not ok.any():
        return None
    complement = shared.complement
    if not ok.all():
        Q2, R2, X, norms, complement = Q2[ok], R2[ok], X[ok], norms[ok], complement[ok]
        b = b[ok]
    b1 = X[:, :, k2]  # b - Q_1 Q_1^H b
    Q2H = np.conj(np.swapaxes(Q2, 1, 2))
    Q2H_b = np.einsum("bil,bl->bi", Q2H, b1)
    residual = b1 - np.einsum("bli,bi->bl", Q2, Q2H_b)
    coefficients = np.linalg.solve(R2, Q2H_b[..., None])[..., 0] / norms
    _, x = window_offsets(layout.half_window)
    powers = x[:, None] ** np.arange(1, layout.den_degree + 1)  # (L, Re)
    w = np.tile(np.abs(1.0 + coefficients @ powers.T) ** 2, (1, P))  # |e(x_s)|^2
    B = w.shape[0]
    # the residual projector R = I - Q Q^H, formed entry by entry (its block
    # sums of |R_rs|^2 w_s from products of Q alone lose the small entries
    # of well-fitted rows to cancellation)
    projector = np.matmul(Q2, Q2H)
    np.subtract(complement, projector, out=projector)
    parts = projector.view(np.float64).reshape(B, P, L, P, L, 2)
    # M_k[p, j] = sum_{r in p, s in j} |R_rs|^2 w_s; o_k[p] = ||r_p||^2
    gain = np.einsum("bpljsc,bpljsc,bjs->bpj", parts, parts, w.reshape(B, P, L))
    energy = (np.abs(residual) ** 2).reshape(B, P, L).sum(axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        level = energy.sum(axis=1) / gain.sum(axis=(1, 2))  # pooled, per window
    # windows fitted to round-off (noise-free data) carry no noise level
    exact = energy.sum(axis=1) <= EXACT_RESIDUAL**2 * np.sum(np.abs(b) ** 2, axis=1)
    keep = np.isfinite(level) & (level > 0) & ~exact
    if not keep.any():
        return None
    gain, energy, level = gain[keep], energy[keep], level[keep]
    # each window normalised by its pooled level: E energy_b = gain_b c, and
    # c = G^-1 sum_b energy_b with G = sum_b gain_b
    G_inv = np.linalg.pinv(gain.sum(axis=0))
    ratio = G_inv @ (energy / level[:, None]).sum(axis=0)
    clamped = bool(np.min(ratio) <= 1e-3 * np.max(ratio))
    ratio = np.maximum(ratio, 1e-3 * np.max(ratio))
    ratio /= ratio.mean()
    # The covariance of the (normalised) energies if the levels were equal
    # (complex Gaussian noise of covariance diag(w), the pooled level 1):
    # cov(||r_p||^2, ||r_q||^2) = tr(R D_p R W R D_q R W) = sum_{r in p, s in
    # q} |T_rs|^2 with T = R W R, W = diag(w), D_p experiment p's rows. The
    # residual rows are far from independent (R has rank dof), which the
    # Satterthwaite count over rows of earlier versions ignored: it put the
    # spread of the levels 1.5-11x too low (review30).
    T = np.matmul(projector[keep] * w[keep][:, None, :], projector[keep])
    parts = T.view(np.float64).reshape(-1, P, L, P, L, 2)
    energy_cov = np.einsum("bpljsc,bpljsc->bpj", parts, parts)
    # Each window's energies are divided by its estimated level l = S / g
    # (S = 1^T E, g = 1^T M 1 its pooled gain): n = g E / S. At equal levels
    # E[E] = m = M 1 and E[S] = g; to first order dn = J dE with J = I - m
    # 1^T / g (1^T J = 0: the n sum to g exactly), cov(n) = J C J^T. That
    # term alone is ~0 when m is even across the experiments; the gap is of
    # finite dof: where the residual's direction is independent of its norm
    # (W = I: r = R e isotropic in the range of R), E = S (E / S) gives
    # exactly cov(n) = g^2 cov(E / S) = J C J^T / (1 + v), v = 1^T C 1 / g^2
    # the relative variance of S (the Beta(k, k) variance 1 / (2k + 1) in
    # place of 1 / 2k for two equal experiments). Used for any W; on
    # synthetic windows (benchmarks/noise_level_spread.py) the simulated
    # variance of c_0 - c_1 is 0.99-1.03x of it, 0.78-0.94x of G^-1 C G^-T
    # (the plain quadratic forms, review31) and 0.81-0.95x of J C J^T alone.
    m = gain.sum(axis=2)  # (B, P)
    g = gain.sum(axis=(1, 2))
    J = np.eye(P) - m[:, :, None] / g[:, None, None]
    shrink = 1.0 / (1.0 + energy_cov.sum(axis=(1, 2)) / g**2)
    normalised_cov = np.einsum("bpi,bij,bqj,b->pq", J, energy_cov, J, shrink)
    # at equal levels c = 1 and cov(c) = G^-1 (sum_b J_b C_b J_b^T) G^-T (the
    # windows independent)
    return ratio, clamped, G_inv @ normalised_cov @ G_inv.T


def unequal_noise_rows(levels: ExperimentNoiseLevels | None) -> np.ndarray:
    """Output rows whose experiments' noise levels clearly differ.

    A row is flagged when two of its experiments' estimated variances differ
    by a factor of more than :data:`EQUAL_NOISE_RATIO` and by more than
    :data:`EQUAL_NOISE_Z` standard deviations of their difference at equal
    levels, ``|ratio_p - ratio_q| > Z sqrt(v_pp + v_qq - 2 v_pq)`` with ``v
    = levels.cov``. The difference, a sum of quadratic forms of the noise,
    is tested on the linear scale: its log has heavy tails at few residual
    dof (an estimate near zero).

    Returns
    -------
    ndarray of shape (n_y,), bool
        Empty (shape ``(0,)``) for ``levels`` None.
    """
    if levels is None:
        return np.zeros(0, dtype=bool)
    ratio = levels.ratio
    factor = np.log(ratio)[:, None] - np.log(ratio)[None, :]  # (P, P, n_y)
    v = np.diagonal(levels.cov).T  # (P, n_y)
    scale = np.sqrt(np.maximum(v[:, None] + v[None, :] - 2 * levels.cov, 0.0))
    return np.any((factor > np.log(EQUAL_NOISE_RATIO))
                  & (ratio[:, None] - ratio[None, :] > EQUAL_NOISE_Z * scale),
                  axis=(0, 1))


def experiment_noise_weights(spectra, layout: LocalModelLayout, *,
                             iterations: int = NOISE_WEIGHT_ITERATIONS,
                             stacklevel: int = 2):
    """Weights of a fit on experiments with clearly unequal noise levels.

    Scaling experiment ``p``'s input and output spectra by the same factor
    leaves the system (and the local model class) unchanged and scales its
    noise variance by the square: the weights ``1 / sqrt(ratio)``
    (:func:`experiment_noise_levels`) equalise the levels, so the weighted
    fit's ``"eiv"`` std (which assumes one noise variance per output row)
    is calibrated, and the estimate is the (first-order) best linear one.
    The levels are estimated on the unweighted fit, then again on the
    weighted one (up to ``iterations`` times, until no weight changes by
    more than :data:`WEIGHT_TOL`): the unweighted fit absorbs more of the noisier
    experiments' noise than its first-order expectation, so large ratios
    come out low at first.

    Parameters
    ----------
    spectra : lrmfrf.local_models.OneSidedSpectra
    layout : LocalModelLayout
    iterations : int, default NOISE_WEIGHT_ITERATIONS

    Returns
    -------
    ndarray of shape (P, n_y) or None
        ``1 / sqrt(ratio)`` (``ratio`` of mean 1 over the experiments) in
        the rows :func:`unequal_noise_rows` flags on the unweighted fit,
        exactly 1 in the others; None when no row is flagged (then the
        unweighted fit is unchanged). A flagged row whose levels are not a
        noise estimate keeps weights of 1 (it is fitted pooled) and a
        ``UserWarning`` names it: a level at its lower bound (1e-3 of the
        largest) or no convergence in ``iterations`` (e.g. model misfit
        that differs between the experiments, or experiments that nearly
        repeat each other); the other flagged rows keep their weights (each
        row is its own fit), and None when no row is left weighted. With
        fewer than :data:`MIN_NOISE_LEVEL_DOF` residual dof per window and
        experiment no row is weighted.
    stacklevel : int, default 2
        Of that warning (:meth:`LRMBeyondNyquist.fit` passes its caller's).
    """
    weights, problem = _noise_weights(spectra, layout, iterations)
    if problem is not None:
        siso = layout.n_inputs == 1 and spectra.outputs.shape[1] == 1
        where = "" if siso else f" in output row(s) {problem[0]}"
        # only the rows named are pooled; the other flagged rows keep weights
        fitted = ("fitted" if siso else
                  "that row is fitted" if len(problem[0]) == 1 else
                  "those rows are fitted")
        if layout.dof < MIN_NOISE_LEVEL_DOF * layout.n_experiments:
            # too few residual dof: not misfit, and higher local degrees
            # would take dof away
            text = (f"The experiments' residual levels{where} differ, but "
                    f"with {problem[1]}, they are no noise estimate: {fitted} "
                    "with one pooled noise level, as for equal noise. Raise "
                    "half_window or lower the local degrees to weight the "
                    "experiments.")
        else:
            text = (f"The experiments' residual levels{where} "
                    f"differ in a way noise alone does not explain ({problem[1]}; "
                    "model misfit that differs between the experiments, e.g. one "
                    f"with an input missing?): {fitted} with one pooled noise "
                    "level, as for equal noise. Raise the local degrees "
                    "or half_window, or check the experiments.")
        warnings.warn(text, UserWarning, stacklevel=stacklevel)
    return weights


def _noise_weights(spectra, layout, iterations, diagnostics=None):
    """``(weights, problem)`` of :func:`experiment_noise_weights`:
    ``problem`` None, or (rows, reason) when flagged rows are left
    unweighted. ``diagnostics`` (a dict) receives the intermediate values."""
    levels = experiment_noise_levels(spectra, layout)
    unequal = unequal_noise_rows(levels)
    if diagnostics is not None:
        diagnostics["levels"] = [levels]
    if not unequal.any():
        return None, None
    rows = np.flatnonzero(unequal).tolist()
    P = layout.n_experiments
    if layout.dof < MIN_NOISE_LEVEL_DOF * P:
        return None, (rows, f"{layout.dof} residual degrees of freedom per "
                            f"window, fewer than {MIN_NOISE_LEVEL_DOF} per "
                            "experiment")
    weights = np.where(unequal[None, :], 1.0 / np.sqrt(levels.ratio), 1.0)
    settled = np.zeros(unequal.shape, dtype=bool)
    for _ in range(iterations):
        levels = experiment_noise_levels(spectra, layout, weights=weights)
        if diagnostics is not None:
            diagnostics["levels"].append(levels)
        new = np.where(unequal[None, :], 1.0 / np.sqrt(levels.ratio), 1.0)
        settled = np.max(np.abs(new / weights - 1.0), axis=0) < WEIGHT_TOL
        weights = new
        if settled.all():
            break
    if diagnostics is not None:
        diagnostics["converged"] = bool(settled.all())
    # each output row is its own fit: a row whose levels are not a noise
    # estimate is fitted pooled, the other flagged rows keep their weights
    clamped = unequal & levels.clamped
    unsettled = unequal & ~settled & ~clamped
    if not (clamped.any() or unsettled.any()):
        return weights, None
    reasons = []
    if clamped.any():
        reasons.append("an experiment's level estimate at its lower bound"
                       + _in_rows(clamped, unequal))
    if unsettled.any():
        reasons.append(f"the level estimate did not settle in {iterations} "
                       "re-estimations" + _in_rows(unsettled, unequal))
    refused = clamped | unsettled
    weights[:, refused] = 1.0
    problem = (np.flatnonzero(refused).tolist(), "; ".join(reasons))
    return (None if refused.sum() == unequal.sum() else weights), problem


def _in_rows(rows: np.ndarray, flagged: np.ndarray) -> str:
    """" in row(s) [...]" where only some of the flagged rows are meant."""
    if rows.sum() == flagged.sum():
        return ""
    return f" in row(s) {np.flatnonzero(rows).tolist()}"
