"""Is ``frf_std_`` calibrated on stages nobody tuned on? (issue 15, item 2)

For each stage (``lrmfrf.plants.random_stage(seed, downsampling_factor=F)``,
its closed-loop channels ``G_y4`` and ``G_z`` and, with ``--open``, the
open-loop plant's; and ``wafer_stage()``), one random-phase multisine of
``N = 400 F`` samples (``M = 400`` slow samples) is simulated without noise;
``n_runs`` noise realisations at a given output SNR are added and
``LRMBeyondNyquist`` (default degrees; at ``F = 5`` the half window 23, which
leaves 10 residual degrees of freedom) is fitted to each. Every covariance
route of :mod:`lrmfrf.uncertainty` is evaluated on the same fits, and per
route the table reports, over the stages:

* ``ratio``: the median over the valid bins (all runs valid, finite truth,
  not DC) of the predicted std (root mean square over the runs) divided by
  the Monte-Carlo std (the spread of the estimates around their Monte-Carlo
  mean);
* ``cover``: the fraction of estimates within 2 predicted std of the truth
  (``lrmfrf.simulate.true_frf``); 98.2 % for a complex Gaussian with a known
  std.

``default`` is the estimator's own ``frf_std_`` (the default ``std_method``,
compiled and streamed); the other routes are recomputed in numpy from its
``local_fit_``. ``eiv_true`` is the ``eiv`` sandwich with the true noise variance
(``M sigma^2``): it separates the shape of the covariance from the estimate
of the noise level. Run::

    nice -n 5 python benchmarks/generalisation_std.py --seeds 1000-1019 \
        --F 2 3 5 --snr 25 30 45 70 --runs 100

Tuning stages: seeds 1000-1019; held-out: seeds 2000-2019. 2x2 stages
(``random_stage(seed, downsampling_factor=F, mimo=True)`` and
``mimo_wafer_stage``, :func:`mimo_monte_carlo`), one F per process::

    nice -n 5 python benchmarks/generalisation_std.py --mimo --F 3 \
        --seeds 1000-1009 --snr 30 45 70 --runs 30 --routes default eiv_robust
"""

from __future__ import annotations

import argparse
import csv
import sys
import time

import numpy as np

from lrmfrf import LRMBeyondNyquist
from lrmfrf.local_models import dft, one_sided_fast_grid
from lrmfrf.plants import random_stage, wafer_stage
from lrmfrf.signals import multisine, orthogonal_multisines
from lrmfrf.simulate import simulate, true_frf
from lrmfrf.uncertainty import (
    band_covariance,
    robust_band_covariance,
    variance_terms,
)

ROUTES = ("default", "lemma2", "eiv", "hc", "eiv_pooled", "eiv_dof", "eiv_robust",
          "eiv_true")

#: Half window per F: the default 18, and 23 at F = 5 (10 residual dof).
HALF_WINDOW = {2: 18, 3: 18, 4: 18, 5: 23}

#: Slow samples per record.
N_SLOW = 400


