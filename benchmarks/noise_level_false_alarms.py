"""False alarms and detection of the experiments' unequal-noise test.

:func:`lrmfrf.uncertainty._noise_weights` (what ``experiment_noise_weights``
and the fit use) on records with equal noise on every experiment (false
alarm: a row weighted, or the warning that a flagged row is fitted with
one pooled noise level) and with experiment 1's noise std 2x and 4x that of the
others (detection: weighted).

Systems (``lrmfrf.plants.random_stage``, ``F`` its drawn
``downsampling_factor``): SISO ``G_y4`` open loop (``loop="open"``) and
closed loop, and MIMO ``G[0:2, 0:2]`` (closed-loop equivalent). ``P`` drawn
from 2, 3, 4; every experiment and input its own random-phase multisine
(``lrmfrf.signals.multisine``), simulated from rest (each experiment its own
transient), ``M = 400`` slow samples. White noise on the slow outputs, per
output ``snr`` dB (drawn from 25-70) below the noise-free output of
experiment 0. Local layout drawn (half window 6-24, degrees 1-4, denominator
0-7) until its residual dof per window is within 3-60 and its window fits.

Two seed sets: ``--set tune`` (stage seeds 0-11, record seeds from 0) and
``--set check`` (stage seeds 100-111, record seeds from 10000): the test's
constants were chosen on ``tune`` only.

Run (about 4 minutes for 300 records)::

    python benchmarks/noise_level_false_alarms.py --records 300 --set check

``--z Z`` runs the test at ``EQUAL_NOISE_Z = Z``; the last table gives the
share of records whose unweighted levels' statistic exceeds a grid of Z
(what ``--set tune`` chooses the threshold from).

To compare with an older version put its tree first on ``PYTHONPATH``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

if "--old" not in sys.argv:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lrmfrf.local_models import OneSidedSpectra  # noqa: E402
from lrmfrf.plants import random_stage  # noqa: E402
from lrmfrf.signals import multisine  # noqa: E402
from lrmfrf.simulate import simulate  # noqa: E402
from lrmfrf.uncertainty import _noise_weights, experiment_noise_levels  # noqa: E402
from lrmfrf.windows import LocalModelLayout  # noqa: E402

M = 400
BUCKETS = [(3, 6), (7, 12), (13, 20), (21, 35), (36, 60)]
KINDS = ("siso-open", "siso-closed", "mimo")
SEEDS = {"tune": (0, 0), "check": (100, 10000)}


def stage_system(kind, seed):
    if kind == "mimo":
        stage, draw = random_stage(seed, mimo=True)
        return stage.G[0:2, 0:2], draw.downsampling_factor
    stage, draw = random_stage(seed, loop="open" if kind == "siso-open" else "closed")
    return stage.G_y4, draw.downsampling_factor


def draw_layout(rng, F, P, n_u):
    """A layout whose residual dof per window is in a bucket drawn uniformly
    from BUCKETS (degrees drawn until one fits; None if none does)."""
    lo, hi = BUCKETS[int(rng.integers(0, len(BUCKETS)))]
    for _ in range(2000):
        hw = int(rng.integers(6, 25))
        layout = LocalModelLayout(
            F=F, n_experiments=P, n_inputs=n_u, half_window=hw,
            num_degree=int(rng.integers(1, 5)),
            transient_degree=int(rng.integers(1, 5)),
            den_degree=int(rng.integers(0, 8)))
        if lo <= layout.dof <= hi and 3 * layout.window + 2 * hw + 2 < M // 2:
            return layout
    return None


def record(system, F, P, n_u, snr_db, ratio, rng):
    N = M * F
    u = np.stack([[multisine(N, rng=rng) for _ in range(n_u)] for _ in range(P)])
    clean = np.stack([np.atleast_2d(simulate(system, u_p, F, noise_std=0.0).y_l)
                      for u_p in u])
    sigma = np.std(clean[0], axis=-1) * 10 ** (-snr_db / 20)
    scale = np.ones(P)
    scale[1] = ratio
    noise = rng.standard_normal(clean.shape) * sigma[None, :, None]
    return u, clean + noise * scale[:, None, None]


def test_statistic(spectra, layout):
    """The largest ``(ratio_p - ratio_q) / sd`` of
    :func:`lrmfrf.uncertainty.unequal_noise_rows` over the rows and the pairs
    whose ratio exceeds ``EQUAL_NOISE_RATIO`` (-inf if none)."""
    import lrmfrf.uncertainty as unc

    levels = experiment_noise_levels(spectra, layout)
    if levels is None:
        return -np.inf
    ratio = levels.ratio
    factor = np.log(ratio)[:, None] - np.log(ratio)[None, :]
    v = np.diagonal(levels.cov).T
    scale = np.sqrt(np.maximum(v[:, None] + v[None, :] - 2 * levels.cov, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (ratio[:, None] - ratio[None, :]) / scale
    z = np.where((factor > np.log(unc.EQUAL_NOISE_RATIO)) & np.isfinite(z), z, -np.inf)
    return float(z.max())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--records", type=int, default=300)
    parser.add_argument("--set", choices=sorted(SEEDS), default="check")
    parser.add_argument("--ratios", type=float, nargs="+", default=[1.0, 2.0, 4.0])
    parser.add_argument("--old", action="store_true",
                        help="import lrmfrf from PYTHONPATH, not this tree")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--z", type=float, default=None,
                        help="set lrmfrf.uncertainty.EQUAL_NOISE_Z to this")
    args = parser.parse_args(argv)
    import lrmfrf.uncertainty as unc

    if args.z is not None:
        unc.EQUAL_NOISE_Z = args.z
    stage0, record0 = SEEDS[args.set]
    systems = {}
    rows = []  # (ratio, kind, P, dof, outcome)
    start = time.perf_counter()
    for i in range(args.records):
        rng = np.random.default_rng(record0 + i)
        kind = KINDS[i % 3]
        seed = stage0 + int(rng.integers(0, 12))
        if (kind, seed) not in systems:
            systems[kind, seed] = stage_system(kind, seed)
        system, F = systems[kind, seed]
        n_u = 2 if kind == "mimo" else 1
        P = int(rng.integers(2, 5))
        layout = draw_layout(rng, F, P, n_u)
        if layout is None:
            continue
        snr = float(rng.uniform(25, 70))
        for ratio in args.ratios:
            u, y = record(system, F, P, n_u, snr, ratio,
                          np.random.default_rng([record0 + i, int(ratio * 10)]))
            spectra = OneSidedSpectra.from_records(u, y, F)
            weights, problem = _noise_weights(spectra, layout, 16)
            outcome = "W" if weights is not None else ("!" if problem else ".")
            rows.append((ratio, kind, P, layout.dof, outcome,
                         test_statistic(spectra, layout)))
    lines = []

    def emit(text):
        print(text, flush=True)
        lines.append(text)

    new = hasattr(unc.ExperimentNoiseLevels, "__dataclass_fields__") and (
        "cov" in unc.ExperimentNoiseLevels.__dataclass_fields__)
    kind = "quadratic-form covariance, linear" if new else "Satterthwaite dof, log"
    test = (f"{kind} difference > {unc.EQUAL_NOISE_Z:g} sd and ratio > "
            f"{unc.EQUAL_NOISE_RATIO:g}")
    emit(f"{args.records} records per ratio, seed set {args.set!r}, M = {M}, "
         f"test: {test} ({unc.__file__}), {time.perf_counter() - start:.0f} s")
    emit("W: a row weighted, !: flagged but warned instead (pooled fit); "
         "false alarm = W or ! at ratio 1; detection = W")
    emit("| noise std ratio | residual dof per window | records | W | ! | "
         "flagged % |")
    emit("|---|---|---|---|---|---|")
    for ratio in args.ratios:
        sel = [r for r in rows if r[0] == ratio]
        for lo, hi in BUCKETS + [(3, 60)]:
            b = [r for r in sel if lo <= r[3] <= hi]
            if not b:
                continue
            w = sum(r[4] == "W" for r in b)
            bang = sum(r[4] == "!" for r in b)
            label = f"{lo}-{hi}" if (lo, hi) != (3, 60) else "all"
            emit(f"| {ratio:g} | {label} | {len(b)} | {w} | {bang} | "
                 f"{100 * (w + bang) / len(b):.1f} |")
    emit("")
    emit("| noise std ratio | kind | P | records | W | ! |")
    emit("|---|---|---|---|---|---|")
    for ratio in args.ratios:
        for kind in KINDS:
            for P in (2, 3, 4):
                b = [r for r in rows if r[0] == ratio and r[1] == kind and r[2] == P]
                emit(f"| {ratio:g} | {kind} | {P} | {len(b)} | "
                     f"{sum(r[4] == 'W' for r in b)} | "
                     f"{sum(r[4] == '!' for r in b)} |")
    emit("")
    emit("The test's statistic on the unweighted levels (largest standardised "
         "difference over the pairs whose ratio exceeds EQUAL_NOISE_RATIO; "
         "-inf: none): records above z, % (the first step's flag; W needs the "
         "weighted re-estimation to settle too)")
    grid = (2.5, 3.0, 3.25, 3.5, 3.75, 4.0)
    emit("| noise std ratio | residual dof per window | "
         + " | ".join(f"z > {z:g}" for z in grid) + " |")
    emit("|---|---|" + "---|" * len(grid))
    for ratio in args.ratios:
        sel = [r for r in rows if r[0] == ratio]
        for lo, hi in BUCKETS + [(3, 60)]:
            b = np.array([r[5] for r in sel if lo <= r[3] <= hi])
            if not b.size:
                continue
            label = f"{lo}-{hi}" if (lo, hi) != (3, 60) else "all"
            emit(f"| {ratio:g} | {label} | "
                 + " | ".join(f"{100 * np.mean(b > z):.1f}" for z in grid) + " |")
    if 1.0 in args.ratios:
        top = sorted((r[5] for r in rows if r[0] == 1.0), reverse=True)[:5]
        emit("")
        emit("largest statistics at equal noise: "
             + ", ".join(f"{t:.2f}" for t in top))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
