"""Compiled Sanathanan-Koerner refinement against the numpy reference path."""

from __future__ import annotations

import functools
import warnings

import numpy as np
import pytest

from lrmfrf import _compiled
from lrmfrf.local_models import dft, fit_local_models
from lrmfrf.refinement import refine_local_models
from lrmfrf.signals import multisine
from lrmfrf.windows import LocalModelLayout

pytestmark = pytest.mark.skipif(not _compiled.AVAILABLE, reason="needs numba")

PAPER = {"half_window": 18, "num_degree": 4, "transient_degree": 4, "den_degree": 7}


def test_schur_cohn_root_test_matches_eigenvalues():
    """root_in_disk agrees with the roots from eigenvalues (np.roots) on random
    complex polynomials of degree 1..8 whose coefficients span decades, away
    from ties (a root within 1e-6 relative of the disk's edge)."""
    from lrmfrf._compiled_refine import root_in_disk

    rng = np.random.default_rng(11)
    checked = inside = 0
    for _ in range(3000):
        d = int(rng.integers(1, 9))
        coef = (rng.standard_normal(d) + 1j * rng.standard_normal(d)) * 10.0 ** (
            rng.uniform(-3, 3, d)
        )
        radius = 10.0 ** rng.uniform(-3, 1)
        roots = np.roots(np.concatenate([coef[::-1], [1.0]]))
        closest = np.abs(roots).min()
        if abs(closest - radius) <= 1e-6 * radius:
            continue
        checked += 1
        inside += closest < radius
        assert root_in_disk(coef, radius) == (closest < radius), (coef, radius)
    assert checked > 2900 and 300 < inside < checked - 300  # both outcomes seen


def _stage_records(system, F, N, seed, snr_db=45.0):
    from lrmfrf.simulate import simulate

    rng = np.random.default_rng(seed)
    u = multisine(N, rms=1.44, rng=rng)
    y = simulate(system, u, F, snr_db=snr_db, rng=rng).y_l
    return dft(u)[None], dft(y)[None]


