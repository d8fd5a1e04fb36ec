"""frf_joint_cov_: the covariance of the local-model estimates between output
rows (lrmfrf.uncertainty.cross_row_covariance), against a Monte Carlo with
output noise correlated between rows, and its contract."""

import warnings

import control
import numpy as np
import pytest

from lrmfrf import LPMBeyondNyquist, LRMBeyondNyquist, LRMBeyondNyquistCV
from lrmfrf.signals import multisine, orthogonal_multisines
from lrmfrf.simulate import simulate

N, F = 600, 3
# one input, two outputs with different dynamics (different local denominators)
SIMO = control.ss([[0.5, 0, 0], [0, 0.3, -0.1], [0, 1, 0]], [[1], [1], [0]],
                  [[0.2, 0, 0], [0, 0.1, -0.05]], [[0.2], [0.1]], 1.0)


def _fit(estimator, u, y):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return estimator.fit(u, y, F)


def test_cross_row_covariance_matches_monte_carlo():
    """Slow output noise with correlation 0.8 between the two outputs, 2 %
    of each output's std, 40 runs. The estimates' errors are correlated about
    as much (measured |corr| 0.76 MC, 0.78 predicted); the rows as
    independent (cross covariance 0, as before frf_joint_cov_) are far off.
    The std of an MC cross covariance from 40 runs is about 14 % per bin;
    over the ~590 inner bins the median ratio |MC| / |predicted| must be in
    [0.9, 1.1] (measured 1.02 with 60 runs) and the median |corr| agree to
    0.05."""
    u = multisine(N, rng=0)
    clean = simulate(SIMO, u[None], F).y_l
    rng = np.random.default_rng(0)
    G, J = [], []
    for _ in range(40):
        a, b = rng.standard_normal((2, N // F))
        v = 0.02 * clean.std(axis=1)[:, None] * np.vstack([a, 0.8 * a + 0.6 * b])
        est = _fit(LRMBeyondNyquist(), u, clean + v)
        G.append(est.frf_[:, 0])
        J.append(est.frf_joint_cov_[:, 0, :, 0])
    G, J = np.array(G), np.array(J)
    d = G - G.mean(axis=0)
    mc = np.einsum("rok,rpk->opk", d, d.conj()) / len(G)
    pred = J.mean(axis=0)
    M, k = N // F, np.arange(N // 2 + 1)
    inner = (k % M != 0) & (k % M != M // 2)
    ratio = np.abs(mc[0, 1]) / np.abs(pred[0, 1])
    assert 0.9 < np.median(ratio[inner]) < 1.1

    def corr(c):
        return np.abs(c[0, 1]) / np.sqrt(c[0, 0].real * c[1, 1].real)

    assert np.median(corr(mc)[inner]) > 0.6  # the rows are far from independent
    assert abs(np.median(corr(mc)[inner]) - np.median(corr(pred)[inner])) < 0.05


def test_joint_covariance_contract():
    """Shape, the rows' own blocks frf_cov_ bit for bit, Hermitian and
    positive semidefinite per bin, kept after the first access, None where
    frf_cov_ is not of the closed form's eiv/Lemma 2 route; one row: frf_cov_
    itself."""
    r = orthogonal_multisines(2, N, rng=0)
    plant = control.ss([[0.5, 0], [0, 0.3]], [[1, 0.5], [0.2, 1]],
                       [[0.2, 0], [0, 0.1], [0.1, 0.1]], np.zeros((3, 2)), 1.0)
    rng = np.random.default_rng(1)
    y = np.stack([simulate(plant, r[p], F).y_l for p in range(2)])
    common = rng.standard_normal((2, 1, N // F))
    y = y + 0.01 * (common + rng.standard_normal(y.shape))
    est = _fit(LRMBeyondNyquist(), r, y)
    joint = est.frf_joint_cov_
    K = N // 2 + 1
    assert joint.shape == (3, 2, 3, 2, K)
    assert est.frf_joint_cov_ is joint
    for o in range(3):
        np.testing.assert_array_equal(joint[o, :, o], est.frf_cov_[o])
    flat = np.moveaxis(joint, -1, 0).reshape(K, 6, 6)
    np.testing.assert_allclose(flat, np.conj(np.swapaxes(flat, 1, 2)),
                               atol=1e-12 * np.abs(flat).max())
    eig = np.linalg.eigvalsh(flat)
    assert np.all(eig[:, 0] > -1e-10 * eig[:, -1])
    # after local_fit_ too (which releases its own copy of the spectra)
    other = _fit(LRMBeyondNyquist(), r, y)
    other.local_fit_  # noqa: B018
    np.testing.assert_allclose(other.frf_joint_cov_, joint, rtol=1e-9,
                               atol=1e-12 * np.abs(joint).max())
    assert _fit(LRMBeyondNyquist(sk_iterations=1), r, y).frf_joint_cov_ is None
    assert _fit(LRMBeyondNyquist(std_method="hc"), r, y).frf_joint_cov_ is None
    lpm = _fit(LPMBeyondNyquist(), r, y)
    assert lpm.frf_joint_cov_.shape == (3, 2, 3, 2, K)
    siso = _fit(LRMBeyondNyquist(), r[0, 0], y[0, 0])
    assert siso.frf_joint_cov_.shape == (1, 1, 1, 1, K)
    with pytest.raises(AttributeError, match="call fit first"):
        LRMBeyondNyquist().frf_joint_cov_  # noqa: B018


def _three_by_two(one_at_a_time, noise_scales, seed):
    """Records of a 3x2 plant, P = 2, output noise partly common to the rows
    (1 % of the outputs' std) times ``noise_scales[p]`` in experiment ``p``."""
    r = orthogonal_multisines(2, N, rng=0)
    if one_at_a_time:
        r = r * np.eye(2)[:, :, None]
    plant = control.ss([[0.5, 0], [0, 0.3]], [[1, 0.5], [0.2, 1]],
                       [[0.2, 0], [0, 0.1], [0.1, 0.1]], np.zeros((3, 2)), 1.0)
    rng = np.random.default_rng(seed)
    y = np.stack([simulate(plant, r[p], F).y_l for p in range(2)])
    common = rng.standard_normal((2, 1, N // F))
    noise = 0.8 * common + 0.6 * rng.standard_normal(y.shape)
    scale = 0.01 * y.std(axis=-1, keepdims=True) * np.array(noise_scales)[:, None, None]
    return r, y + scale * noise


def test_joint_covariance_of_weighted_rows_is_a_covariance():
    """Experiment 1 five times as noisy (std): every row is fitted on weighted
    experiments (noise_weights_). The cross blocks come from the rows' local
    problems as they were solved: the weighted spectra with the weighted
    fit's transient. Before, the weighted spectra were paired with
    local_fit_.theta, whose transient is in the records' units: the residuals
    carried the transient's mismatch, the levels between the rows were far
    too large and every bin's joint covariance had a negative eigenvalue
    (|correlation| of the rows' estimates up to 4000 on a 2x2 stage; 0.79
    predicted against 0.77 by Monte Carlo after the fix, 7.8 before). The
    correlation of two entries is at most 1 (Cauchy-Schwarz): allow 1e-9 for
    round-off."""
    r, y = _three_by_two(True, [1.0, 5.0], 2)
    est = _fit(LRMBeyondNyquist(), r, y)
    assert np.all(est.noise_weights_[1] < 1.0)  # every row weighted
    joint = est.frf_joint_cov_
    K = N // 2 + 1
    flat = np.moveaxis(joint, -1, 0).reshape(K, 6, 6)
    ok = np.isfinite(flat).all(axis=(1, 2))
    assert ok.mean() > 0.9
    variance = np.einsum("kii->ki", flat[ok]).real
    corr = np.abs(flat[ok]) / np.sqrt(variance[:, :, None] * variance[:, None, :])
    assert np.max(corr) < 1 + 1e-9
    eig = np.linalg.eigvalsh(flat[ok])
    assert np.all(eig[:, 0] > -1e-10 * eig[:, -1])


@pytest.fixture(scope="module")
def ordinary():
    """Records of the 3x2 plant, equal noise, and their fit (one for the
    scale tests)."""
    r, y = _three_by_two(False, [1.0, 1.0], 1)
    return r, y, _fit(LRMBeyondNyquist(), r, y)


@pytest.mark.parametrize("exponent", [600, -600])
def test_joint_covariance_does_not_depend_on_the_records_scale(ordinary, exponent):
    """Inputs and outputs both scaled by 2**+-600: the FRF and frf_cov_ are
    those of the ordinary records bit for bit (the fit normalises them), and
    so is frf_joint_cov_. Before, its cross blocks were computed on the
    records in their own units: NaN at 2**600 (the residuals' products
    overflowed), 0 at 2**-600 (underflowed)."""
    r, y, ref = ordinary
    est = _fit(LRMBeyondNyquist(), np.ldexp(r, exponent), np.ldexp(y, exponent))
    np.testing.assert_array_equal(est.frf_cov_, ref.frf_cov_)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow warning either
        joint = est.frf_joint_cov_
    np.testing.assert_array_equal(joint, ref.frf_joint_cov_)


def test_cv_classes_pass_on_the_refits_joint_covariance(ordinary):
    """``LRMBeyondNyquistCV.frf_joint_cov_`` is its refit's (before, the CV
    classes had none, and :func:`lrmfrf.plant_from_closed_loop` silently took
    their rows as independent); None for a per-band blend, whose covariance
    between rows is not formed."""
    r, y, _ = ordinary
    grid = dict(half_windows=[10, 14], num_degrees=[2], transient_degrees=[2],
                den_degrees=[2])
    cv = _fit(LRMBeyondNyquistCV(**grid), r, y)
    joint = cv.frf_joint_cov_
    assert joint is cv.best_estimator_.frf_joint_cov_
    assert joint.shape == (3, 2, 3, 2, N // 2 + 1)
    assert _fit(LRMBeyondNyquistCV(per_band=True, **grid), r, y).frf_joint_cov_ is None
    with pytest.raises(AttributeError, match="call fit first"):
        LRMBeyondNyquistCV().frf_joint_cov_  # noqa: B018


def test_rows_without_input_spectra_must_be_pairs():
    """With U None each row gives its own (U_o, Y_o); a plain (P, M) output
    array (here P = 2, which tuple() would have split into a wrong 'pair')
    is an error that says what to pass, before any work."""
    from lrmfrf.local_models import LocalModelLayout
    from lrmfrf.uncertainty import cross_row_covariance

    layout = LocalModelLayout(F=F, half_window=6, num_degree=1,
                              transient_degree=1, den_degree=1)
    Y = np.ones((2, 40), dtype=complex)
    thetas = [np.zeros((1, layout.n_params), dtype=complex)] * 2
    with pytest.raises(ValueError, match=r"\(U_o, Y_o\) pair"):
        cross_row_covariance(None, [Y, Y], layout, thetas, np.array([3]))


def _random_windows(P=2, n_u=2, M=60):
    """Random spectra (P, n_u N) and two rows' (P, M), a 2-input layout and
    random parameters of 12 windows: the covariance's algebra, not a fit."""
    from lrmfrf.local_models import LocalModelLayout

    rng = np.random.default_rng(0)
    layout = LocalModelLayout(F=2, n_experiments=P, n_inputs=n_u, half_window=6,
                              num_degree=1, transient_degree=1, den_degree=1)

    def cn(*shape):
        return rng.standard_normal(shape) + 1j * rng.standard_normal(shape)

    bins = np.arange(8, 20)
    return (layout, cn(P, n_u * 2 * M), [cn(P, M), cn(P, M)],
            [cn(bins.size, layout.n_params) for _ in range(2)], bins)


def test_weighted_rows_equal_the_weighted_spectra_with_the_weighted_transient():
    """``cross_row_covariance(weights=...)`` (the thetas' transient
    unweighted) is the local problem of the weighted copies ``(U w, Y w)``
    with the transient weighted, as its docstring says (to round-off; the
    values are O(1))."""
    from lrmfrf.uncertainty import cross_row_covariance

    layout, U, Ys, thetas, bins = _random_windows()
    w = np.array([1.0, 0.3])
    unweighted = thetas[0].copy()
    for p in range(layout.n_experiments):  # the records' transient
        start = layout.transient_column(p)
        unweighted[:, start:start + layout.transient_degree + 1] /= w[p]
    ours = cross_row_covariance(U, Ys, layout, [unweighted, thetas[1]], bins,
                                weights=[w, None])
    copies = cross_row_covariance(None, [(U * w[:, None], Ys[0] * w[:, None]),
                                         (U, Ys[1])], layout, thetas, bins)
    assert np.isfinite(copies).all()
    np.testing.assert_allclose(ours, copies, rtol=0, atol=1e-12 * np.abs(copies).max())


def test_weights_are_one_entry_per_row():
    """``weights`` is a list per output row. The (P, n_y) array of
    experiment_noise_weights (or noise_weights_) given as it is was read
    row by row, i.e. transposed, without an error when P == n_y (here 2 x
    2: row 0 got experiment 0's weights of both rows, 41 % off); an entry of
    the wrong length failed deep in numpy, a NaN weight was taken. Now each
    is an error that says what to pass."""
    from lrmfrf.uncertainty import cross_row_covariance

    layout, U, Ys, thetas, bins = _random_windows()
    W = np.array([[1.0, 1.0], [0.3, 1.0]])  # (P, n_y): row 0 weighted
    with pytest.raises(ValueError, match=r"not an array of shape \(2, 2\)"):
        cross_row_covariance(U, Ys, layout, thetas, bins, weights=W)
    for bad in ([np.array([1.0, 0.3, 1.0]), None], [np.array([1.0, np.nan]), None],
                [np.array([1.0, 0.0]), None], [0.5, None]):
        with pytest.raises(ValueError, match=r"weights\[0\]` must be None or 2"):
            cross_row_covariance(U, Ys, layout, thetas, bins, weights=bad)
    # the list the message asks for gives the row-0-weighted result
    listed = cross_row_covariance(U, Ys, layout, thetas, bins,
                                  weights=[W[:, o] for o in range(2)])
    np.testing.assert_array_equal(
        listed, cross_row_covariance(U, Ys, layout, thetas, bins,
                                     weights=[W[:, 0], None]))


def test_complex_or_ragged_weights_are_refused():
    """A complex weight was cast to float with only a ComplexWarning (its
    imaginary part dropped, the row weighted by the real part, no error); a
    ragged entry failed in numpy's conversion. Both now get the message that
    says what to pass."""
    import warnings

    from lrmfrf.uncertainty import cross_row_covariance

    layout, U, Ys, thetas, bins = _random_windows()
    for bad in ([np.array([1.0, 0.3 + 0.5j]), None], [[1.0, [0.3]], None],
                [np.array([True, True]), None]):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # (the old ComplexWarning)
            with pytest.raises(ValueError, match=r"weights\[0\]` must be None or 2"):
                cross_row_covariance(U, Ys, layout, thetas, bins, weights=bad)
