"""The spread of the experiments' level difference at equal noise: the
quadratic-form variance of ``lrmfrf.uncertainty._noise_levels_of_row``
against simulation on synthetic windows (review31).

B = 5 windows, P = 2 experiments of L = 20 equation rows each, a random
complex regressor per window (experiment 1's rows scaled by ``amp``, as an
input of larger RMS) and its residual projector R, equation-noise weights
``w`` (log-normal, spread ``wspread``). With ``e ~ CN(0, diag(w))`` and ``r =
R e`` the energies ``||r_p||^2`` are normalised per window by the estimated
pooled level (as the library) or by the true one, and ``c = G^-1 sum_b
energy_b``. Printed: the simulated variance of ``c_0 - c_1`` over
``G^-1 C G^-T``'s (4000 draws: about 2 % std), and, for the estimated level,
over the first-order covariance the library uses, ``G^-1 (sum_b J_b C_b
J_b^T) G^-T`` with ``J_b = I - m_b 1^T / g_b`` (``m_b = M_b 1``, ``g_b = 1^T
M_b 1``: the division by the window's estimated level, first order), and
over ``G^-1 (sum_b J_b C_b J_b^T / (1 + v_b)) G^-T`` with ``v_b = 1^T C_b 1 /
g_b^2`` the relative variance of the window's level (what the library
uses: exact for ``w`` constant, where the residual direction is independent
of its norm; the first-order term alone is ~0 for a symmetric window, while
the finite-dof factor ``1 / (1 + v_b)`` is what the gap of the estimated
level was).

Run (a few seconds)::

    python benchmarks/noise_level_spread.py
"""

from __future__ import annotations

import numpy as np

P, L, B = 2, 20, 5


def case(rng, n_params, wspread, amp, draws=4000):
    projectors, weights = [], []
    for _ in range(B):
        A = (rng.standard_normal((P * L, n_params))
             + 1j * rng.standard_normal((P * L, n_params)))
        A[L:] *= amp
        Q, _ = np.linalg.qr(A)
        projectors.append(np.eye(P * L) - Q @ Q.conj().T)
        weights.append(np.exp(wspread * rng.standard_normal(P * L)))
    R, w = np.array(projectors), np.array(weights)
    gain = np.einsum("bpljs,bjs->bpj", (np.abs(R) ** 2).reshape(B, P, L, P, L),
                     w.reshape(B, P, L))
    G_inv = np.linalg.inv(gain.sum(axis=0))
    T = R * w[:, None, :] @ R
    C_b = np.einsum("bpljs->bpj", (np.abs(T) ** 2).reshape(B, P, L, P, L))
    V = G_inv @ C_b.sum(axis=0) @ G_inv.T
    predicted = V[0, 0] + V[1, 1] - 2 * V[0, 1]
    J = np.eye(P) - gain.sum(axis=2)[:, :, None] / gain.sum(axis=(1, 2))[:, None, None]
    V = G_inv @ np.einsum("bpi,bij,bqj->pq", J, C_b, J) @ G_inv.T
    corrected = V[0, 0] + V[1, 1] - 2 * V[0, 1]
    g = gain.sum(axis=(1, 2))
    v = C_b.sum(axis=(1, 2)) / g**2  # relative variance of the window's level
    V = G_inv @ np.einsum("bpi,bij,bqj,b->pq", J, C_b, J, 1 / (1 + v)) @ G_inv.T
    exact = V[0, 0] + V[1, 1] - 2 * V[0, 1]
    estimated, true = [], []
    for _ in range(draws):
        e = (rng.standard_normal((B, P * L)) + 1j * rng.standard_normal((B, P * L)))
        e *= np.sqrt(w / 2)
        r = np.einsum("brs,bs->br", R, e)
        energy = (np.abs(r) ** 2).reshape(B, P, L).sum(axis=2)
        level = energy.sum(axis=1) / gain.sum(axis=(1, 2))
        a = G_inv @ (energy / level[:, None]).sum(axis=0)
        b = G_inv @ energy.sum(axis=0)
        estimated.append(a[0] - a[1])
        true.append(b[0] - b[1])
    print(f"| {P * L - n_params} | {wspread} | {amp} | "
          f"{np.var(estimated) / predicted:.3f} | {np.var(true) / predicted:.3f} | "
          f"{np.var(estimated) / corrected:.3f} | {np.var(estimated) / exact:.3f} |")


def main():
    rng = np.random.default_rng(0)
    print("| residual dof | wspread | amp | var / predicted, estimated level | "
          "var / predicted, true level | var / J C J^T, estimated level | "
          "var / J C J^T / (1 + v), estimated level |")
    print("|---|---|---|---|---|---|---|")
    for n_params, wspread, amp in [(30, 0.0, 1), (30, 0.5, 1), (30, 0.5, 4),
                                   (10, 0.5, 4), (36, 0.5, 4)]:
        case(rng, n_params, wspread, amp)


if __name__ == "__main__":
    main()
