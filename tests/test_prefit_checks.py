"""The pre-fit checks of the MIMO path, computed the fast way (checks30),
against their direct definitions: the delayed-copy correlation at the lags
(multiples of F) and the experiments' noise levels (dense QR of every
window's whole regressor and the full residual projector)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import fft as sp_fft
from scipy.signal import lfilter

from lrmfrf.local_models import OneSidedSpectra, _correlation_at_multiples
from lrmfrf.solvers import RANK_TOL
from lrmfrf.uncertainty import experiment_noise_levels
from lrmfrf.windows import LocalModelLayout, local_regressor, window_offsets


@pytest.mark.parametrize("N, F", [(120, 3), (121, 11), (100, 4), (99, 3), (30, 5),
                                  (11, 3), (16, 16)])
def test_correlation_at_multiples_is_the_full_transform(N, F):
    rng = np.random.default_rng(N + F)
    cross = rng.standard_normal(N // 2 + 1) + 1j * rng.standard_normal(N // 2 + 1)
    direct = sp_fft.irfft(cross, n=N)[::F][: N // F]
    folded = _correlation_at_multiples(cross, N, F)[: N // F]
    np.testing.assert_allclose(folded, direct, rtol=0,
                               atol=1e-14 * np.abs(direct).max())


def _levels_direct(spectra, layout, weights=None, max_windows=16):
    """experiment_noise_levels by its definition, one dense QR per window."""
    P, n_y = spectra.outputs.shape[:2]
    n, L, M = layout.half_window, layout.window, spectra.n_slow
    centres = np.arange(n + 1, M // 2 - n, L)
    if centres.size > max_windows:
        pick = np.linspace(0, centres.size - 1, max_windows).round().astype(int)
        centres = centres[pick]
    ratio, dof = np.ones((P, n_y)), np.zeros((P, n_y))
    _, x = window_offsets(n)
    for o in range(n_y):
        gains, energies, covs = [], [], []
        for k in centres:
            U, Y, bins = spectra.window_spectra(k, k + 1, n, o)
            A, b = local_regressor(U, Y, bins, layout)
            A, b = A[0], b[0]
            if weights is not None:
                rows = np.repeat(weights[:, o], L)
                A, b = A * rows[:, None], b * rows
            norms = np.linalg.norm(A, axis=0)
            Q, R = np.linalg.qr(A / norms)
            d = np.abs(np.diag(R))
            if not d.min() > RANK_TOL * d.max():
                continue
            theta = np.linalg.solve(R, Q.conj().T @ b) / norms
            e = 1.0 + theta[layout.den_columns] @ (x[:, None] ** np.arange(
                1, layout.den_degree + 1)).T
            w = np.tile(np.abs(e) ** 2, P)
            proj = np.eye(P * L) - Q @ Q.conj().T
            residual = proj @ b
            gains.append((np.abs(proj) ** 2 * w).reshape(P, L, P, L).sum(axis=(1, 3)))
            energies.append((np.abs(residual) ** 2).reshape(P, L).sum(axis=1))
            # cov(r^H D_p r, r^H D_q r) = tr(K_p W K_q W), K_p = R^H D_p R, for
            # r = R e, e ~ CN(0, W)
            K = [proj.conj().T @ np.diag(np.repeat(np.eye(P)[p], L)) @ proj
                 for p in range(P)]
            W = np.diag(w)
            C = np.array([[np.real(np.trace(K[p] @ W @ K[q] @ W)) for q in range(P)]
                          for p in range(P)])
            # the energies divided by the window's level sum(E) / g: first
            # order J = d(g E / sum(E)) / dE at E = M 1, and the finite-dof
            # factor 1 / (1 + var(sum(E)) / g^2)
            g = gains[-1].sum()
            J = np.eye(P) - np.outer(gains[-1].sum(axis=1), np.ones(P)) / g
            covs.append(J @ C @ J.T / (1.0 + C.sum() / g**2))
        gain, energy = np.array(gains), np.array(energies)
        level = energy.sum(axis=1) / gain.sum(axis=(1, 2))
        G_inv = np.linalg.inv(gain.sum(axis=0))
        r = G_inv @ (energy / level[:, None]).sum(axis=0)
        r = np.maximum(r, 1e-3 * r.max())
        r /= r.mean()
        dof[:, o] = 1.0 / np.diag(G_inv @ np.sum(covs, axis=0) @ G_inv.T)
        ratio[:, o] = r
        if weights is not None:
            ratio[:, o] /= weights[:, o] ** 2
            ratio[:, o] /= ratio[:, o].mean()
    return ratio, dof


@pytest.mark.parametrize("P, n_u, n_y, den_degree", [(2, 2, 2, 7), (3, 2, 3, 3),
                                                     (2, 1, 2, 0)])
@pytest.mark.parametrize("weighted", [False, True])
def test_noise_levels_match_their_definition(P, n_u, n_y, den_degree, weighted):
    F, M = 3, 400
    rng = np.random.default_rng(P * 100 + n_u * 10 + n_y + den_degree)
    u = rng.standard_normal((P, n_u, F * M))
    y = np.zeros((P, n_y, F * M))
    for o in range(n_y):
        for i in range(n_u):
            y[:, o] += lfilter([0.2, 0.1 * (o + 1)], [1.0, -0.8 + 0.1 * i], u[:, i])
    y = y[..., ::F]
    scale = np.arange(1, P + 1)[:, None, None]  # unequal noise levels
    y = y + 0.01 * y.std() * scale * rng.standard_normal(y.shape)
    spectra = OneSidedSpectra.from_records(u, y, F)
    layout = LocalModelLayout(F=F, half_window=10, num_degree=2, transient_degree=2,
                              den_degree=den_degree, n_experiments=P, n_inputs=n_u)
    weights = None
    if weighted:  # rows weighted differently, one row not at all
        weights = np.ones((P, n_y))
        weights[:, 0] = np.linspace(0.5, 2.0, P)
    levels = experiment_noise_levels(spectra, layout, weights=weights)
    ratio, dof = _levels_direct(spectra, layout, weights)
    np.testing.assert_allclose(levels.ratio, ratio, rtol=1e-10)
    np.testing.assert_allclose(levels.dof, dof, rtol=1e-10)