def stage_systems(seeds, F, *, loops=("closed",), channels=("G_y4", "G_z"),
                  wafer=True, alternate=False):
    """``(name, system)`` of every channel of every stage to measure.

    With ``alternate``, stage ``i`` (in the order of ``seeds``) contributes one
    system only: loop ``loops[i % len(loops)]`` and channel
    ``channels[(i // len(loops)) % len(channels)]`` (all combinations in turn,
    at a quarter of the cost).
    """
    out = []
    for i, seed in enumerate(seeds):
        pairs = [(lp, ch) for lp in loops for ch in channels]
        if alternate:
            pairs = [(loops[i % len(loops)],
                      channels[(i // len(loops)) % len(channels)])]
        for loop in sorted({lp for lp, _ in pairs}):
            stage, _ = random_stage(seed, downsampling_factor=F, loop=loop)
            for lp, ch in pairs:
                if lp == loop:
                    out.append((f"s{seed}-{loop}-{ch}", getattr(stage, ch)))
    if wafer:
        stage = wafer_stage()
        for ch in channels:
            out.append((f"wafer-{ch}", getattr(stage, ch)))
    return out


def route_variances(U, Y, est, routes, true_noise_variance):
    """Per route, the fast-grid variance of one fit, shape (N//2+1,)."""
    out = {}
    if "default" in routes:  # the estimator's own frf_std_
        out["default"] = est.frf_std_**2
        routes = [r for r in routes if r != "default"]
        if not routes:
            return out
    fit, layout = est.local_fit_, est.layout_
    terms = variance_terms(U, Y, layout, fit.theta, fit.slow_bins)
    M = Y.shape[1]
    N = M * layout.F
    for route in routes:
        if route == "eiv_robust":  # + the neighbour term (local models)
            cov = robust_band_covariance(terms.eiv_lead, terms.eiv_trace, fit, M)
        elif route == "eiv_true":
            s2 = np.full(fit.slow_bins.size, true_noise_variance)
            cov = band_covariance(terms, layout, "eiv", noise_variance=s2)
        else:
            cov = band_covariance(terms, layout, route, slow_bins=fit.slow_bins,
                                  n_slow=M)
        var = np.real(np.diagonal(cov, axis1=1, axis2=2))
        out[route] = one_sided_fast_grid(var, N, layout.F, conj=False)
    return out


def monte_carlo(system, F, snr_db, n_runs, seed, routes=ROUTES, half_window=None):
    """Std ratio and 2-std coverage of each route on one system.

    Returns
    -------
    dict
        ``{route: (ratio, coverage)}`` and ``"bias"``: median over the bins
        of |MC mean - truth| / MC std.
    """
    rng = np.random.default_rng(seed)
    N = N_SLOW * F
    u = multisine(N, rms=1.44, rng=rng)
    clean = simulate(system, u, F, snr_db=snr_db, rng=rng)
    sigma = float(clean.noise_std)
    y_clean = clean.y_l_clean
    truth = true_frf(system, N)
    n = HALF_WINDOW[F] if half_window is None else half_window
    U = dft(u)[None]
    estimates, variances = [], {r: [] for r in routes}
    for _ in range(n_runs):
        y = y_clean + sigma * rng.standard_normal(y_clean.size)
        est = LRMBeyondNyquist(half_window=n).fit(u, y, F)
        estimates.append(est.frf_)
        var = route_variances(U, dft(y)[None], est, routes, N_SLOW * sigma**2)
        for r in routes:
            variances[r].append(var[r])
    estimates = np.array(estimates)
    mean = estimates.mean(axis=0)
    # unbiased (n_runs - 1): with the mean estimated from the same runs the
    # plain mean square is low by (n_runs - 1) / n_runs
    mc_std = np.sqrt(np.sum(np.abs(estimates - mean) ** 2, axis=0) / (n_runs - 1))
    bins = np.all(np.isfinite(estimates), axis=0) & np.isfinite(truth) & (mc_std > 0)
    bins[0] = False
    error = np.abs(estimates[:, bins] - truth[bins])
    out = {
        "bias": float(np.median(np.abs(mean - truth)[bins] / mc_std[bins])),
        # the best coverage any std can give: within 2 MC std of the truth
        "mc_cover": float(np.mean(error <= 2 * mc_std[bins])),
    }
    for r in routes:
        var = np.array(variances[r])[:, bins]
        predicted = np.sqrt(np.mean(var, axis=0))
        ratio = float(np.median(predicted / mc_std[bins]))
        coverage = float(np.mean(error <= 2 * np.sqrt(var)))
        out[r] = (ratio, coverage)
    return out


def std_table(seeds, snrs, Fs, n_runs, *, routes=ROUTES, loops=("closed",),
              channels=("G_y4", "G_z"), wafer=True, alternate=False, seed=0,
              progress=None):
    """Monte-Carlo rows, one per (F, SNR, system).

    Parameters
    ----------
    seeds : iterable of int
        Random-stage seeds.
    snrs : iterable of float
        Output SNRs in dB.
    Fs : iterable of int
        Downsampling factors.
    n_runs : int
        Noise realisations per system and SNR.
    routes : tuple of str
        Routes of :mod:`lrmfrf.uncertainty` and ``"eiv_true"``.
    loops, channels, wafer, alternate
        Which systems (see :func:`stage_systems`).
    seed : int
        Seed of the multisines and noise.
    progress : callable, optional
        Called with each row.

    Returns
    -------
    list of dict
        Keys ``F``, ``snr_db``, ``system``, ``bias`` (median |MC mean - truth|
        / MC std), ``mc_cover`` (fraction within 2 MC std of the truth: the
        coverage of a perfectly calibrated std) and per route
        ``<route>_ratio`` and ``<route>_cover``.
    """
    rows = []
    for F in Fs:
        systems = stage_systems(seeds, F, loops=loops, channels=channels,
                                wafer=wafer, alternate=alternate)
        for snr in snrs:
            for i, (name, system) in enumerate(systems):
                res = monte_carlo(system, F, snr, n_runs, seed + 1000 * i + F,
                                  routes=routes)
                row = {"F": F, "snr_db": snr, "system": name, "bias": res["bias"],
                       "mc_cover": res["mc_cover"]}
                for r in routes:
                    row[f"{r}_ratio"], row[f"{r}_cover"] = res[r]
                rows.append(row)
                if progress is not None:
                    progress(row)
    return rows


def summary(rows, routes=ROUTES):
    """Per (F, SNR, route): median, min and max ratio; mean and min coverage."""
    keys = sorted({(r["F"], r["snr_db"]) for r in rows})
    lines = [
        f"{'F':>2} {'SNR':>4} {'route':<11} {'ratio med':>9} {'min':>6} {'max':>6}"
        f" {'in 0.95-1.05':>12} {'cover mean':>10} {'min':>6}"
    ]
    for F, snr in keys:
        sel = [r for r in rows if r["F"] == F and r["snr_db"] == snr]
        best = np.array([r["mc_cover"] for r in sel]) * 100
        bias = np.median([r["bias"] for r in sel])
        lines.append(f"{F:>2} {snr:>4g} {'(MC std)':<11} {'':>9} {'':>6} {'':>6} "
                     f"{'':>12} {best.mean():9.1f}% {best.min():5.1f}%  "
                     f"bias/std {bias:.2f}")
        for route in routes:
            ratio = np.array([r[f"{route}_ratio"] for r in sel])
            cover = np.array([r[f"{route}_cover"] for r in sel]) * 100
            inside = np.mean((ratio >= 0.95) & (ratio <= 1.05)) * 100
            lines.append(
                f"{F:>2} {snr:>4g} {route:<11} {np.median(ratio):9.3f} "
                f"{ratio.min():6.3f} {ratio.max():6.3f} {inside:11.0f}% "
                f"{cover.mean():9.1f}% {cover.min():5.1f}%"
            )
    return "\n".join(lines)


def refined_monte_carlo(system, F, snr_db, n_runs, seed, refinements):
    """Std ratio and coverage of refined fits (SK, LM), as they are and with
    the closed form's errors-in-variables noise variance.

    ``as is``: ``frf_std_`` of the refined fit (linearised at the final
    estimate, noise variance ``J / dof``). ``eiv noise``: the same shape
    ``frf_std_**2 / noise_variance_`` times the closed form's
    ``rss / sum |e|^2 (1 - h)`` of the same record.

    Returns
    -------
    dict
        ``{name: {"as is": (ratio, cover), "eiv noise": (ratio, cover)}}``,
        with the closed form (default ``std_method``) as ``"closed form"``.
    """
    rng = np.random.default_rng(seed)
    N = N_SLOW * F
    u = multisine(N, rms=1.44, rng=rng)
    clean = simulate(system, u, F, snr_db=snr_db, rng=rng)
    sigma = float(clean.noise_std)
    truth = true_frf(system, N)
    n = HALF_WINDOW[F]
    U = dft(u)[None]
    settings = {"closed form": {}, **refinements}
    est = {k: [] for k in settings}
    var = {k: {"as is": [], "eiv noise": []} for k in settings}
    for _ in range(n_runs):
        y = clean.y_l_clean + sigma * rng.standard_normal(N_SLOW)
        closed = LRMBeyondNyquist(half_window=n).fit(u, y, F)
        fit = closed.local_fit_
        terms = variance_terms(U, dft(y)[None], closed.layout_, fit.theta,
                               fit.slow_bins, with_hc=False)
        s2_eiv = terms.rss / terms.eiv_trace
        for name, kwargs in settings.items():
            # refined fits with their own noise level ("as is"); "eiv noise"
            # is then what the default std_method="eiv" gives them
            e = closed if not kwargs else LRMBeyondNyquist(
                half_window=n, std_method="lemma2", **kwargs).fit(u, y, F)
            est[name].append(e.frf_)
            var[name]["as is"].append(e.frf_std_**2)
            if not kwargs:  # the closed form's std is already the route's
                var[name]["eiv noise"].append(e.frf_std_**2)
                continue
            scale = np.repeat((s2_eiv / e.noise_variance_)[:, None], F, axis=1)
            scale = one_sided_fast_grid(scale, N, F, conj=False)
            var[name]["eiv noise"].append(e.frf_std_**2 * scale)
    out = {}
    for name in settings:
        e = np.array(est[name])
        mc = np.sqrt(np.sum(np.abs(e - e.mean(0)) ** 2, axis=0) / (n_runs - 1))
        bins = np.all(np.isfinite(e), axis=0) & np.isfinite(truth) & (mc > 0)
        bins[0] = False
        out[name] = {}
        for kind, values in var[name].items():
            v = np.array(values)[:, bins]
            ratio = float(np.median(np.sqrt(v.mean(0)) / mc[bins]))
            cover = float(np.mean(np.abs(e[:, bins] - truth[bins]) <= 2 * np.sqrt(v)))
            out[name][kind] = (ratio, cover)
    return out


#: Routes of :func:`mimo_monte_carlo`.
MIMO_ROUTES = ("default", "lemma2", "eiv", "eiv_pooled", "eiv_robust")


def mimo_monte_carlo(system, F, snr_db, n_runs, seed,
                     routes=("default", "lemma2", "eiv", "eiv_pooled")):
    """Std ratio and coverage of each route on a 2x2 system, all four entries.

    Two orthogonal random-phase multisine experiments
    (:func:`lrmfrf.signals.orthogonal_multisines`) of ``N = 400 F`` samples;
    ``LRMBeyondNyquist`` defaults (half window 18, 23 at F = 5).
    ``"eiv_robust"`` is the ``frf_std_`` of a second fit of the same record
    with ``std_method="eiv_robust"`` (the same ``frf_``, checked; refitting
    costs less than rebuilding the default fit's ``local_fit_``).

    Returns
    -------
    dict
        ``{route: (ratio, coverage)}``, ratio the median over entries and bins.
    """
    rng = np.random.default_rng(seed)
    N = N_SLOW * F
    u = orthogonal_multisines(2, N, rms=1.44, rng=rng)  # (P, n_u, N)
    clean = [simulate(system, u[p], F, snr_db=snr_db, rng=rng) for p in range(2)]
    y_clean = np.stack([c.y_l_clean for c in clean])  # (P, n_y, M)
    sigma = np.asarray(clean[0].noise_std)[None, :, None]
    truth = true_frf(system, N)  # (n_y, n_u, K)
    U = dft(u).reshape(2, -1)
    est, var = [], {r: [] for r in routes}
    for _ in range(n_runs):
        y = y_clean + sigma * rng.standard_normal(y_clean.shape)
        fit = LRMBeyondNyquist(half_window=HALF_WINDOW[F]).fit(u, y, F)
        est.append(fit.frf_)
        Y = dft(y)
        for route in routes:
            if route == "default":  # the estimator's own frf_std_
                var[route].append(fit.frf_std_**2)
                continue
            if route == "eiv_robust":  # its own frf_std_ (whole record)
                robust = LRMBeyondNyquist(half_window=HALF_WINDOW[F],
                                          std_method="eiv_robust").fit(u, y, F)
                if not np.array_equal(robust.frf_, fit.frf_, equal_nan=True):
                    raise RuntimeError("eiv_robust changed frf_")
                var[route].append(robust.frf_std_**2)
                continue
            v = np.empty(truth.shape)
            for o, lf in enumerate(fit.local_fit_):
                terms = variance_terms(U, Y[:, o], fit.layout_, lf.theta,
                                       lf.slow_bins, with_hc=False)
                cov = band_covariance(terms, fit.layout_, route,
                                      slow_bins=lf.slow_bins, n_slow=N_SLOW)
                d = np.real(np.diagonal(cov, axis1=1, axis2=2))
                for i in range(2):
                    v[o, i] = one_sided_fast_grid(d[:, i * F:(i + 1) * F], N, F,
                                                  conj=False)
            var[route].append(v)
    est = np.array(est)
    mc = np.sqrt(np.sum(np.abs(est - est.mean(0)) ** 2, axis=0) / (n_runs - 1))
    bins = np.all(np.isfinite(est), axis=0) & np.isfinite(truth) & (mc > 0)
    bins[..., 0] = False
    error = np.abs(est - truth)[:, bins]
    out = {"mc_cover": float(np.mean(error <= 2 * mc[bins]))}
    for route in routes:
        v = np.array(var[route])[:, bins]
        ratio = float(np.median(np.sqrt(v.mean(0)) / mc[bins]))
        out[route] = (ratio, float(np.mean(error <= 2 * np.sqrt(v))))
    return out


def mimo_summary(results, routes):
    """Per (F, SNR): the MC std's own coverage, then per route the median
    (min, max) over systems of the ratio and the mean (min) coverage."""
    lines = [f"{'F':>2} {'SNR':>4} {'route':<11} {'ratio med':>9} {'min':>6} "
             f"{'max':>6} {'cover mean':>10} {'min':>6}"]
    for (F, snr), cell in sorted(results.items()):
        best = np.array([c["mc_cover"] for c in cell]) * 100
        lines.append(f"{F:>2} {snr:>4g} {'(MC std)':<11} {'':>9} {'':>6} "
                     f"{'':>6} {best.mean():9.1f}% {best.min():5.1f}%  "
                     f"({len(cell)} systems)")
        for route in routes:
            ratio = np.array([c[route][0] for c in cell])
            cover = np.array([c[route][1] for c in cell]) * 100
            lines.append(f"{F:>2} {snr:>4g} {route:<11} {np.median(ratio):9.3f} "
                         f"{ratio.min():6.3f} {ratio.max():6.3f} "
                         f"{cover.mean():9.1f}% {cover.min():5.1f}%")
    return "\n".join(lines)


def _mimo_main(args) -> int:
    import warnings

    from lrmfrf.plants import mimo_wafer_stage

    if args.routes is None:
        args.routes = list(MIMO_ROUTES)
    unknown = [r for r in args.routes if r not in MIMO_ROUTES]
    if unknown:
        raise SystemExit(
            f"--mimo supports the routes {', '.join(MIMO_ROUTES)}; got "
            f"{', '.join(unknown)}. Drop them from --routes."
        )
    routes = tuple(args.routes)
    print(f"2x2 (G[0:2, 0:2]), two orthogonal experiments, {args.runs} runs; "
          "ratio / coverage per route")
    start = time.perf_counter()
    results = {}
    for F in args.F:
        systems = []
        for seed in _seed_range(args.seeds):
            stage, _ = random_stage(seed, downsampling_factor=F, mimo=True)
            systems.append((f"s{seed}-mimo", stage.G[0:2, 0:2]))
        if not args.no_wafer:
            systems.append(("mimo-wafer",
                            mimo_wafer_stage(downsampling_factor=F).G[0:2, 0:2]))
        for snr in args.snr:
            cell = results.setdefault((F, snr), [])
            for i, (name, system) in enumerate(systems):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    res = mimo_monte_carlo(system, F, snr, args.runs,
                                           1000 * i + F, routes)
                cell.append(res)
                if args.verbose:
                    cells = " ".join(f"{r}={res[r][0]:.3f}/{res[r][1] * 100:.1f}%"
                                     for r in routes)
                    print(f"F={F} {snr:g} dB {name}: {cells} "
                          f"mc_cover={res['mc_cover'] * 100:.1f}%", flush=True)
            print(f"F={F} {snr:g} dB done, {time.perf_counter() - start:.0f} s",
                  flush=True)
    print(f"seeds {args.seeds}, wafer {not args.no_wafer}, {args.runs} runs, "
          f"M = {N_SLOW}, {time.perf_counter() - start:.0f} s")
    print(mimo_summary(results, routes))
    return 0


def _speed_main(args) -> int:
    """Time of a default fit (``std_method="eiv"``) over a Lemma 2 fit."""
    stage = wafer_stage()
    print("fit time, std_method='eiv' / 'lemma2' (best of 3, one process)")
    for N in (1200, 12000, 120000):
        u = multisine(N, rms=1.44, rng=0)
        y = simulate(stage.G_z, u, 3, snr_db=45, rng=1).y_l
        times = {}
        for method in ("lemma2", "eiv", "lemma2", "eiv"):  # first: warm-up
            best = np.inf
            for _ in range(3):
                start = time.perf_counter()
                LRMBeyondNyquist(std_method=method).fit(u, y, 3)
                best = min(best, time.perf_counter() - start)
            times[method] = best
        print(f"N = {N:>6}: lemma2 {times['lemma2']:.3f} s, eiv {times['eiv']:.3f} s, "
              f"ratio {times['eiv'] / times['lemma2']:.1f}", flush=True)
    return 0


def _seed_range(text: str) -> list[int]:
    if "-" in text:
        lo, hi = text.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(s) for s in text.split(",")]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1000-1019",
                        help="random-stage seeds, e.g. 1000-1019 or 1,2,3")
    parser.add_argument("--F", type=int, nargs="+", default=[2, 3, 5])
    parser.add_argument("--snr", type=float, nargs="+", default=[25, 30, 45, 70])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--routes", nargs="+", default=None,
                        help="default: every route of the mode (SISO or --mimo)")
    parser.add_argument("--open", action="store_true",
                        help="also the open-loop channels of each stage")
    parser.add_argument("--channels", nargs="+", default=["G_y4", "G_z"])
    parser.add_argument("--no-wafer", action="store_true")
    parser.add_argument("--alternate", action="store_true",
                        help="one loop/channel per stage, in turn")
    parser.add_argument("--csv", help="write the per-system rows here")
    parser.add_argument("--verbose", action="store_true")
    parser.add_argument("--refined", action="store_true",
                        help="instead: closed form, SK 30 and SK 30 + LM 300")
    parser.add_argument("--mimo", action="store_true",
                        help="instead: 2x2 MIMO stages (G[0:2, 0:2])")
    parser.add_argument("--speed", action="store_true",
                        help="instead: time of the default std against Lemma 2")
    args = parser.parse_args(argv)
    if args.speed:
        return _speed_main(args)
    if args.refined:
        return _refined_main(args)
    if args.mimo:
        return _mimo_main(args)
    if args.routes is None:
        args.routes = list(ROUTES)
    unknown = [r for r in args.routes if r not in ROUTES]
    if unknown:
        raise SystemExit(
            f"the SISO tables support the routes {', '.join(ROUTES)}; got "
            f"{', '.join(unknown)}. Drop them from --routes."
        )
    loops = ("closed", "open") if args.open else ("closed",)
    start = time.perf_counter()

    def progress(row):
        if args.verbose:
            cells = " ".join(f"{r}={row[f'{r}_ratio']:.3f}/{row[f'{r}_cover']:.3f}"
                             for r in args.routes)
            print(f"F={row['F']} {row['snr_db']:g} dB {row['system']}: {cells} "
                  f"bias={row['bias']:.2f} mc_cover={row['mc_cover']:.3f}", flush=True)

    rows = std_table(_seed_range(args.seeds), args.snr, args.F, args.runs,
                     routes=tuple(args.routes), loops=loops,
                     channels=tuple(args.channels), wafer=not args.no_wafer,
                     alternate=args.alternate, progress=progress)
    print(f"seeds {args.seeds}, loops {loops}, channels {args.channels}, "
          f"alternate {args.alternate}, "
          f"wafer {not args.no_wafer}, {args.runs} runs, M = {N_SLOW}, "
          f"{time.perf_counter() - start:.0f} s")
    print(summary(rows, tuple(args.routes)))
    if args.csv:
        with open(args.csv, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return 0


def _refined_main(args) -> int:
    import warnings

    refinements = {"SK 30": {"sk_iterations": 30},
                   "SK 30 + LM 300": {"sk_iterations": 30, "lm_iterations": 300}}
    loops = ("closed", "open") if args.open else ("closed",)
    print(f"{'F':>2} {'SNR':>4} {'system':<22} {'fit':<15} {'as is':>13} "
          f"{'eiv noise':>13}   (ratio / coverage)")
    for F in args.F:
        systems = stage_systems(_seed_range(args.seeds), F, loops=loops,
                                channels=tuple(args.channels),
                                wafer=not args.no_wafer, alternate=args.alternate)
        for snr in args.snr:
            for i, (name, system) in enumerate(systems):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    res = refined_monte_carlo(system, F, snr, args.runs,
                                              1000 * i + F, refinements)
                for fit, kinds in res.items():
                    cells = " ".join(f"{r:6.3f}/{c * 100:5.1f}%"
                                     for r, c in kinds.values())
                    print(f"{F:>2} {snr:>4g} {name:<22} {fit:<15} {cells}",
                          flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