def _assert_same_refinement(U, Y, layout, rtol=1e-8, **params):
    """The compiled and numpy SK agree to 1e-8 relative on every window whose
    guard decision is the same: the FRF, costs and parameters; variances to
    the 1e-5 of the closed form's normal-equation variance (test_fast_solver).

    Exception, parameters only, at most 1 % of the windows and to 1e-5: a
    window whose SK trajectory passes an ill-conditioned reweighted problem.
    Both paths solve it by normal equations with one refinement step,
    accurate to about ``cond * 1e-16`` relative; on the one such window of
    the wafer-stage case (its second SK problem has an equilibrated condition
    number of 7.8e6) numpy's iterate is 1.2e-6 from the QR solution of the same
    problem and the compiled one 2.6e-7, so 1e-8 agreement is beyond both.
    Its FRF still agrees to 1e-10 (checked below like every window's)."""
    closed = fit_local_models(U, Y, layout)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = refine_local_models(U, Y, layout, closed, backend="numpy", **params)
        new = refine_local_models(U, Y, layout, closed, backend="numba", **params)
    same = ref.guarded == new.guarded
    assert np.count_nonzero(~same) <= max(2, same.size // 100)
    a, b = ref.local_fit, new.local_fit
    # exact fits (in-class data): both costs are round-off, far below 1e-20
    # |b|^2 (the exact-fit threshold is 1e-26 |b|^2; any noise is far above)
    bb = layout.n_equations * np.mean(np.abs(Y) ** 2)
    exact = (a.rss <= 1e-20 * bb) & (b.rss <= 1e-20 * bb)
    np.testing.assert_array_equal(exact, (a.rss <= 1e-20 * bb) | (b.rss <= 1e-20 * bb))
    for name, tol in (("theta", rtol), ("system", rtol), ("rss", rtol),
                      ("noise_var", rtol), ("system_var", max(rtol, 1e-5)),
                      ("transient", rtol)):
        x, z = getattr(a, name)[same], getattr(b, name)[same]
        scale = np.abs(x).reshape(x.shape[0], -1).max(axis=1)
        diff = np.abs(x - z).reshape(x.shape[0], -1).max(axis=1)
        assert np.array_equal(np.isnan(diff), np.isnan(scale)), name
        ok = ~np.isnan(scale)
        if name in ("rss", "noise_var", "system_var"):
            ok &= ~exact[same]  # round-off costs (and variances from them)
        off = np.flatnonzero(ok & ~(diff <= tol * scale))
        if name == "theta" and off.size:
            assert off.size <= max(1, same.size // 100)
            assert np.all(diff[off] <= 1e-5 * scale[off])
            continue
        assert off.size == 0, (name, np.max(diff[ok] / scale[ok]))
    np.testing.assert_array_equal(ref.converged[same], new.converged[same])
    if same.all():
        assert ref.sk_iterations == new.sk_iterations
        assert ref.lm_iterations == new.lm_iterations
        np.testing.assert_allclose(new.cost_history, ref.cost_history, rtol=rtol)
        np.testing.assert_allclose(
            new.sk_cost_history, ref.sk_cost_history, rtol=rtol
        )
        assert ref.stopped_far == new.stopped_far
    return ref, new


@pytest.mark.parametrize("tol", [0.0, 1e-6])
def test_compiled_sk_equals_numpy_sk_on_the_wafer_stage(tol):
    from lrmfrf.plants import wafer_stage

    F = 3
    U, Y = _stage_records(wafer_stage().G_y4, F, 1200 * F, seed=4)
    layout = LocalModelLayout(F=F, **PAPER)
    ref, new = _assert_same_refinement(
        U, Y, layout, sk_iterations=10, tol=tol
    )
    if tol == 0.0:  # early stopping off: every window runs every iteration
        assert new.sk_iterations == 10 and not new.converged.any()


@pytest.mark.parametrize("F, seed", [(1, 0), (2, 1), (3, 2), (5, 3)])
def test_compiled_sk_equals_numpy_sk_on_random_stages(F, seed):
    from lrmfrf.plants import random_stage

    stage, _ = random_stage(seed, downsampling_factor=F)
    U, Y = _stage_records(stage.G_y4, F, 600 * F, seed=seed, snr_db=40.0)
    half_window = 18 if F < 5 else 22
    layout = LocalModelLayout(
        F=F, half_window=half_window, num_degree=4, transient_degree=4,
        den_degree=7,
    )
    for tol in (0.0, 1e-6):
        _assert_same_refinement(U, Y, layout, sk_iterations=8, tol=tol)


def test_compiled_sk_with_two_experiments_and_guard_acting():
    """P = 2, and a guard tight enough to reject iterates (jump = 0.5 sd)."""
    from lrmfrf.plants import wafer_stage
    from lrmfrf.simulate import simulate

    F, N = 3, 3600
    rng = np.random.default_rng(8)
    system = wafer_stage().G_y4
    u = np.stack([multisine(N, rng=rng) for _ in range(2)])
    y = np.stack([simulate(system, u[p], F, snr_db=40, rng=rng).y_l for p in range(2)])
    layout = LocalModelLayout(F=F, n_experiments=2, **PAPER)
    ref, new = _assert_same_refinement(
        dft(u), dft(y), layout, sk_iterations=6, tol=0.0, jump=0.5
    )
    assert new.n_guarded > 10


def test_compiled_sk_keeps_exact_fits():
    """Noise-free in-class windows are exact: the compiled SK leaves them."""
    from lrmfrf.testing import in_class_data

    layout = LocalModelLayout(F=3, **PAPER)
    u, y, centres, G = in_class_data(layout, 300, rng=2)
    ref, new = _assert_same_refinement(dft(u), dft(y), layout, sk_iterations=5)
    fit = new.local_fit
    rows = np.searchsorted(fit.slow_bins, centres)
    np.testing.assert_allclose(fit.system[rows], G, rtol=1e-8, atol=1e-10)
    assert new.converged[rows].all()


def test_estimator_uses_the_compiled_sk_on_long_records(monkeypatch):
    """LRMBeyondNyquist(sk_iterations=...) goes through the compiled kernel
    when it is available (auto backend) and gives the numpy result."""
    import lrmfrf._compiled_refine as kernel
    from lrmfrf import LRMBeyondNyquist

    calls = []
    original = kernel.sk_windows

    def spy(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    rng = np.random.default_rng(3)
    u = multisine(30_000, rng=rng)
    from scipy.signal import lfilter

    y = lfilter([0.2, 0.1], [1.0, -1.2, 0.5], u)[::3]
    y = y + 1e-3 * rng.standard_normal(y.size)
    monkeypatch.setattr(kernel, "sk_windows", spy)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fast = LRMBeyondNyquist(den_degree=2, sk_iterations=3).fit(u, y, 3)
        monkeypatch.setenv("LRMFRF_DISABLE_NUMBA", "1")
        slow = LRMBeyondNyquist(den_degree=2, sk_iterations=3).fit(u, y, 3)
    assert len(calls) == 1
    np.testing.assert_allclose(fast.frf_, slow.frf_, rtol=1e-8)
    np.testing.assert_allclose(fast.frf_std_, slow.frf_std_, rtol=1e-5)
    np.testing.assert_allclose(fast.cost_history_, slow.cost_history_, rtol=1e-8)


@pytest.mark.parametrize("F, seed", [(3, 4), (2, 1)])
def test_compiled_lm_equals_numpy_lm(F, seed):
    """Guarded LM from the closed form (5 iterations): as SK, 1e-8."""
    from lrmfrf.plants import random_stage, wafer_stage

    system = wafer_stage().G_y4 if F == 3 else random_stage(
        seed, downsampling_factor=F)[0].G_y4
    U, Y = _stage_records(system, F, 1200 * F, seed=seed)
    layout = LocalModelLayout(F=F, **PAPER)
    ref, new = _assert_same_refinement(U, Y, layout, lm_iterations=5)
    assert new.lm_iterations == 5


def test_compiled_sk_then_lm_equals_numpy():
    """SK 5 then LM 20 with the guard acting. LM amplifies round-off (numpy
    solves its damped equations by LU without refinement, accurate to about
    cond * 1e-16, and 25 iterations compound it; we see the FRF agree to
    1.3e-8 at worst): FRF, costs and parameters to 1e-6."""
    from lrmfrf.plants import wafer_stage

    U, Y = _stage_records(wafer_stage().G_y4, 3, 3600, seed=4)
    layout = LocalModelLayout(F=3, **PAPER)
    ref, new = _assert_same_refinement(
        U, Y, layout, rtol=1e-6, sk_iterations=5, lm_iterations=20
    )
    assert new.n_guarded > 0 and new.lm_iterations == 20


def test_compiled_lm50_equals_numpy_lm_on_the_benchmark_case():
    """The benchmark's refinement (guarded LM, 50 iterations, from the closed
    form; default tol) on wafer-stage data: the compiled LM, whose ``J^H J``
    is formed from moments in the layout basis, against numpy's LM (``J``
    formed explicitly), on every window whose guard decision is the same.

    The FRF and the cost agree to about 1e-8 relative. Fifty LM iterations amplify
    round-off in the parameters of ill-conditioned windows (directions the
    cost hardly sees): we allow 3 % of the windows parameters within 1e-5
    and 1 % a cost within 1e-6. Measured when this test was written: the
    compiled LM before the layout-basis moments was off numpy on 18 of 751
    windows in ``theta`` (at most 9.8e-6) and one in ``rss`` (1.5e-7); after
    it, 17 windows (3.5e-6) and one (2.4e-8); the FRF within 6.2e-9 in
    both. The FRF is held to 1e-8 on all but 1 % of the windows and to 1e-7
    on every one: the problem's own sensitivity is about that size (numpy's
    LM started from the closed form with each parameter moved by 2e-16
    relative ends up to 8.2e-9 away on the FRF), and after the compiled
    kernel's shared steps changed their round-off (output rows solved
    together) one of 751 windows is 1.1e-8 off numpy (freshly compiled).
    Likewise the parameters: that 2e-16 start moves numpy's own theta by up
    to 6.7e-6 (8 windows beyond 1e-8) and rss by 1e-7; the compiled LM,
    whose arithmetic differs in every iteration, measured up to 2.2e-5 in
    theta (17 windows beyond 1e-8) and 2.5e-7 in rss, so theta is held to
    1e-4 (15x numpy's own sensitivity) and rss to 1e-6; the mean cost over
    the windows (measured 1.3e-8 apart) to 1e-7."""
    from lrmfrf.plants import wafer_stage

    U, Y = _stage_records(wafer_stage().G_y4, 3, 1500 * 3, seed=5)
    layout = LocalModelLayout(F=3, **PAPER)
    closed = fit_local_models(U, Y, layout)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = refine_local_models(U, Y, layout, closed, lm_iterations=50,
                                  backend="numpy")
        new = refine_local_models(U, Y, layout, closed, lm_iterations=50,
                                  backend="numba")
    same = ref.guarded == new.guarded
    assert np.count_nonzero(~same) <= 2 and 10 < np.count_nonzero(new.guarded)
    assert new.lm_iterations == ref.lm_iterations > 20
    assert 0 < np.count_nonzero(new.converged) < new.converged.size
    a, b = ref.local_fit, new.local_fit

    def rel(name):
        x = getattr(a, name)[same].reshape(np.count_nonzero(same), -1)
        z = getattr(b, name)[same].reshape(x.shape)
        return np.abs(x - z).max(axis=1) / np.abs(x).max(axis=1)

    frf = rel("system")
    assert np.all(frf <= 1e-7)
    assert np.count_nonzero(frf > 1e-8) <= 0.01 * frf.size
    for name, share, loose in (("theta", 0.03, 1e-4), ("rss", 0.01, 1e-6)):
        diff = rel(name)
        assert np.all(diff <= loose), name
        assert np.count_nonzero(diff > 1e-8) <= share * diff.size, name
    np.testing.assert_allclose(new.cost_history, ref.cost_history, rtol=1e-7)


def test_layout_tables_give_the_changed_basis_gram():
    """The layout moment tables used by the compiled LM give ``S H S^T`` of
    the internal Gram ``H`` (``A_layout = A_int S^T``) on a random window
    weight, to round-off."""
    from lrmfrf.refinement import _sk_layout

    layout = LocalModelLayout(F=3, **PAPER)
    sk = _sk_layout(layout)
    rng = np.random.default_rng(1)
    L = 2 * PAPER["half_window"] + 1
    base = rng.standard_normal((5, L)) + 1j * rng.standard_normal((5, L))
    base[3] = 1.0  # the transient constant
    row_weight = rng.uniform(0.5, 2.0, L)

    def gram(weights, col_base):
        A = weights * base[col_base].T
        return A.conj().T @ (row_weight[:, None] * A)

    S = sk["from_layout"]
    H = gram(sk["weights"], sk["col_base"])
    G = gram(sk["layout_weights"], sk["layout_col_base"])
    np.testing.assert_allclose(G, S @ H @ S.T, rtol=0, atol=1e-11 * np.abs(G).max())


def test_lm_repacking_leaves_every_window_unchanged(monkeypatch):
    """Windows still active after some LM iterations are packed densely into
    new lane groups (``_LM_STAGES``, when LM does not refill lanes): a
    window's LM iterates do not depend on the lane it sits in nor on its
    neighbours, and its model is a function of its estimate alone, so the
    results with packing after iterations 1, 2, 3, 7 and 20 equal, bit for
    bit, those of lane groups that run all 50 iterations. Each stage has
    windows to pack (checked on the number of windows still active after
    each)."""
    from lrmfrf import _compiled_refine
    from lrmfrf.plants import wafer_stage

    U, Y = _stage_records(wafer_stage().G_y4, 3, 1500 * 3, seed=5)
    layout = LocalModelLayout(F=3, **PAPER)
    closed = fit_local_models(U, Y, layout)
    monkeypatch.setattr(_compiled_refine, "_LM_REFILL", False)
    resumed = []
    lm_range = _compiled_refine._lm_range

    def spy(*args):
        resumed.append(args[41])  # the stage's first iteration
        return lm_range(*args)

    monkeypatch.setattr(_compiled_refine, "_lm_range", spy)
    results = {}
    for stages in ((), (1, 2, 3, 7, 20)):
        monkeypatch.setattr(_compiled_refine, "_LM_STAGES", stages)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            results[stages] = refine_local_models(
                U, Y, layout, closed, lm_iterations=50, backend="numba"
            )
    ref, new = results.values()
    assert set(resumed) == {1, 2, 3, 7, 20}
    assert new.lm_iterations == ref.lm_iterations == 50
    assert 0 < np.count_nonzero(new.converged) < new.converged.size
    for name in ("theta", "system", "rss", "system_var"):
        np.testing.assert_array_equal(
            getattr(new.local_fit, name), getattr(ref.local_fit, name), err_msg=name
        )
    np.testing.assert_array_equal(new.converged, ref.converged)
    np.testing.assert_array_equal(new.guarded, ref.guarded)
    np.testing.assert_allclose(new.cost_history, ref.cost_history, rtol=1e-13)


@pytest.mark.parametrize("sk_iterations, lm_iterations", [(0, 50), (3, 20)])
def test_lm_lane_refill_leaves_every_window_unchanged(
    monkeypatch, sk_iterations, lm_iterations
):
    """LM with lane refill (``_LM_REFILL``: a lane takes the next window as
    soon as its window stops, every lane at its own iteration) against lane
    groups that run every iteration without packing: the windows' iterates
    do not depend on their lane, neighbours or start time, so every result
    is equal bit for bit; the per-iteration cost sums are summed in another
    order (1e-13). Three tasks of about four interleaved lane groups each,
    so windows enter lanes freed mid-run and each task's group drains at its
    end (checked: more windows than lanes per task, and some windows stop
    before the last iteration while others run on)."""
    from lrmfrf import _compiled_refine
    from lrmfrf.plants import wafer_stage

    U, Y = _stage_records(wafer_stage().G_y4, 3, 2200 * 3, seed=6)
    layout = LocalModelLayout(F=3, **PAPER)
    closed = fit_local_models(U, Y, layout)
    tasks = []
    refill = _compiled_refine._lm_refill_range

    def spy(*args):
        tasks.append(len(range(*args[-3:])))  # lane groups of the task
        return refill(*args)

    monkeypatch.setattr(_compiled_refine, "_lm_refill_range", spy)
    monkeypatch.setattr(_compiled_refine, "_LM_STAGES", ())
    monkeypatch.setattr(_compiled_refine, "sk_windows", functools.partial(
        _compiled_refine.sk_windows, n_threads=3))
    monkeypatch.setattr(_compiled_refine, "_REFILL_TASKS_PER_THREAD", 1)
    results = {}
    for on in (False, True):
        monkeypatch.setattr(_compiled_refine, "_LM_REFILL", on)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            results[on] = refine_local_models(
                U, Y, layout, closed, sk_iterations=sk_iterations,
                lm_iterations=lm_iterations, backend="numba",
            )
    ref, new = results.values()
    n_groups = -(-closed.slow_bins.size // _compiled_refine.LANES)
    assert len(tasks) == 3 and sum(tasks) == n_groups and min(tasks) >= 3
    assert new.lm_iterations == ref.lm_iterations == lm_iterations
    assert 0.2 < np.mean(new.converged) < 0.95
    for name in ("theta", "system", "rss", "system_var", "system_cov"):
        np.testing.assert_array_equal(
            getattr(new.local_fit, name), getattr(ref.local_fit, name), err_msg=name
        )
    np.testing.assert_array_equal(new.converged, ref.converged)
    np.testing.assert_array_equal(new.guarded, ref.guarded)
    np.testing.assert_array_equal(new.sk_cost_history, ref.sk_cost_history)
    np.testing.assert_allclose(new.cost_history, ref.cost_history, rtol=1e-13)


def _refill_and_groups(monkeypatch, U, Y, layout, n_threads=2, **params):
    """``refine_local_models`` through the compiled LM with lane refill and
    with lane groups that run every iteration (no packing)."""
    from lrmfrf import _compiled_refine

    closed = fit_local_models(U, Y, layout)
    monkeypatch.setattr(_compiled_refine, "_LM_STAGES", ())
    monkeypatch.setattr(_compiled_refine, "sk_windows", functools.partial(
        _compiled_refine.sk_windows, n_threads=n_threads))
    results = []
    for on in (True, False):
        monkeypatch.setattr(_compiled_refine, "_LM_REFILL", on)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            results.append(refine_local_models(U, Y, layout, closed,
                                               backend="numba", **params))
    return results


def _assert_bitwise_equal(new, ref):
    for name in ("theta", "system", "rss", "system_var", "system_cov"):
        np.testing.assert_array_equal(
            getattr(new.local_fit, name), getattr(ref.local_fit, name), err_msg=name
        )
    np.testing.assert_array_equal(new.converged, ref.converged)
    np.testing.assert_array_equal(new.guarded, ref.guarded)
    np.testing.assert_allclose(new.cost_history, ref.cost_history, rtol=1e-13)


def test_lm_lane_refill_passes_exact_fits_through(monkeypatch):
    """Exact in-class windows skip LM in the refill driver (queued for the
    results directly, between windows that do run LM): they keep the closed
    form's FRF (1e-8) and count as converged, and every result equals, bit
    for bit, that of lane groups without refill (two tasks)."""
    from lrmfrf.testing import in_class_data

    layout = LocalModelLayout(F=3, **PAPER)
    u, y, centres, G = in_class_data(layout, 600, rng=2)
    new, ref = _refill_and_groups(monkeypatch, dft(u), dft(y), layout,
                                  sk_iterations=2, lm_iterations=10)
    rows = np.searchsorted(new.local_fit.slow_bins, centres)
    assert rows.size >= 6 and not new.converged.all()  # LM ran elsewhere
    np.testing.assert_allclose(new.local_fit.system[rows], G, rtol=1e-8,
                               atol=1e-10)
    assert new.converged[rows].all()
    _assert_bitwise_equal(new, ref)


def test_lm_lane_refill_keeps_the_sk_guard_flag(monkeypatch):
    """A window the guard stopped during SK enters LM (as in numpy, LM runs
    from its last good estimate) and stays flagged ``guarded`` with refill
    too; P = 2 and a tight guard (jump = 0.5 sd) so that SK hits it."""
    from lrmfrf.plants import wafer_stage
    from lrmfrf.simulate import simulate

    F, N = 3, 3600
    rng = np.random.default_rng(8)
    system = wafer_stage().G_y4
    u = np.stack([multisine(N, rng=rng) for _ in range(2)])
    y = np.stack([simulate(system, u[p], F, snr_db=40, rng=rng).y_l
                  for p in range(2)])
    U, Y = dft(u), dft(y)
    layout = LocalModelLayout(F=F, n_experiments=2, **PAPER)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sk = refine_local_models(U, Y, layout, fit_local_models(U, Y, layout),
                                 sk_iterations=2, jump=0.5, backend="numba")
    assert sk.n_guarded > 10
    new, ref = _refill_and_groups(monkeypatch, U, Y, layout, sk_iterations=2,
                                  lm_iterations=10, jump=0.5)
    assert new.guarded[sk.guarded].all()
    _assert_bitwise_equal(new, ref)
