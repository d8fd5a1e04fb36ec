"""False alarms of the experiment noise weights on equal-noise SISO records.

SISO fits with several experiments are weighted when the experiments' noise
levels clearly differ (:func:`lrmfrf.uncertainty.experiment_noise_weights`).
This counts how often records whose experiments have the SAME white noise
level are weighted anyway (a false alarm) or refused with the pooled-fit
``UserWarning``, and checks that the fits that are not weighted are the
pooled fit bit for bit.

Records: ``lrmfrf.plants.random_stage(seed, downsampling_factor=F, loop=...)``
(closed loop ``G_y4`` / ``G_z``, or the open-loop plant), F = 2..5, P = 2..4,
M in {200, 400, 1000}, SNR 25-70 dB (noise std from the RMS of experiment 0's
noise-free output, the same in every experiment), independent random-phase
multisines; in half of the records the experiments' input RMS differ (by up
to 4x: equal noise, unequal SNR and misfit). Default
``LRMBeyondNyquist()`` (and ``LPMBeyondNyquist()`` with ``--lpm``).

Run (about 2 minutes for 240 records)::

    python benchmarks/siso_equal_noise_weights.py --records 240 \\
        --out benchmarks/results/x.txt
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lrmfrf.estimators.local as local  # noqa: E402
from lrmfrf import LPMBeyondNyquist, LRMBeyondNyquist  # noqa: E402
from lrmfrf.plants import random_stage  # noqa: E402
from lrmfrf.signals import multisine  # noqa: E402
from lrmfrf.simulate import simulate, true_frf  # noqa: E402

CHANNELS = [("closed", "G_y4"), ("closed", "G_z"), ("open", "G_y4")]


def record(i, base_seed):
    rng = np.random.default_rng([base_seed, i])
    F = int(rng.integers(2, 6))
    P = int(rng.integers(2, 5))
    M = int(rng.choice([200, 400, 1000]))
    snr = float(rng.uniform(25, 70))
    loop, channel = CHANNELS[i % len(CHANNELS)]
    seed = int(rng.integers(0, 10_000))
    system = getattr(random_stage(seed, downsampling_factor=F, loop=loop)[0],
                     channel)
    N = M * F
    u = np.stack([multisine(N, rng=rng) for _ in range(P)])
    unequal_inputs = i % 2 == 1
    if unequal_inputs:
        u *= rng.uniform(1.0, 4.0, size=P)[:, None]
    clean = np.stack([simulate(system, u_p, F, noise_std=0.0).y_l for u_p in u])
    sigma = np.std(clean[0]) * 10 ** (-snr / 20)
    y = clean + sigma * rng.standard_normal(clean.shape)
    info = dict(F=F, P=P, M=M, snr=snr, loop=loop, channel=channel, seed=seed,
                unequal_inputs=unequal_inputs)
    return list(u), list(y), F, info, system


def fit(est, u, y, F):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est.fit(u, y, F)
    # the pooled-fit warning of experiment_noise_weights (any of its reasons)
    pooled = [w for w in caught if "pooled noise level" in str(w.message)]
    return est, bool(pooled)


def _without_weights(make, u, y, F):
    original = local.experiment_noise_weights
    local.experiment_noise_weights = lambda spectra, layout, **_: None
    try:
        return fit(make(), u, y, F)[0]
    finally:
        local.experiment_noise_weights = original


def weighted_error_ratio(make, est, u, y, F, system):
    """Median relative error against the truth of the weighted fit ``est``
    over that of the same fit without the weights (valid bins of both)."""
    ref = _without_weights(make, u, y, F)
    truth = true_frf(system, len(u[0]))
    ok = est.valid_ & ref.valid_ & np.isfinite(truth) & (truth != 0)
    err = [np.median(np.abs(g.frf_[ok] - truth[ok]) / np.abs(truth[ok]))
           for g in (est, ref)]
    return float(err[0] / err[1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=int, default=240)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--lpm", action="store_true")
    parser.add_argument("--compare-every", type=int, default=4,
                        help="compare every k-th unweighted fit with the pooled "
                             "fit bit for bit")
    parser.add_argument("--error", action="store_true",
                        help="for every weighted record, also the median "
                             "relative error against the truth of the weighted "
                             "fit over that of the pooled (unweighted) fit")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    make = LPMBeyondNyquist if args.lpm else LRMBeyondNyquist
    lines = []

    def emit(text):
        print(text, flush=True)
        lines.append(text)

    emit(f"{make.__name__}(), {args.records} equal-noise SISO records, seed "
         f"{args.seed}, F 2-5, P 2-4, M 200/400/1000, 25-70 dB")
    weighted, warned, compared, differ = [], [], 0, 0
    infos = []
    error_ratios = []
    start = time.perf_counter()
    for i in range(args.records):
        u, y, F, info, system = record(i, args.seed)
        infos.append(info)
        est, pooled = fit(make(), u, y, F)
        w = est.noise_weights_
        assert w.shape == (info["P"],)
        if np.any(w != 1.0):
            ratio = (w.max() / w.min()) ** 2
            weighted.append((i, info, ratio))
            note = ""
            if args.error:
                err = weighted_error_ratio(make, est, u, y, F, system)
                error_ratios.append(err)
                note = f", error weighted / pooled {err:.3f}"
            emit(f"weighted: record {i} {info} variance ratio {ratio:.2f}{note}")
        elif pooled:
            warned.append((i, info))
            emit(f"pooled with warning: record {i} {info}")
        elif i % args.compare_every == 0:
            ref = _without_weights(make, u, y, F)
            compared += 1
            same = all(np.array_equal(getattr(est, a), getattr(ref, a),
                                      equal_nan=True)
                       for a in ("frf_", "frf_std_", "frf_cov_", "valid_",
                                 "noise_variance_", "transient_"))
            differ += not same
    seconds = time.perf_counter() - start
    emit(f"weighted (false alarms): {len(weighted)} / {args.records}; pooled with "
         f"the UserWarning: {len(warned)} / {args.records}; unweighted fits "
         f"compared with the pooled fit: {compared}, not bit-identical: {differ} "
         f"({seconds:.0f} s)")
    if error_ratios:
        e = np.array(error_ratios)
        emit(f"median relative error against the truth, weighted fit / pooled "
             f"fit, over the {e.size} weighted records: median {np.median(e):.3f}, "
             f"min {e.min():.3f}, max {e.max():.3f}, worse than pooled by > 5 %: "
             f"{int(np.sum(e > 1.05))}")
    flagged = {i for i, *_ in weighted} | {i for i, _ in warned}
    for name, key in (("closed loop", lambda d: d["loop"] == "closed"),
                      ("open loop", lambda d: d["loop"] == "open"),
                      ("unequal input RMS", lambda d: d["unequal_inputs"]),
                      ("equal input RMS", lambda d: not d["unequal_inputs"])):
        ids = [i for i, d in enumerate(infos) if key(d)]
        emit(f"  {name}: {sum(i in flagged for i in ids)} of {len(ids)} weighted "
             "or warned")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
