"""plant_from_closed_loop on a non-square loop: frf_std_ against a Monte Carlo.

Plant: ``G[0:3, 0:2]`` of ``lrmfrf.plants.random_stage(3, mimo=True)`` (3
outputs, 2 inputs, stable), in a loop whose 2x2 dynamic controller (a lag times
a fixed mixing matrix, loop gain up to ``--gain`` x 2.2 at low frequencies)
reads outputs 0 and 2 and runs at the slow rate (F = 3, vision in the loop,
``simulate_slow_feedback``), N = 1200, P = 2 orthogonal multisines, 40 dB per
output, ``--runs`` noise realisations. LRM (defaults) from r to y_l, then
``plant_from_closed_loop``. Two noise placements:

* in the loop (the measured slow outputs, noise included, feed the controller:
  the realistic case), and
* outside it (noise added to the noise-free closed-loop outputs).

Printed per entry, at the bins where the loop gain ``||C(z) P_fb||`` exceeds
0.3: the median over those bins of the predicted std of the plant (RMS over
runs) over its Monte-Carlo std, with the estimator's covariance (its
``frf_joint_cov_``, between output rows too, since
``benchmarks/closed_loop_row_covariance.py``; ``frf_cov_`` alone before) and
with the Monte-Carlo per-row covariance of ``G_eq`` fed to the same
propagation (rows independent); and the median correlation between the errors
of ``G_eq`` in the two fed-back rows. The noise in the loop correlates the
rows: with the rows taken as independent the propagation over-predicts the
plant's std even with the exact per-row covariance.

Run::

    python benchmarks/closed_loop_nonsquare.py --runs 40
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import control
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lrmfrf import LRMBeyondNyquist, plant_from_closed_loop  # noqa: E402
from lrmfrf.plants import random_stage  # noqa: E402
from lrmfrf.signals import orthogonal_multisines  # noqa: E402
from lrmfrf.simulate import simulate_slow_feedback, true_frf  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=40)
    parser.add_argument("--gain", type=float, default=3.0)
    args = parser.parse_args(argv)
    stage, _ = random_stage(3, mimo=True)
    plant = stage.G[0:3, 0:2]
    ts, F, N, fb = plant.dt, 3, 1200, [0, 2]
    truth = true_frf(plant, N)
    mix = args.gain / np.abs(truth).max() * np.array([[1.0, 0.3], [-0.2, 0.8]])
    controller = control.ss(np.diag([0.8, 0.8]), np.eye(2), 0.2 * mix, mix, F * ts)
    fast_twin = control.ss(controller.A, controller.B, controller.C, controller.D, ts)
    Cz = true_frf(fast_twin, N)  # C(z) at the fast bins (its slow bin's value)
    loop_gain = np.array([np.linalg.norm(Cz[:, :, k] @ truth[fb, :, k], 2)
                          for k in range(N // 2 + 1)])
    high = loop_gain > 0.3
    high[0] = high[-1] = False
    r = orthogonal_multisines(2, N, rng=0)
    print(f"3x2 plant, slow loop on outputs {fb}, gain {args.gain} (max loop gain "
          f"{loop_gain.max():.2f}), {args.runs} runs, {high.sum()} bins with loop "
          "gain > 0.3; ratios predicted std / MC std of the plant, median over "
          "those bins, per entry (rows: outputs)")
    for in_loop in (True, False):
        closed, plants, stds = [], [], []
        for run in range(args.runs):
            if in_loop:
                y = np.stack([simulate_slow_feedback(
                    plant, controller, r[p], F, feedback_outputs=fb, snr_db=40,
                    rng=100 * run + p).y_l for p in range(2)])
            else:
                sims = [simulate_slow_feedback(plant, controller, r[p], F,
                                               feedback_outputs=fb) for p in range(2)]
                std = np.mean([s.y_l.std(axis=1) for s in sims], axis=0) / 100
                rng = np.random.default_rng(run)
                y = np.stack([s.y_l + std[:, None] * rng.standard_normal(s.y_l.shape)
                              for s in sims])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                est = LRMBeyondNyquist().fit(r, y, F, sample_time=ts)
            result = plant_from_closed_loop(est, controller, fb)
            closed.append(est.frf_)
            plants.append(result.frf_)
            stds.append(result.frf_std_)
        g, p = np.array(closed), np.array(plants)
        mc = np.sqrt(np.mean(np.abs(p - p.mean(axis=0)) ** 2, axis=0))
        predicted = np.sqrt(np.mean(np.array(stds) ** 2, axis=0))
        d = g - g.mean(axis=0)
        cov = np.einsum("royk,rozk->oyzk", d, d.conj()) / args.runs
        exact = SimpleNamespace(
            frequencies_=est.frequencies_, frf_=g.mean(axis=0),
            frf_std_=np.sqrt(np.einsum("oiik->oik", cov).real), frf_cov_=cov,
            valid_=np.ones(g.shape[1:], bool), sample_time_=ts,
            downsampling_factor_=F, n_inputs_=2, n_outputs_=3)
        with_mc_cov = plant_from_closed_loop(exact, controller, fb).frf_std_
        corr = np.abs(np.mean(d[:, 0, 0] * d[:, 2, 0].conj(), axis=0)) / np.sqrt(
            np.mean(np.abs(d[:, 0, 0]) ** 2, axis=0)
            * np.mean(np.abs(d[:, 2, 0]) ** 2, axis=0))
        print(f"noise {'in' if in_loop else 'outside'} the loop:")
        print("  with the estimator's covariance:",
              np.round(np.median((predicted / mc)[..., high], axis=-1), 3).tolist())
        print("  with the MC per-row cov of G_eq:",
              np.round(np.median((with_mc_cov / mc)[..., high], axis=-1), 3).tolist())
        print("  with the estimator's covariance, median over all bins but DC "
              "and Nyquist:",
              np.round(np.median((predicted / mc)[..., 1:-1], axis=-1), 3).tolist())
        print(f"  |corr| of G_eq errors, rows 0 and 2 (input 0): "
              f"{np.median(corr[high]):.2f} at those bins, "
              f"{np.median(corr[~high]):.2f} elsewhere")


if __name__ == "__main__":
    main()
