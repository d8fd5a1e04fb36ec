"""Local rational (LRM) and local polynomial (LPM) estimators beyond Nyquist.

Both are thin shells over :func:`lrmfrf.local_models.fit_local_models`: LPM is
the same computation with ``den_degree = 0``.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from .._validation import (
    check_bool,
    check_local_degrees,
    check_nonnegative_int,
    check_nonnegative_int_or_none,
    check_positive_float,
    check_records,
    check_sample_time,
)
from ..exceptions import IdentifiabilityWarning
from ..local_models import (
    NEAR_DEPENDENCE_TOL,
    OneSidedSpectra,
    _fast_grid_runs,
    _joined_fits,
    _rescaled_theta,
    experiments_needed,
    fast_grid_targets,
    fit_local_models,
    half_slow_bins,
    nearly_dependent_windows,
    one_sided_fast_grid,
    rescale_local_fit,
    scale_by_power_of_two,
)
from ..refinement import (
    emit_refinement_warnings,
    pool_summaries,
    refine_local_models,
    result_summary,
)
from ..solvers import resolve_backend
from ..uncertainty import (
    DEFAULT_STD_METHOD,
    calibrated_local_fit,
    calibrated_refined_fit,
    check_std_method,
    cross_row_covariance,
    experiment_noise_weights,
    iter_calibrated_fit_rows,
    keeps_lemma2,
)
from ..windows import LocalModelLayout
from ._base import _BaseFRFEstimator, _normalise_in_place

__all__ = ["LRMBeyondNyquist", "LPMBeyondNyquist"]

logger = logging.getLogger(__name__)


_HALF_WINDOW = partial(check_nonnegative_int, minimum=1)


class _LocalModelEstimator(_BaseFRFEstimator):
    """Common ``fit`` of the local-model estimators (LRM, LPM)."""

    def _local_degrees(self, params: dict) -> tuple[dict, dict]:  # pragma: no cover
        """The four local-model settings from the checked parameters, and how
        the estimator names them in messages (None: not a parameter)."""
        raise NotImplementedError

    def _refines(self, params: dict) -> bool:
        """Whether ``fit`` refines the closed form (:meth:`_refine`)."""
        return False

    def _reset_refinement(self) -> None:
        """Hook: the fitted attributes of refinement, before any is run."""

    def _refine(self, U, Y, layout, local_fit, params: dict, y_exponent: int):
        """Hook for iterative refinement; the closed form by default.

        ``U``, ``Y`` and ``local_fit`` are normalised (see ``fit``); costs
        stored on the estimator are scaled back by ``2**(2*y_exponent)``.
        """
        return local_fit

    @property
    def local_fit_(self):
        """Per-slow-bin results (see the class docstring).

        A closed-form fit stores only what computes them
        (``_local_fit_source_``: the one-sided DFTs of the normalised records,
        the layout, the normalisation exponents and the backend of the fit);
        the first access runs :func:`lrmfrf.local_models.fit_one_sided` per
        output row, which gives the results of the fit bit for bit, keeps
        them and releases the spectra.
        """
        fit = self.__dict__.get("_local_fit_cache_")
        if fit is None:
            source = self.__dict__.get("_local_fit_source_")
            if source is None:
                raise AttributeError(
                    f"{type(self).__name__!r} object has no attribute 'local_fit_' "
                    "(call fit first)"
                )
            fit = source.compute()
            self._local_fit_cache_, self._local_fit_source_ = fit, None
        return fit

    @local_fit_.setter
    def local_fit_(self, value) -> None:
        self._local_fit_cache_, self._local_fit_source_ = value, None

    @property
    def frf_joint_cov_(self):
        """Covariance of all entries of a bin, between output rows too.

        ``frf_joint_cov_[o, i, p, j, k] = E[dG_oi(k) conj(dG_pj(k))]``, shape
        (n_y, n_u, n_y, n_u, K), complex; the blocks ``o == p`` are
        ``frf_cov_``. The rows of a MIMO fit are separate local problems, but
        noise that is correlated between the outputs (fed back through a
        controller: :func:`lrmfrf.plant_from_closed_loop` reads this)
        correlates their estimates; the blocks between rows follow from the
        rows' residuals in the same windows
        (:func:`lrmfrf.uncertainty.cross_row_covariance`, route ``"eiv"``, or
        ``"lemma2"`` with that ``std_method``).

        Computed on first access, then kept: the closed form is solved again
        from the stored spectra (``local_fit_``) and the rows' projections
        formed in numpy: about twice the fit's time on short records (3x2,
        P = 2, F = 3, M = 400: 0.74 s against 0.34 s), but about 20x on long
        ones, whose fit is compiled (M = 40000: 33 s against 1.6 s); the
        spectra, about the
        size of the records, are kept until then, also after ``local_fit_``.
        ``None`` for fits whose ``frf_cov_`` is not of the
        closed form's ``"eiv"`` or ``"lemma2"`` route (refined fits, other
        ``std_method``): the rows are then taken as independent.
        """
        if "_frf_joint_cov_cache_" in self.__dict__:
            return self._frf_joint_cov_cache_
        if not hasattr(self, "frf_cov_"):
            raise AttributeError(
                f"{type(self).__name__!r} object has no attribute "
                "'frf_joint_cov_' (call fit first)"
            )
        cov = self.frf_cov_
        n_y, n_u = cov.shape[:2]
        source = self.__dict__.get("_joint_cov_source_")
        if n_y == 1:
            joint = cov[:, :, None]  # (1, n_u, 1, n_u, K), a view
        elif source is None:
            joint = None
        else:
            joint = _joint_covariance(source, self.local_fit_, cov)
        self._frf_joint_cov_cache_, self._joint_cov_source_ = joint, None
        return joint

    def fit(self, u_h, y_l, F, *, sample_time: float = 1.0):
        """Estimate the fast-rate FRF from a fast input and a slow output.

        Parameters
        ----------
        u_h : array-like of shape (N,), (n_u, N) or (P, n_u, N), or list
            Fast-rate input(s), real: one record (1-D, or 2-D with channels
            first) or ``P`` experiments (3-D, or a list of 1-D/2-D records).
            A 2-D array is ONE record: several SISO experiments go in a list
            or a (P, 1, N) array.
        y_l : array-like of shape (M,), (n_y, M) or (P, n_y, M), or list
            Slow-rate output(s) likewise, real, ``y_l(m) = y_h(m F) + noise``.
        F : int
            Downsampling factor, ``N = F M``.
        sample_time : float, default=1.0
            Fast sample time in seconds (sets ``frequencies_`` in Hz). With
            the default 1.0, time is counted in samples and ``frequencies_``
            and ``slow_frequencies_`` are in cycles per (fast) sample, from 0
            to 0.5.

        Returns
        -------
        self
            The fitted estimator.

        Raises
        ------
        TypeError, ValueError
            For a parameter out of range, signals that are not real, finite,
            non-empty records of equal length in the record convention,
            ``N != F M``, a window wider than the slow record, or fewer
            equations than parameters (the message names the smallest half
            window, or the number of experiments, that would do).

        Warns
        -----
        IdentifiabilityWarning
            Once, when some local problems are rank-deficient (an input that
            does not excite every aliased band): those bins are NaN with
            ``valid_ == False``. Once more when the windows need several
            experiments and in some of them the experiments' inputs are
            nearly linearly dependent (differ by less than about 2 % for two
            experiments, about 3 % for three nearly equal ones, e.g. one
            excitation repeated with a noisy input sensor) or some have no
            input there: those bins are NaN
            with ``valid_ == False`` too
            (:func:`lrmfrf.local_models.nearly_dependent_windows`).

        Notes
        -----
        The FRF is a ratio, so the result does not depend on the units of
        ``u_h`` and ``y_l``: records whose largest magnitude is outside
        ``2**-64 .. 2**64`` (about 5e-20 .. 1.8e19) are divided by a power of
        two before the DFT, which is exact, and the results are multiplied
        back (``frf_`` and ``frf_std_`` by the output-to-input factor,
        ``transient_`` by the output factor, ``noise_variance_`` and costs by
        its square, ``local_fit_`` likewise). Any finite scale thus gives the
        same FRF; ordinary records are not touched (bit-identical results).
        A variance whose value exceeds the float range (e.g. the noise
        variance of an output of 1e160) is inf.
        """
        params = self._checked_params()
        records = check_records(u_h, y_l, F)
        F = records.F
        sample_time = check_sample_time(sample_time)
        P, n_u, N = records.u.shape
        n_y, M = records.n_outputs, records.n_slow
        local_degrees, names = self._local_degrees(params)
        # The FRF is a ratio: fit on records normalised by powers of two
        # (exact; none for ordinary data) and undo it on the results.
        u, y = records.u, records.y  # new arrays: check_records copies
        u_exponent = _normalise_in_place(u)
        y_exponent = _normalise_in_place(y)
        # real records: one-sided DFTs (half the memory, the same values)
        spectra = OneSidedSpectra.from_records(u, y, F)
        # the degrees after the DFTs: the count of independent experiments
        # reads the input spectra (no second DFT)
        degrees = check_local_degrees(
            **local_degrees, F=F, n_slow=M, n_experiments=P,
            parameter_names=names, n_inputs=n_u, hint=records.hint(),
            n_independent=records.independent_experiments(spectra.inputs),
        )
        layout = LocalModelLayout(F=F, n_experiments=P, n_inputs=n_u, **degrees)
        del u, y, records
        # windows whose experiments are nearly dependent (None: none can be,
        # e.g. one experiment or a window that one experiment fills)
        near = nearly_dependent_windows(spectra, layout)
        if near is not None and not near.any():
            near = None
        # experiments with clearly unequal noise levels (per output row; SISO
        # and MIMO, P > 1): those rows are fitted on experiments weighted to
        # equal levels (None: the levels agree, or one experiment: the
        # unweighted fit)
        # (not when every window is nearly dependent: nothing is fitted)
        weights = None
        if near is None or not near.all():
            weights = experiment_noise_weights(spectra, layout, stacklevel=3)
        self._reset_refinement()
        refines = self._refines(params)
        std_method = params.get("std_method", "lemma2")
        # refinement and the std routes of lrmfrf.uncertainty other than
        # Lemma 2 and eiv need the whole per-window fit: not streamed
        whole = refines or std_method not in ("lemma2", "eiv")
        # the streamed eiv fit computes its terms with the solve (a dearer
        # numpy window); a whole fit solves the closed form alone here (its
        # std and refinement choose their own backends)
        backend = resolve_backend(
            "auto", M // 2 + 1, layout.n_params,
            eiv=not whole and not keeps_lemma2(std_method, layout),
        )
        if whole:
            U = spectra.full_inputs()  # (P, n_u N): the F n_u bands
            self._refined_rows = []  # refinement summaries, one per output row
            self._refinements = []  # their results, for one set of warnings
            fits = []
            for o in range(n_y):  # one local problem (one denominator) per row
                Y_o = spectra.full_outputs(o)
                U_o = U
                if weights is not None and np.any(weights[:, o] != 1.0):
                    U_o, Y_o = U * weights[:, o, None], Y_o * weights[:, o, None]
                local_fit = fit_local_models(
                    U_o, Y_o, layout, return_cov=True, backend=backend
                )
                if refines:  # linearised variance, at the eiv noise level
                    # nearly dependent windows end invalid: not refined (work
                    # and warnings of windows whose values are dropped)
                    local_fit = _invalidated(local_fit, near)
                    fit = self._refine(U_o, Y_o, layout, local_fit, params,
                                       y_exponent)
                    fit = calibrated_refined_fit(U_o, Y_o, layout, local_fit, fit,
                                                 std_method)
                else:  # closed form: the std route (lrmfrf.uncertainty)
                    fit = calibrated_local_fit(U_o, Y_o, layout, local_fit,
                                               std_method)
                fits.append(_unweighted(fit, weights, o))
            if self._refinements:  # at the caller of fit, naming the rows
                emit_refinement_warnings(self._refinements)
            del U, U_o, self._refined_rows, self._refinements
            chunks = [(0, range(n_y), fits)]
        else:  # streamed, all output rows at once: no per-window parameters kept
            chunks = _iter_weighted_fit_rows(spectra, layout, std_method, backend,
                                             weights)
        try:
            self._set_fitted(chunks, layout, N, M, F, P, n_y, sample_time,
                             u_exponent, y_exponent, near)
        finally:
            if not whole:
                # the generator holds a single-threaded-BLAS section while
                # suspended: an exception here (e.g. KeyboardInterrupt) would
                # keep it, and BLAS on one thread, as long as its traceback
                chunks.close()
        if whole:
            fits = [rescale_local_fit(_invalidated(fit, near), u_exponent,
                                      y_exponent) for fit in fits]
            self.local_fit_ = fits[0] if n_u == n_y == 1 else fits
        else:
            self._local_fit_cache_ = None
            self._local_fit_source_ = _LocalFitSource(
                spectra, layout, u_exponent, y_exponent, backend, std_method,
                near, weights,
            )
        weights = np.ones((P, n_y)) if weights is None else weights.copy()
        # SISO: no output axis, as noise_variance_ and transient_
        self.noise_weights_ = weights[:, 0] if n_u == n_y == 1 else weights
        # frf_joint_cov_ on first access (streamed closed forms: eiv, Lemma 2)
        self.__dict__.pop("_frf_joint_cov_cache_", None)
        self._joint_cov_source_ = (self._local_fit_source_
                                   if not whole and n_y > 1 else None)
        return self

    def _set_fitted(
        self, chunks, layout, N, M, F, P, n_y, sample_time, u_exponent, y_exponent,
        near=None,
    ) -> None:
        """Set the fitted attributes from the local fits of each output row.

        ``chunks`` yields ``(start, rows, fits)``: ``fits[i]`` the
        (normalised) results of slow bins ``start..`` of output row
        ``rows[i]`` (all of them at once, or chunk by chunk from
        :func:`lrmfrf.local_models.iter_local_fit_rows`); they are written
        into the outputs, allocated once, and not kept.
        """
        n_u = layout.n_inputs
        siso = n_u == 1 and n_y == 1
        K, B = N // 2 + 1, M // 2 + 1
        self.frequencies_ = np.arange(K, dtype=float)
        self.frequencies_ /= N * sample_time
        out = _FittedArrays(
            frf=np.empty((n_y, n_u, K), dtype=complex),
            std=np.empty((n_y, n_u, K)),
            cov=np.empty((n_y, n_u, n_u, K), dtype=complex),
            valid=np.empty((n_y, n_u, K), dtype=bool),
            noise=np.empty((n_y, B)),
            transient=np.empty((P, n_y, B), dtype=complex),
        )
        n_bad = n_unexcited = 0
        for start, rows, fits in chunks:
            # (the fast bins of the chunk's slow bins: the same for every row)
            runs = _fast_grid_runs(start, start + fits[0].slow_bins.size, N, F)
            for o, fit in zip(rows, fits, strict=True):
                bad = ~fit.well_posed
                if near is not None:  # not refined (whole fits): warned below
                    bad = bad & ~near[fit.slow_bins]
                n_bad += int(np.count_nonzero(bad))
                # (not excited: not well posed either)
                n_unexcited += int(np.count_nonzero(~fit.excited & bad))
                out.write(o, start, fit, N, F, u_exponent, y_exponent, runs)
        if n_bad:
            rows_note = " (over all output rows)" if n_y > 1 else ""
            bad_fast = ~out.valid[:, 0]
            if near is not None:  # the fast bins of the windows counted here
                bad_fast = bad_fast & ~one_sided_fast_grid(
                    np.repeat(near[:, None], F, axis=1), N, F, conj=False)
            msg = (
                f"{n_bad} of {n_y * B} slow bins{rows_note} "
                f"({np.count_nonzero(bad_fast)} of {n_y * K} fast bins of "
                "frf_) are not identifiable: their local problem is rank-deficient "
                f"({n_unexcited} of them because the input has no energy in some "
                "aliased band of the window). Their FRF is NaN and valid_ is "
                "False. Use an input that excites every band, e.g. a random-phase "
                "multisine (lrmfrf.signals.multisine)."
            )
            if n_u > 1 and n_bad > n_unexcited:
                msg += (
                    f" With {n_u} inputs, inputs that are linearly dependent "
                    "(e.g. one a multiple of another), or a band excited at too "
                    "few bins of the window (e.g. at the edge of a band-limited "
                    "input), leave the problem rank-deficient too: excite the "
                    "inputs independently over the whole band "
                    "(lrmfrf.signals.orthogonal_multisines)."
                )
            warnings.warn(msg, IdentifiabilityWarning, stacklevel=3)
        if near is not None:
            out.invalidate(near, N, F)
            _warn_nearly_dependent(near, layout, M)
        if layout.dof == 0:
            warnings.warn(
                "The local problems have zero residual degrees of freedom: the "
                "noise variance and frf_std_ are NaN. Increase half_window.",
                UserWarning,
                stacklevel=3,
            )
        self.n_samples_ = N
        self.n_slow_ = M
        self.n_experiments_ = P
        self.n_inputs_ = n_u
        self.n_outputs_ = n_y
        self.downsampling_factor_ = F
        self.sample_time_ = sample_time
        self.n_params_ = layout.n_params
        self.dof_ = layout.dof
        self.layout_ = layout
        self.frf_cov_ = out.cov
        self.frf_ = out.frf[0, 0] if siso else out.frf
        self.frf_std_ = out.std[0, 0] if siso else out.std
        self.valid_ = out.valid[0, 0] if siso else out.valid
        self.slow_frequencies_ = np.arange(B) / (N * sample_time)
        if siso:
            self.noise_variance_ = out.noise[0]
            self.transient_ = (
                out.transient[0, 0] if P == 1 else out.transient[:, 0]
            )
        else:
            self.noise_variance_ = out.noise
            self.transient_ = out.transient
        logger.debug(
            "%s fitted: N=%d, F=%d, P=%d, n_u=%d, n_y=%d, %d params, %d dof, %d "
            "invalid bins", type(self).__name__, N, F, P, n_u, n_y,
            layout.n_params, layout.dof, n_bad,
        )

    def _fast_frf(self, n_samples: int) -> np.ndarray:
        half = self.frf_
        mirror = np.conj(half[..., 1 : n_samples - n_samples // 2][..., ::-1])
        return np.concatenate([half, mirror], axis=-1)


class LRMBeyondNyquist(_LocalModelEstimator):
    """Local rational modelling beyond the Nyquist frequency (closed form).

    Identifies the fast-rate FRF ``G(k)``, ``k = 0..N//2``, from a fast input
    and a slow output downsampled by ``F``, with local rational models over
    the ``F`` aliased bands: eqs. (Kvector), (linearSolution) and
    (linearPlantSolution) of van Haren et al., with variance from Lemma 2.
    ``F = 1`` is the single-rate LRM of McKelvey and Guerin (2012).

    Parameters
    ----------
    half_window : int, default=18
        ``n``: each local window holds ``2n+1`` slow bins.
    num_degree : int, default=4
        ``R_g``: degree of the system numerators.
    transient_degree : int, default=4
        ``R_t``: degree of the transient numerator.
    den_degree : int, default=7
        ``R_e``: degree of the common denominator.
    sk_iterations : int, default=0
        Maximum Sanathanan-Koerner iterations after the closed form
        (eq. LinearizedCostFunctionSK), e.g. 30. ``0`` with
        ``lm_iterations=0`` gives the closed form exactly.
    lm_iterations : int, default=0
        Maximum Levenberg-Marquardt iterations on the original cost
        eq. (CostFunction) after SK, e.g. 300.
    tol : float, default=1e-6
        A window stops iterating when its cost changes by less than ``tol``
        (relative) in an iteration.
    guard : float or None, default=0.5
        Guard radius in slow bins: a refined iterate whose denominator gets a
        root within ``guard`` bins of the window centre is rejected and the
        window falls back to its last good estimate. ``None`` disables it.
    jump : float or None, default=5.0
        A refined iterate whose FRF moves more than ``jump`` closed-form
        standard deviations away from the closed form is rejected likewise.
        ``None`` disables it.
    verbose : bool, default=False
        Show a progress bar over the chunks of windows during refinement
        (long records; needs tqdm).
    std_method : {"eiv", "lemma2", "hc", "eiv_pooled", "eiv_dof", "eiv_robust"}, \
