"""plant_from_closed_loop: the covariance between output rows of G_eq.

Monte Carlo of the plant's ``frf_std_`` from closed-loop data when the noise is
fed back (it then reaches several outputs, and the errors of the rows of
``G_eq`` are correlated), on three cases:

* ``slow``: the 3x2 slow-rate loop of ``benchmarks/closed_loop_nonsquare.py``
  (``G[0:3, 0:2]`` of ``random_stage(3, mimo=True)``, a 2x2 lag controller on
  outputs 0 and 2 at ``F Ts``, F = 3, N = 1200, P = 2 orthogonal multisines,
  40 dB slow noise on each output, in the loop);
* ``fast``: the same plant and controller at the fast rate (``Ts``, gain
  halved: the fast loop of gain 3 is unstable), white noise on the fast
  outputs in the loop (1 % of each output's std), ``y_l = y_h[::F]``;
* ``open``: the same plant in open loop with independent 40 dB noise per
  output, through ``plant_from_closed_loop`` with the slow controller as if
  it were in the loop (the rows are independent: the cross terms must not
  change anything).

Per run: LRM (defaults) from r to y_l, then ``plant_from_closed_loop`` with
the rows independent (``frf_cov_`` only: the old propagation) and with the
estimator's ``frf_joint_cov_`` (the covariance between rows). Printed per
entry, at the bins where the loop gain ``||C(z) P_fb||`` exceeds 0.3 and over
all bins but the DC and slow-Nyquist band sets: the median over bins of the
predicted std (RMS over runs) over the Monte-Carlo std; the same with the
Monte-Carlo covariance of ``G_eq`` fed to the propagation (per row, and
between rows too), and the estimator's correlations (its mean
``frf_joint_cov_`` over the runs) on the Monte-Carlo variances; the median
|corr| of the errors of ``G_eq`` between rows 0 and 2, measured and
predicted; and the time of ``frf_joint_cov_`` against that of the fit.

Run::

    python benchmarks/closed_loop_row_covariance.py --runs 40
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

import control
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lrmfrf import LRMBeyondNyquist, plant_from_closed_loop  # noqa: E402
from lrmfrf.plants import random_stage  # noqa: E402
from lrmfrf.signals import orthogonal_multisines  # noqa: E402
from lrmfrf.simulate import simulate, simulate_slow_feedback, true_frf  # noqa: E402

F, N, FB = 3, 1200, [0, 2]


def _setup(gain):
    stage, _ = random_stage(3, mimo=True)
    plant = stage.G[0:3, 0:2]
    ts = plant.dt
    truth = true_frf(plant, N)
    mix = gain / np.abs(truth).max() * np.array([[1.0, 0.3], [-0.2, 0.8]])
    return plant, ts, truth, mix


def _fast_loop_system(plant, controller):
    """The fast closed loop from [r; v] (plant inputs, output noise) to y."""
    n_y = plant.noutputs
    zeros = np.zeros((plant.nstates, n_y))
    augmented = control.ss(plant.A, np.hstack([plant.B, zeros]),
                           plant.C, np.hstack([plant.D, np.eye(n_y)]), plant.dt)
    select = np.eye(n_y)[FB]  # S
    K = control.ss(controller.A, controller.B @ select,
                   np.vstack([controller.C, np.zeros((n_y, controller.nstates))]),
                   np.vstack([controller.D @ select, np.zeros((n_y, n_y))]),
                   plant.dt)
    return control.feedback(augmented, K)


def _records(case, plant, controller, loop, r, run):
    if case == "slow":
        return np.stack([simulate_slow_feedback(
            plant, controller, r[p], F, feedback_outputs=FB, snr_db=40,
            rng=100 * run + p).y_l for p in range(2)])
    if case == "open":
        return np.stack([simulate(plant, r[p], F, snr_db=40,
                                  rng=100 * run + p).y_l for p in range(2)])
    rng = np.random.default_rng(run)
    out = []
    for p in range(2):
        clean = simulate(loop, np.vstack([r[p], np.zeros((3, N))]), F).y_h
        v = 0.01 * clean.std(axis=1)[:, None] * rng.standard_normal((3, N))
        out.append(simulate(loop, np.vstack([r[p], v]), F).y_l)
    return np.stack(out)


def _ratios(values, mc, high, inner):
    return (np.round(np.median((values / mc)[..., high], axis=-1), 3).tolist(),
            np.round(np.median((values / mc)[..., inner], axis=-1), 3).tolist())


def run_case(case, runs, gain):
    plant, ts, truth, mix = _setup(gain)
    if case == "fast":
        mix = mix / 2
    dt = ts if case == "fast" else F * ts
    controller = control.ss(np.diag([0.8, 0.8]), np.eye(2), 0.2 * mix, mix, dt)
    fast_twin = control.ss(controller.A, controller.B, controller.C, controller.D, ts)
    Cz = true_frf(fast_twin, N)
    loop_gain = np.array([np.linalg.norm(Cz[:, :, k] @ truth[FB, :, k], 2)
                          for k in range(N // 2 + 1)])
    M = N // F
    bins = np.arange(N // 2 + 1)
    inner = (bins % M != 0) & (bins % M != M // 2)
    high = (loop_gain > 0.3) & inner
    loop = _fast_loop_system(plant, controller) if case == "fast" else None
    r = orthogonal_multisines(2, N, rng=0)
    closed, plants, old, new, joints = [], [], [], [], []
    t_fit = t_joint = 0.0
    for run in range(runs):
        y = _records(case, plant, controller, loop, r, run)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            est = LRMBeyondNyquist().fit(r, y, F, sample_time=ts)
            t_fit += time.perf_counter() - t0
        rows_only = SimpleNamespace(**{
            name: getattr(est, name) for name in (
                "frequencies_", "frf_", "frf_std_", "frf_cov_", "valid_",
                "sample_time_", "downsampling_factor_", "n_inputs_", "n_outputs_")})
        result = plant_from_closed_loop(rows_only, controller, FB)
        closed.append(est.frf_)
        plants.append(result.frf_)
        old.append(result.frf_std_)
        if hasattr(type(est), "frf_joint_cov_"):
            t0 = time.perf_counter()
            est.frf_joint_cov_  # noqa: B018 (computed on first access)
            t_joint += time.perf_counter() - t0
            new.append(plant_from_closed_loop(est, controller, FB).frf_std_)
            joints.append(est.frf_joint_cov_)
    g, p = np.array(closed), np.array(plants)
    mc = np.sqrt(np.mean(np.abs(p - p.mean(axis=0)) ** 2, axis=0))
    d = g - g.mean(axis=0)
    joint = np.einsum("royk,rpzk->oypzk", d, d.conj()) / runs
    base = dict(frequencies_=est.frequencies_, frf_=g.mean(axis=0),
                frf_std_=np.sqrt(np.abs(np.einsum("oioik->oik", joint))),
                valid_=np.ones(g.shape[1:], bool), sample_time_=ts,
                downsampling_factor_=F, n_inputs_=2, n_outputs_=3)
    per_row = np.einsum("oiojk->oijk", joint)
    mc_rows = plant_from_closed_loop(SimpleNamespace(**base, frf_cov_=per_row),
                                     controller, FB).frf_std_
    mc_joint = plant_from_closed_loop(
        SimpleNamespace(**base, frf_cov_=per_row, frf_joint_cov_=joint),
        controller, FB).frf_std_
    corr = np.abs(np.mean(d[:, 0, 0] * d[:, 2, 0].conj(), axis=0)) / np.sqrt(
        np.mean(np.abs(d[:, 0, 0]) ** 2, axis=0)
        * np.mean(np.abs(d[:, 2, 0]) ** 2, axis=0))
    # the estimator's G_eq std against the MC std of G_eq
    geq = np.sqrt(np.mean(np.array([est.frf_std_]) ** 2, axis=0))
    print(f"case {case}: loop rate {'fast' if case == 'fast' else 'slow'}, "
          f"{runs} runs, max loop gain {loop_gain.max():.2f}, {high.sum()} bins "
          f"with loop gain > 0.3 (of {inner.sum()} inner bins); ratios predicted "
          "std / MC std of the plant, median over those bins | over all inner "
          "bins, per entry (rows: outputs)")
    print("  rows independent (old), estimator's frf_cov_:    %s | %s"
          % _ratios(np.sqrt(np.mean(np.array(old) ** 2, axis=0)), mc, high, inner))
    if new:
        print("  with the estimator's frf_joint_cov_ (new):       %s | %s"
              % _ratios(np.sqrt(np.mean(np.array(new) ** 2, axis=0)), mc, high,
                        inner))
    print("  MC cov of G_eq, rows independent:                %s | %s"
          % _ratios(mc_rows, mc, high, inner))
    print("  MC cov of G_eq, between rows too:                %s | %s"
          % _ratios(mc_joint, mc, high, inner))
    if joints:
        # the estimator's correlations (mean joint over runs) on the MC's
        # variances: what the correlation alone gives
        mean = np.mean(joints, axis=0)
        own = np.sqrt(np.abs(np.einsum("oioik->oik", mean)))
        mc_own = np.sqrt(np.abs(np.einsum("oioik->oik", joint)))
        scale = mc_own / own
        hybrid = mean * scale[:, :, None, None] * scale[None, None]
        print("  estimator's correlations on the MC variances:    %s | %s"
              % _ratios(plant_from_closed_loop(SimpleNamespace(
                  **base, frf_cov_=np.einsum("oiojk->oijk", hybrid),
                  frf_joint_cov_=hybrid), controller, FB).frf_std_, mc, high,
                  inner))
        predicted_corr = np.abs(mean[0, 0, 2, 0]) / (own[0, 0] * own[2, 0])
    mc_g = np.sqrt(np.mean(np.abs(d) ** 2, axis=0))
    print("  G_eq: last run's frf_std_ / MC std, median (high | inner): %s | %s"
          % _ratios(geq, mc_g, high, inner))
    print(f"  |corr| of G_eq errors, rows 0 and 2 (input 0): "
          f"{np.median(corr[high]):.2f} where the loop gain > 0.3, "
          f"{np.median(corr[inner & ~high]):.2f} elsewhere")
    if joints:
        print(f"  |corr| the estimator predicts (mean frf_joint_cov_): "
              f"{np.median(predicted_corr[high]):.2f} and "
              f"{np.median(predicted_corr[inner & ~high]):.2f}")
    if new:
        print(f"  time: fit {1e3 * t_fit / runs:.0f} ms, frf_joint_cov_ "
              f"{1e3 * t_joint / runs:.0f} ms per run")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=40)
    parser.add_argument("--gain", type=float, default=3.0)
    parser.add_argument("--cases", nargs="+", default=["slow", "fast", "open"])
    args = parser.parse_args(argv)
    for case in args.cases:
        run_case(case, args.runs, args.gain)


if __name__ == "__main__":
    main()
