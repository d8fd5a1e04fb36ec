"""Shared behaviour of the FRF estimators: parameter checks, fitted checks,
predict, score, FRD."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sklearn.base import BaseEstimator
from sklearn.exceptions import NotFittedError

from .._validation import (
    SEVERAL_EXPERIMENTS_HINT,
    check_records,
    format_like_input,
    parse_record_set,
)
from ..local_models import dft, power_of_two_exponent, scale_by_power_of_two

__all__ = ["FRFEstimatorMixin"]

#: An input DFT bin whose magnitude is below this fraction of the record's
#: largest bin counts as not excited in ``predict`` (round-off of a zero).
_UNEXCITED_TOL = 1e-12


def _normalise_in_place(x: np.ndarray) -> int:
    """Scale a validated (already copied) float array by a power of two in place.

    Returns the exponent ``e`` of :func:`lrmfrf.local_models.power_of_two_exponent`
    (``x`` becomes ``x * 2**-e``); 0, and ``x`` untouched, for ordinary data.
    """
    exponent = power_of_two_exponent(x)
    if exponent:
        np.ldexp(x, -exponent, out=x)
    return exponent


class FRFEstimatorMixin:
    """Accessors common to every estimator that exposes ``frequencies_``/``frf_``.

    Subclasses implement ``fit`` and ``_fast_frf(n_samples)`` (the FRF on the
    full fast DFT grid ``k = 0..N-1``).
    """

    def _check_fitted(self) -> None:
        if not hasattr(self, "frf_"):
            raise NotFittedError(
                f"This {type(self).__name__} instance is not fitted yet. Call "
                "`fit(u_h, y_l, F)` before using this method."
            )

    def _fast_frf(self, n_samples: int) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def _n_channels(self) -> tuple[int, int]:
        """(n_y, n_u) of the fitted FRF (1, 1 for an estimator fitted before
        these attributes existed)."""
        return getattr(self, "n_outputs_", 1), getattr(self, "n_inputs_", 1)

    def predict(self, u_h):
        """Steady-state slow-rate output predicted by the FRF.

        ``Y_h(k) = G(k) U_h(k)`` on the fast DFT grid, ``y_l = y_h[::F]``
        (periodic steady state: no transient). Bins where an input's DFT is
        zero (below ``1e-12`` of its largest bin) contribute nothing, so an
        input without energy at invalid bins (``valid_ == False``) can be
        predicted.

        Parameters
        ----------
        u_h : array-like of shape (N,), (n_u, N) or (P, n_u, N), or list
            Fast input(s) of the same length as the training records, in the
            record convention of ``fit``.

        Returns
        -------
        ndarray or list
            Slow output(s) in the units of the training ``y_l`` and in the
            form of the input: (M,) for a 1-D input and one output, (n_y, M)
            for one record otherwise, (P, n_y, M) for a 3-D input, a list of
            records for a list.

        Raises
        ------
        NotFittedError
            Before ``fit``.
        ValueError
            If the input has a different length or number of channels than
            the training records, or excites a frequency where the FRF is
            invalid.
        """
        self._check_fitted()
        u, form, item_ndim = parse_record_set(u_h, "u_h", purpose="predicting")
        y = self._predict_records(u, form)
        return format_like_input(y, form, item_ndim)

    def _predict_records(self, u: np.ndarray, form: str = "3d") -> np.ndarray:
        """Predicted slow outputs (P, n_y, M) of validated inputs (P, n_u, N)."""
        F = self.downsampling_factor_
        n_y, n_u = self._n_channels()
        if u.shape[1] != n_u:
            hint = " " + SEVERAL_EXPERIMENTS_HINT if form == "2d" else ""
            raise ValueError(
                f"The estimator was fitted with {n_u} input channel(s); u_h has "
                f"{u.shape[1]}." + hint
            )
        if u.shape[2] != self.n_samples_:
            raise ValueError(
                f"predict needs an input of the training length N="
                f"{self.n_samples_}. Got {u.shape[2]} samples. The FRF is only "
                "known on the training DFT grid: pass records of that length."
            )
        # G U with both normalised by powers of two (exact), scaled back last
        u_exponent = _normalise_in_place(u)
        U = dft(u)  # (P, n_u, N)
        del u
        G = self._fast_frf(self.n_samples_).reshape(n_y, n_u, -1)
        g_exponent = power_of_two_exponent(np.nan_to_num(np.abs(G)))
        G = scale_by_power_of_two(G, -g_exponent)
        unexcited = np.abs(U) <= _UNEXCITED_TOL * np.abs(U).max(axis=2, keepdims=True)
        with np.errstate(invalid="ignore"):
            terms = np.where(unexcited[:, None], 0.0, G[None] * U[:, None])
        Yh = terms[:, :, 0] if n_u == 1 else terms.sum(axis=2)  # (P, n_y, N)
        if np.isnan(Yh).any():
            n_bad = int(np.count_nonzero(np.isnan(Yh).any(axis=(0, 1))))
            raise ValueError(
                f"The FRF is invalid (NaN) at {n_bad} fast DFT bin(s) this input "
                "excites (see `valid_`). Refit with an input that excites every "
                "band, or predict with an input that has no energy at the invalid "
                "bins."
            )
        y = np.fft.ifft(Yh, axis=2).real[:, :, ::F]
        return scale_by_power_of_two(y, u_exponent + g_exponent)

    def score(self, u_h, y_l) -> float:
        """R^2 of the predicted slow output against ``y_l`` (all experiments).

        Per output channel ``o``, ``1 - sum (y_o - predict(u_h)_o)^2 / sum
        (y_o - mean(y_o))^2`` over all samples of all experiments; the score
        is the uniform average over the outputs (scikit-learn's
        ``multioutput="uniform_average"``). The transient in ``y_l`` is not
        predicted.

        Parameters
        ----------
        u_h : array-like or list
            Fast input(s) of the training length (record convention of
            ``fit``).
        y_l : array-like or list
            Measured slow output(s).

        Returns
        -------
        float
            1 for a perfect prediction; can be negative.
        """
        self._check_fitted()
        records = check_records(
            u_h, y_l, self.downsampling_factor_, purpose="scoring"
        )
        prediction = self._predict_records(records.u, records.u_form)
        y = records.y
        if prediction.shape[1] != y.shape[1]:
            raise ValueError(
                f"The estimator predicts {prediction.shape[1]} output channel(s); "
                f"y_l has {y.shape[1]}." + records.hint()
            )
        scores = []
        for o in range(y.shape[1]):
            y_o, p_o = y[:, o], prediction[:, o]
            # R^2 is a ratio: normalise both by the same power of two (exact)
            exponent = power_of_two_exponent(y_o)
            y_o = scale_by_power_of_two(y_o, -exponent)
            p_o = scale_by_power_of_two(p_o, -exponent)
            ss_res = np.sum((y_o - p_o) ** 2)
            ss_tot = np.sum((y_o - y_o.mean()) ** 2)
            if ss_tot == 0.0:
                scores.append(0.0 if ss_res > 0 else 1.0)
            else:
                scores.append(float(1.0 - ss_res / ss_tot))
        return float(np.mean(scores))

    def to_frd(self, *, return_std: bool = False):
        """The valid bins of the FRF as a ``control.FrequencyResponseData``.

        Parameters
        ----------
        return_std : bool, default=False
            Also return the standard deviation of the FRF on the FRD's
            frequencies (scikit-learn's ``return_std`` pattern, as in
            ``GaussianProcessRegressor.predict``).

        Returns
        -------
        frd : control.FrequencyResponseData
            ``omega`` in rad/s, ``dt`` the fast sample time in seconds, with
            ``n_y`` outputs and ``n_u`` inputs. Bins where any entry has
            ``valid_ == False`` are left out.
        std : ndarray of shape (n_valid,) or (n_y, n_u, n_valid)
            Only with ``return_std=True``: ``frf_std_`` at the same bins, in
            the order of ``frd.omega`` (``sqrt(E|G_hat - G|^2)``, units of
            the FRF; NaN where the estimator has no std, e.g. spectral
            analysis of a single segment).

        Examples
        --------
        >>> from scipy.signal import lfilter
        >>> from lrmfrf import LRMBeyondNyquist
        >>> from lrmfrf.signals import multisine
        >>> u = multisine(1200, rng=0)
        >>> y = lfilter([0.2, 0.1], [1.0, -0.5], u)[::3]
        >>> frd, std = LRMBeyondNyquist(den_degree=2).fit(u, y, F=3).to_frd(
        ...     return_std=True)
        >>> frd.omega.shape == std.shape
        True
        """
        import control

        from .._validation import check_bool

        return_std = check_bool(return_std, "return_std")
        self._check_fitted()
        valid = np.asarray(self.valid_)
        keep = valid if valid.ndim == 1 else valid.all(axis=(0, 1))
        frd = control.FrequencyResponseData(
            self.frf_[..., keep],
            2 * np.pi * self.frequencies_[keep],
            dt=self.sample_time_,
        )
        if return_std:
            return frd, self.frf_std_[..., keep].copy()
        return frd


class _BaseFRFEstimator(FRFEstimatorMixin, BaseEstimator):
    """BaseEstimator with the FRF accessors and declared parameter checks.

    Each subclass declares, once, how each constructor parameter is checked:
    ``_parameter_checks`` maps the parameter name to ``check(value, name)``,
    which returns the validated value or raises a ``TypeError``/``ValueError``
    naming the parameter, what was received and what to pass instead.
    ``fit`` calls :meth:`_checked_params` first, before looking at the data
    (checks that need the data, e.g. a window wider than the record, follow).
    """

    _parameter_checks: dict[str, Callable] = {}

    def _checked_params(self) -> dict:
        """Validated values of all constructor parameters, by name."""
        params = self.get_params(deep=False)
        missing = set(params) - set(self._parameter_checks)
        if missing:  # pragma: no cover - a programming error, caught by tests
            raise NotImplementedError(
                f"{type(self).__name__} declares no check for {sorted(missing)}."
            )
        return {
            name: self._parameter_checks[name](value, name)
            for name, value in params.items()
        }

    def __sklearn_tags__(self):  # scikit-learn >= 1.6
        tags = super().__sklearn_tags__()
        tags.target_tags.required = True
        tags.non_deterministic = False
        return tags

    def _more_tags(self):  # scikit-learn < 1.6
        return {"requires_y": True, "non_deterministic": False}