default="eiv"
        How ``frf_std_`` and ``frf_cov_`` of the closed form are computed
        (:mod:`lrmfrf.uncertainty`, ``docs/method.md`` section 5).
        ``"eiv"``: the errors-in-variables sandwich, whose equation noise is
        the output noise times the local denominator, with the noise variance
        from the residual over its expected size (about 1.0x the Monte-Carlo
        std on random stages); compiled (numba) and streamed chunk by chunk
        like the closed form, at about 2-3x its time. ``"lemma2"``: the
        paper's eq. (Variance) (about 0.76-0.91x), the earlier default and
        the fastest. ``"hc"``, ``"eiv_pooled"``, ``"eiv_dof"``: the other
        routes studied (numpy, on the whole per-window fit). ``"eiv_robust"``:
        bias-aware (whole record, per output row): the noise level of each
        window the median of its neighbours' (its own where that is over
        twice the median: model misfit), plus the squared disagreement with
        the neighbouring windows' local models where it stands out; about
        96-97 % 2-std coverage at 1.00-1.04x the Monte-Carlo std where
        ``"eiv"`` covers 94-95 % (``benchmarks/coverage_bias_study.py``,
        route ``switch2+nbr_c4``; F = 2 at 30 dB: 95.8 %, F = 5 at 70 dB:
        ratio 1.07). Refined fits
        (``sk_iterations``, ``lm_iterations``) keep the shape of their
        linearised variance; with ``"eiv"`` it is scaled to the closed form's
        errors-in-variables noise variance of the same window
        (:func:`lrmfrf.uncertainty.calibrated_refined_fit`), with the other
        routes it is the refinement's own (``"eiv_robust"`` is for the closed
        form only: an error with refinement).

    Attributes
    ----------
    frequencies_ : ndarray of shape (N//2+1,)
        Fast DFT grid ``k / (N T_s)`` in Hz, ``k = 0..N//2``; in cycles per
        sample (``k / N``) when ``fit`` got no ``sample_time`` (default 1.0).
    frf_ : ndarray of shape (N//2+1,), complex
        Estimated FRF ``G(k)`` from ``u_h`` to ``y_h`` (units of ``y_l`` per
        unit of ``u_h``); NaN where ``valid_`` is False. With ``n_u`` inputs
        or ``n_y`` outputs (not both 1): shape (n_y, n_u, N//2+1), entry
        ``[o, i]`` from input ``i`` to output ``o``. Each output row is one
        local problem per window: the local models of all inputs over all
        ``F`` bands with one denominator and one transient per experiment.
    frf_std_ : ndarray of shape (N//2+1,) or (n_y, n_u, N//2+1)
        Standard deviation of ``frf_``, ``sqrt(E|G_hat - G|^2)``, from the
        route ``std_method`` (the errors-in-variables sandwich by default,
        Lemma 2 with ``std_method="lemma2"``).
    frf_cov_ : ndarray of shape (n_y, n_u, n_u, N//2+1), complex
        Always 4-D: ``E[dG_oi conj(dG_oj)]`` between the entries of one output
        row at each fast bin (route ``std_method`` per output row); ``frf_std_ ==
        sqrt(real(diagonal))``. Cross-band covariances are not kept;
        cross-output ones are ``frf_joint_cov_``.
    frf_joint_cov_ : ndarray of shape (n_y, n_u, n_y, n_u, N//2+1), complex, or None
        ``E[dG_oi conj(dG_pj)]`` between all entries of a fast bin, output
        rows too (noise correlated between the outputs, e.g. fed back in a
        loop, correlates the rows' estimates); the blocks ``o == p`` are
        ``frf_cov_``. Computed on first access (2x the fit's time at M = 400,
        20x at M = 40000;
        :func:`lrmfrf.plant_from_closed_loop` reads it); None for
        refined fits and ``std_method`` other than ``"eiv"`` and
        ``"lemma2"``.
    valid_ : ndarray of shape (N//2+1,) or (n_y, n_u, N//2+1), bool
        False where the local problem was not well posed (``frf_`` is NaN);
        the same for all inputs of an output row.
    slow_frequencies_ : ndarray of shape (M//2+1,)
        Slow window centres in Hz.
    noise_variance_ : ndarray of shape (M//2+1,) or (n_y, M//2+1)
        Per output row (MIMO). The paper's residual estimate of the variance
        of the slow output noise DFT ``V_l(k)``: ``||Y - Theta K||^2 /
        dof_`` of the weighted problem. With ``den_degree > 0`` the output
        sits in the regressor (errors-in-variables) and the fit absorbs part
        of the noise, so this is biased low (on pure noise about 0.3x for
        R_e = 7). It estimates the variance of the weighted equation error
        ``e(x) V_l``; ``frf_std_`` (``std_method="eiv"``) uses its own
        estimate of the variance of ``V_l`` (:mod:`lrmfrf.uncertainty`).
        In an output row whose experiments are weighted (``noise_weights_``)
        it is the variance of the weighted records' noise: about the mean of
        the experiments' levels.
    noise_weights_ : ndarray of shape (P,) or (P, n_y)
        Weight of each experiment in the fit of each output row (SISO: of
        the one row, no output axis, as ``transient_``): 1 unless the
        experiments' noise levels in a row clearly differ (``P > 1``; by more
        than 1.5x in variance and well beyond the spread of their estimate,
        :func:`lrmfrf.uncertainty.experiment_noise_weights`). Then that row
        is fitted on the experiments' inputs and outputs both scaled by ``1 /
        sqrt(level / mean level)`` (the FRF is unchanged, the noise levels
        equalised), so that ``frf_std_``, which assumes one noise level per
        row, is calibrated, and the noisier experiments count less. Without
        it the std was 0.61-0.81x the Monte-Carlo std on some MIMO entries
        and up to 5.9x on others when one input was excited at a time, and
        0.55-0.75x on SISO records whose experiments had inputs 4-10x apart
        in RMS, each at its own SNR (``benchmarks/unequal_noise.py``,
        ``--siso``). ``P = 1``: all ones. All ones too in a row whose levels
        differ in a way noise does not explain (the estimate at its bound or
        not settling; e.g. model misfit that differs between the
        experiments), with a ``UserWarning`` naming the row: that row is the
        pooled fit, the other rows keep their weights; in every row when
        there are too few residual dof.
    transient_ : ndarray of shape (M//2+1,) or (P, M//2+1), complex
        Transient term in the slow output DFT at each window centre; (P, n_y,
        M//2+1) when not SISO.
    n_params_ : int
        Complex parameters per local problem (per output row),
        ``(R_g+1) F n_u + P (R_t+1) + R_e``.
    dof_ : int
        Residual degrees of freedom per local problem, ``P (2n+1) - n_params_``.
    n_samples_, n_slow_, n_experiments_ : int
        ``N``, ``M`` and ``P`` of the training records.
    n_inputs_, n_outputs_ : int
        ``n_u`` and ``n_y``.
    downsampling_factor_ : int
        ``F``.
    sample_time_ : float
        Fast sample time in seconds.
    layout_ : lrmfrf.windows.LocalModelLayout
        Sizes and column order of the local problems.
    local_fit_ : lrmfrf.local_models.LocalModelFit or list of them
        Per-slow-bin results (parameters, band values, variances); a list of
        ``n_y`` fits, one per output row, when not SISO (band ``b = i F + f``
        is input ``i``, see :func:`lrmfrf.windows.band_indices`). For the
        closed form it is computed on first access (the same closed form
        again, from the one-sided DFTs of the training records that the
        estimator keeps until then, about the size of the records) and then
        kept: ``fit`` streams the windows into the other attributes without
        holding the ``(M//2+1, n_params_)`` parameters (0.86 GiB at ``N =
        1.2e7``). After refinement it is the refined fit, kept from ``fit``.
    cost_history_ : ndarray of shape (1 + n_sk_iter_ + n_lm_iter_,) or None
        Mean over the slow bins of the original least-squares cost
        (eq. meanCosts, ``mu_OE``) after the closed form and after each SK,
        then each LM iteration; None without refinement.
    sk_cost_history_ : ndarray of shape (1 + n_sk_iter_,) or None
        Mean SK cost ``mu_SK`` (the closed form's weighted cost first).
    n_sk_iter_, n_lm_iter_ : int
        Iterations run (fewer than requested when every window converged).
    n_guarded_ : int
        Slow bins where the guard rejected a refined iterate.

    Notes
    -----
    Iterative refinement (SK, LM) refines each output row's local problems
    (for MIMO data the histories pool the windows of all rows, ``n_guarded_``
    counts them all). After refinement, ``frf_std_`` is linearised at the
    final estimate (SK: Lemma 2 on the reweighted regressor; LM:
    ``(J^H J)^-1``), with the noise variance ``J_LS / dof_`` for
    ``std_method="lemma2"`` and the closed form's errors-in-variables noise
    variance for the default ``"eiv"``. Iterative refinement is implemented in
    :mod:`lrmfrf.refinement`. On the simulated wafer stage at 45 dB
    (``benchmarks/refinement.py``, 100 runs) SK 30 lowered the mean cost by
    about 84 % and the median FRF error by about 9 %; adding LM 300 lowered
    the cost further (to about 13 %) but fitted noise and raised the median
    error by 12-15 % over the closed form, so SK alone is recommended. With
    the refinement's own noise level (``std_method="lemma2"``) the
    linearised ``frf_std_`` is about 0.90x the Monte-Carlo std after SK and
    0.77x after LM (LM's fit absorbs part of the noise, so its residual
    underestimates it); at the closed form's errors-in-variables noise level
    (the default) it measured 0.93-0.98x on random stages
    (``benchmarks/generalisation_std.py --refined``).

    References
    ----------
    M. van Haren, L. Blanken, K. Classens, T. Oomen, "Local Rational Modeling
    for Identification Beyond the Nyquist Frequency: Applied to a Prototype
    Wafer Stage", 2024.

    Examples
    --------
    >>> import numpy as np
    >>> from scipy.signal import lfilter
    >>> from lrmfrf import LRMBeyondNyquist
    >>> from lrmfrf.signals import multisine
    >>> u = multisine(1200, rng=0)
    >>> y = lfilter([0.2, 0.1], [1.0, -0.5], u)[::3]
    >>> est = LRMBeyondNyquist(den_degree=2).fit(u, y, F=3)
    >>> est.frf_.shape, est.noise_variance_.shape, bool(est.valid_.all())
    ((601,), (201,), True)
    >>> bool(est.score(u, y) > 0.999)  # R^2 of the predicted slow output
    True
    >>> est.to_frd().omega.shape  # control.FrequencyResponseData, rad/s
    (601,)
    """

    _parameter_checks = {
        "half_window": _HALF_WINDOW,
        "num_degree": check_nonnegative_int,
        "transient_degree": check_nonnegative_int,
        "den_degree": check_nonnegative_int,
        "sk_iterations": check_nonnegative_int,
        "lm_iterations": check_nonnegative_int,
        "tol": partial(check_positive_float, allow_none=False),
        "guard": partial(check_positive_float, allow_none=True),
        "jump": partial(check_positive_float, allow_none=True),
        "verbose": check_bool,
        "std_method": check_std_method,
    }

    def __init__(
        self,
        *,
        half_window: int = 18,
        num_degree: int = 4,
        transient_degree: int = 4,
        den_degree: int = 7,
        sk_iterations: int = 0,
        lm_iterations: int = 0,
        tol: float = 1e-6,
        guard: float | None = 0.5,
        jump: float | None = 5.0,
        verbose: bool = False,
        std_method: str = DEFAULT_STD_METHOD,
    ):
        self.half_window = half_window
        self.num_degree = num_degree
        self.transient_degree = transient_degree
        self.den_degree = den_degree
        self.std_method = std_method
        self.sk_iterations = sk_iterations
        self.lm_iterations = lm_iterations
        self.tol = tol
        self.guard = guard
        self.jump = jump
        self.verbose = verbose

    def _checked_params(self) -> dict:
        """As the base class; ``std_method="eiv_robust"`` is for the closed
        form only (refined fits would keep their own noise level)."""
        params = super()._checked_params()
        if params["std_method"] == "eiv_robust" and self._refines(params):
            raise ValueError(
                "std_method='eiv_robust' is computed from the closed form's "
                "local models and is not defined for refined fits; got "
                f"sk_iterations={params['sk_iterations']} and lm_iterations="
                f"{params['lm_iterations']}. Use std_method='eiv' with "
                "refinement, or sk_iterations=0 and lm_iterations=0."
            )
        return params

    def _local_degrees(self, params: dict) -> tuple[dict, dict]:
        degrees = {
            "half_window": params["half_window"],
            "num_degree": params["num_degree"],
            "transient_degree": params["transient_degree"],
            "den_degree": params["den_degree"],
        }
        return degrees, {}

    def _refines(self, params: dict) -> bool:
        return bool(params["sk_iterations"] or params["lm_iterations"])

    def _reset_refinement(self) -> None:
        self.n_sk_iter_ = self.n_lm_iter_ = self.n_guarded_ = 0
        self.cost_history_ = self.sk_cost_history_ = None

    def _refine(self, U, Y, layout, local_fit, params: dict, y_exponent: int):
        sk, lm = params["sk_iterations"], params["lm_iterations"]
        result = refine_local_models(  # fit warns once for all the rows
            U, Y, layout, local_fit, sk_iterations=sk, lm_iterations=lm,
            tol=params["tol"], guard=params["guard"], jump=params["jump"],
            keep_best=True, chunk_size=None, verbose=params["verbose"],
            warn=False,
        )
        self._refinements.append(result)
        self._refined_rows.append(result_summary(result))
        pooled = pool_summaries(self._refined_rows)  # the rows fitted so far
        self.cost_history_ = scale_by_power_of_two(
            pooled["cost_history"], 2 * y_exponent
        )
        self.sk_cost_history_ = scale_by_power_of_two(
            pooled["sk_cost_history"], 2 * y_exponent
        )
        self.n_sk_iter_ = pooled["sk_iterations"]
        self.n_lm_iter_ = pooled["lm_iterations"]
        self.n_guarded_ = pooled["n_guarded"]
        return result.local_fit


#: Default of a deprecated parameter: "not passed" (scikit-learn's pattern).
_DEPRECATED = "deprecated"


def _check_deprecated_degree(value, name: str):
    """LPM's old ``degree``: the sentinel, or a degree checked as ``num_degree``."""
    if isinstance(value, str) and value == _DEPRECATED:
        return None
    return check_nonnegative_int(value, name)


class LPMBeyondNyquist(_LocalModelEstimator):
    """Local polynomial modelling beyond the Nyquist frequency.

    The same computation as :class:`LRMBeyondNyquist` with ``den_degree=0``,
    ``num_degree=num_degree`` and ``transient_degree=transient_degree or
    num_degree`` (van Haren et al., 2023; ``F = 1`` is the LPM of Pintelon et
    al.).

    Parameters
    ----------
    half_window : int, default=18
        ``n``: each local window holds ``2n+1`` slow bins.
    num_degree : int, default=2
        Degree of the local system polynomials (``R_g``). The same name as in
        :class:`LRMBeyondNyquist`, of which LPM is the case ``den_degree=0``:
        the numerator is the whole local model.
    transient_degree : int or None, default=None
        Degree of the transient polynomial; ``None`` uses ``num_degree``.
    degree : int, optional
        Deprecated alias of ``num_degree`` (renamed in 0.2.0, removed in
        0.3.0): passing it sets ``num_degree`` with a ``FutureWarning`` in
        ``fit``.

    Attributes
    ----------
    frequencies_, frf_, frf_std_, valid_, noise_variance_, transient_, n_params_, dof_
        As for :class:`LRMBeyondNyquist` (the other fitted attributes too,
        without those of iterative refinement). For LPM the residual is usually
        dominated by model error, so ``frf_std_`` is then an RMS error estimate
        rather than a noise standard deviation.

    References
    ----------
    The LPM beyond Nyquist of van Haren et al. (2023) and the single-rate LPM
    of Schoukens et al. (2009) and Pintelon et al. (2010), as cited
    (``VanHaren2023a``, ``Schoukens2009``, ``Pintelon2010a``) in van Haren,
    Blanken, Classens and Oomen, "Local Rational Modeling for Identification
    Beyond the Nyquist Frequency: Applied to a Prototype Wafer Stage", 2024.

    Examples
    --------
    >>> from scipy.signal import lfilter
    >>> from lrmfrf import LPMBeyondNyquist
    >>> from lrmfrf.signals import multisine
    >>> u = multisine(1200, rng=0)
    >>> y = lfilter([0.2, 0.1], [1.0, -0.5], u)[::3]
    >>> est = LPMBeyondNyquist(half_window=18, num_degree=2).fit(u, y, F=3)
    >>> est.frf_.shape, est.n_params_, est.dof_
    ((601,), 12, 25)
    """

    _parameter_checks = {
        "half_window": _HALF_WINDOW,
        "num_degree": check_nonnegative_int,
        "transient_degree": check_nonnegative_int_or_none,
        "degree": _check_deprecated_degree,
    }
    def __init__(
        self,
        *,
        half_window: int = 18,
        num_degree: int = 2,
        transient_degree: int | None = None,
        degree="deprecated",
    ):
        self.half_window = half_window
        self.num_degree = num_degree
        self.transient_degree = transient_degree
        self.degree = degree

    def _local_degrees(self, params: dict) -> tuple[dict, dict]:
        num_degree = params["num_degree"]
        names = {"den_degree": None}
        if params["degree"] is not None:
            default = type(self)().num_degree
            if num_degree != default and num_degree != params["degree"]:
                raise ValueError(
                    f"`degree` is the deprecated name of `num_degree`; got both, "
                    f"degree={params['degree']} and num_degree={num_degree}. "
                    "Pass num_degree only."
                )
            warnings.warn(
                "`degree` was renamed `num_degree` in lrmfrf 0.2.0 (the name "
                "LRMBeyondNyquist uses) and will be removed in 0.3.0. Pass "
                f"num_degree={params['degree']} instead.",
                FutureWarning,
                stacklevel=3,  # -> the caller of fit
            )
            num_degree = params["degree"]
            names["num_degree"] = "degree"
        transient = params["transient_degree"]
        if transient is None:
            transient = num_degree
        degrees = {
            "half_window": params["half_window"],
            "num_degree": num_degree,
            "transient_degree": transient,
            "den_degree": 0,
        }
        return degrees, names


@dataclass
class _FittedArrays:
    """The fitted arrays of a local-model estimator, filled chunk by chunk."""

    frf: np.ndarray  # (n_y, n_u, K), complex
    std: np.ndarray  # (n_y, n_u, K)
    cov: np.ndarray  # (n_y, n_u, n_u, K), complex
    valid: np.ndarray  # (n_y, n_u, K), bool
    noise: np.ndarray  # (n_y, B)
    transient: np.ndarray  # (P, n_y, B), complex

    def write(self, o, start, fit, N, F, u_exponent, y_exponent,
              runs=None) -> None:
        """Write the results of slow bins ``start..`` of output row ``o``.

        The fast bins are those :func:`lrmfrf.local_models.one_sided_fast_grid`
        maps from these slow bins, written run by run with slices
        (:func:`lrmfrf.local_models._fast_grid_runs`, or ``runs``, its result,
        shared by the output rows of a chunk; a handful of runs per chunk,
        where gathering and scattering each bin through index arrays took
        most of the Python time of a streamed MIMO fit); values are scaled
        back by the records' normalisation exponents as the whole arrays used
        to be. All inputs (and input pairs of ``cov``) of a band are written
        at once. Each value goes through the same operations as before
        (conjugation, ``sqrt`` and exact power-of-two scaling, elementwise),
        so the results are the same bit for bit.
        """
        stop = start + fit.slow_bins.size
        system_exponent = y_exponent - u_exponent
        if runs is None:
            runs = _fast_grid_runs(start, stop, N, F)
        frf, std, cov, valid = self.frf[o], self.std[o], self.cov[o], self.valid[o]
        for f, k0, k1, j0, mirrored in runs:
            j1 = j0 + k1 - k0
            order = slice(k1 - 1, k0 - 1 if k0 else None, -1) if mirrored else \
                slice(k0, k1)
            # band f of every input: columns i F + f, (T, n_u) -> (n_u, T)
            target = frf[:, j0:j1]
            target[...] = fit.system[order, f::F].T
            _conj_scale(target, mirrored, system_exponent)
            # std from the normalised variance: its square may leave the
            # float range
            target = std[:, j0:j1]
            np.sqrt(fit.system_var[order, f::F].T, out=target)
            _conj_scale(target, False, system_exponent)
            target = cov[:, :, j0:j1]
            target[...] = fit.system_cov[order, f::F, f::F].transpose(1, 2, 0)
            _conj_scale(target, mirrored, 2 * system_exponent)
            valid[:, j0:j1] = fit.well_posed[order]
        self.noise[o, start:stop] = scale_by_power_of_two(
            fit.noise_var, 2 * y_exponent
        )
        self.transient[:, o, start:stop] = scale_by_power_of_two(
            fit.transient.T, y_exponent
        )

    def invalidate(self, near, N, F) -> None:
        """NaN and ``valid_ = False`` at the windows ``near`` (slow bins
        ``0..M//2``) of every output row: the fast bins of their bands, and
        their noise variance and transient."""
        bands = np.repeat(near[:, None], F, axis=1)
        fast = one_sided_fast_grid(bands, N, F, conj=False)
        self.frf[..., fast] = np.nan
        self.std[..., fast] = np.nan
        self.cov[..., fast] = np.nan
        self.valid[..., fast] = False
        self.noise[:, near] = np.nan
        self.transient[..., near] = np.nan


def _invalidated(fit, near):
    """``fit`` (a LocalModelFit of slow bins ``0..M//2``) with the windows
    ``near`` not well posed and their values NaN, as a rank-deficient
    window's; ``fit`` itself when ``near`` is None."""
    if near is None:
        return fit
    fields = {"well_posed": fit.well_posed & ~near}
    for name in ("theta", "system", "system_var", "transient", "noise_var",
                 "rss", "system_cov"):
        values = getattr(fit, name)
        if values is not None:
            values = values.copy()
            values[near] = np.nan
            fields[name] = values
    return replace(fit, **fields)


def _warn_nearly_dependent(near, layout, M) -> None:
    """The :class:`IdentifiabilityWarning` of windows whose experiments are
    nearly dependent (:func:`lrmfrf.local_models.nearly_dependent_windows`)."""
    P, need = layout.n_experiments, experiments_needed(layout)
    count = int(np.count_nonzero(near))
    # the half window at which one experiment fills a window
    wide = -(-(layout.n_system + layout.den_degree + layout.transient_degree) // 2)
    fix = "Give the experiments clearly different inputs, e.g. " \
          "lrmfrf.signals.orthogonal_multisines"
    if 2 * wide + 1 <= M:
        fix += f", or increase half_window to at least {wide} (one experiment " \
               "then gives a window enough equations)"
    warnings.warn(
        f"{count} of {near.size} slow bins ({100 * count / near.size:.0f} %) have "
        f"nearly linearly dependent experiments: in their windows the inputs of "
        f"the {P} experiments differ from a linear combination of each other by "
        f"less than about {200 * NEAR_DEPENDENCE_TOL ** 0.5:.0f} % (two "
        "experiments; more for several nearly equal ones; e.g. one "
        "excitation repeated and measured with a "
        "noisy input sensor, or one non-periodic record replayed with a delay "
        "of whole slow samples), or some of the experiments have no input there "
        f"(e.g. one band-limited), and their local model ({layout.n_params} "
        f"parameters, {layout.window} equations per experiment) needs {need} "
        "independent experiments. Their FRF would be dominated and biased by the "
        "noise far beyond its std: it is NaN and valid_ is False. " + fix + ".",
        IdentifiabilityWarning,
        stacklevel=4,
    )


def _conj_scale(values: np.ndarray, conj: bool, exponent: int) -> None:
    """``values`` conjugated (if ``conj``) and times ``2**exponent``, in
    place: the operations of :func:`lrmfrf.local_models.scale_by_power_of_two`
    (exact) without its new array."""
    if conj:
        np.conjugate(values, out=values)
    if exponent:
        with np.errstate(over="ignore", under="ignore"):
            if np.iscomplexobj(values):
                np.ldexp(values.real, exponent, out=values.real)
                np.ldexp(values.imag, exponent, out=values.imag)
            else:
                np.ldexp(values, exponent, out=values)


@dataclass
class _LocalFitSource:
    """What ``local_fit_`` of a closed-form fit is computed from on first
    access: the one-sided spectra of the normalised training records (about
    the size of the records), the layout, the normalisation exponents and the
    backend of the fit."""

    spectra: OneSidedSpectra
    layout: object
    u_exponent: int
    y_exponent: int
    backend: str
    std_method: str = "lemma2"
    near: np.ndarray | None = None  # nearly dependent windows (invalid)
    weights: np.ndarray | None = None  # experiments' noise weights (P, n_y)

    def compute(self):
        """The fit's ``local_fit_``: a LocalModelFit, or a list per output row."""
        n_y = self.spectra.outputs.shape[1]
        bins = half_slow_bins(self.spectra.n_slow)
        rows = [[] for _ in range(n_y)]
        chunks = _iter_weighted_fit_rows(self.spectra, self.layout,
                                         self.std_method, self.backend,
                                         self.weights)
        for _, outputs, chunk in chunks:
            for o, fit in zip(outputs, chunk, strict=True):
                rows[o].append(fit)
        fits = [
            rescale_local_fit(_invalidated(_joined_fits(parts, bins), self.near),
                              self.u_exponent, self.y_exponent)
            for parts in rows
        ]
        return fits[0] if n_y == 1 and self.layout.n_inputs == 1 else fits


def _joint_covariance(source: _LocalFitSource, fits, cov) -> np.ndarray:
    """``frf_joint_cov_`` of a streamed closed-form fit: the band covariance
    between rows of each window (:func:`lrmfrf.uncertainty.
    cross_row_covariance`) on the one-sided fast grid, with the estimator's
    ``frf_cov_`` (``cov``) as the rows' own blocks.

    Each row's local problem is taken as it was solved: on the normalised
    spectra (records at ``2**+-600`` would overflow the residuals' products),
    a weighted row with its experiments' equations weighted window by window
    (``cross_row_covariance(weights=...)``: no weighted copy of the spectra;
    ``fits``, ``local_fit_``, hold the transient unweighted, as that form
    wants); the result is scaled back to the records' units."""
    spectra, layout = source.spectra, source.layout
    N, F = spectra.n_samples, layout.F
    n_y, n_u, K = cov.shape[0], cov.shape[1], cov.shape[-1]
    U = spectra.full_inputs()
    Ys, thetas, weights = [], [], []
    for o, fit in enumerate(fits):
        thetas.append(_rescaled_theta(fit.theta, layout, -source.u_exponent,
                                      -source.y_exponent))
        Ys.append(spectra.full_outputs(o))
        weighted = source.weights is not None and np.any(source.weights[:, o] != 1.0)
        weights.append(source.weights[:, o] if weighted else None)
    method = "lemma2" if source.std_method == "lemma2" else "eiv"
    bins = fits[0].slow_bins
    windows = cross_row_covariance(U, Ys, layout, thetas, bins, method=method,
                                   weights=weights)
    windows = scale_by_power_of_two(
        windows, 2 * (source.y_exponent - source.u_exponent))
    joint = np.empty((n_y, n_u, n_y, n_u, K), dtype=complex)
    fast, slow, band, mirrored = fast_grid_targets(0, bins.size, N, F)
    for f in range(F):
        sel = band == f
        values = windows[slow[sel]][:, :, f::F, :, f::F]  # (T, n_y, n_u, ..)
        values[mirrored[sel]] = values[mirrored[sel]].conj()
        joint[..., fast[sel]] = np.moveaxis(values, 0, -1)
    for o in range(n_y):  # the rows' own blocks: frf_cov_ itself
        joint[o, :, o] = cov[o]
    return joint


def _iter_weighted_fit_rows(spectra, layout, std_method, backend, weights):
    """:func:`lrmfrf.uncertainty.iter_calibrated_fit_rows` yielding ``(start,
    rows, fits)``, with the output rows whose experiments are weighted
    (``weights[:, o]`` not all 1, :func:`lrmfrf.uncertainty.
    experiment_noise_weights`) fitted one by one on their weighted spectra
    (the input weights differ between rows), after the other rows together
    (unchanged). ``weights`` None: all rows at once, as before."""
    for rows, part in _row_groups(spectra, weights):
        chunks = iter_calibrated_fit_rows(part, layout, std_method,
                                          return_cov=True, backend=backend)
        try:
            for start, fits in chunks:
                yield start, rows, [_unweighted(fit, weights, o)
                                    for o, fit in zip(rows, fits, strict=True)]
        finally:  # (the generator holds a single-threaded-BLAS section)
            chunks.close()
        del part, chunks  # before the next row's copy is made


def _row_groups(spectra, weights):
    """``(rows, spectra)`` of :func:`_iter_weighted_fit_rows`: the unweighted
    rows together, then each weighted row on its own weighted copy of the
    spectra, made when it is reached (one copy of the inputs' spectra alive
    at a time: each is the size of the records' DFTs)."""
    n_y = spectra.outputs.shape[1]
    if weights is None:
        yield list(range(n_y)), spectra
        return
    weighted = [o for o in range(n_y) if np.any(weights[:, o] != 1.0)]
    plain = [o for o in range(n_y) if o not in weighted]
    if plain:
        yield plain, OneSidedSpectra(spectra.inputs, spectra.outputs[:, plain],
                                     spectra.n_samples, spectra.F)
    for o in weighted:
        scale = weights[:, o, None, None]
        yield [o], OneSidedSpectra(spectra.inputs * scale,
                                   spectra.outputs[:, [o]] * scale,
                                   spectra.n_samples, spectra.F)


def _unweighted(fit, weights, o):
    """``fit`` of output row ``o`` with its transient (its value and its
    coefficients in ``theta``) back in the units of the records (the
    weighted fit's is scaled by each experiment's weight); ``fit`` itself
    for an unweighted row. The FRF, its std and the noise variance (of the
    weighted experiments: the mean of their levels), ``rss`` and the
    denominator are those of the weighted fit."""
    if weights is None or not np.any(weights[:, o] != 1.0):
        return fit
    layout = fit.layout
    theta = fit.theta.copy()
    for p in range(layout.n_experiments):
        start = layout.transient_column(p)
        theta[:, start:start + layout.transient_degree + 1] /= weights[p, o]
    return replace(fit, theta=theta, transient=fit.transient / weights[:, o])
