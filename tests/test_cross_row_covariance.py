"""frf_joint_cov_: the covariance of the local-model estimates between output
rows (lrmfrf.uncertainty.cross_row_covariance), against a Monte Carlo with
output noise correlated between rows, and its contract."""

import warnings

import control
import numpy as np
import pytest

from lrmfrf import LPMBeyondNyquist, LRMBeyondNyquist
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
