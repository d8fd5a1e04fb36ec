"""``SpectralAnalysis.frf_std_`` against a Monte Carlo, with and without aliasing.

The coherence counts everything in the zero-stuffed output that is not
linearly related to the input at a bin as noise, including the aliased images
of the other bands. With a fixed broadband input those images are the same in
every run (a bias, not noise), so ``frf_std_`` overstates the spread over noise
realisations; when the input is drawn anew in every run (or lies below the slow
Nyquist frequency) the images vary like noise and the std matches.

Systems: SISO ``b = [0.2, 0.1], a = [1, -0.5]``; 2x2 of first-order entries.
N = 4800, F = 3, default segments (200, overlap 100), output noise 0.3x the
output std, ``--runs`` runs (default 200). Ratio: median over bins of the RMS
predicted std over the Monte-Carlo std ``sqrt(mean_r |G_r - mean G|^2)``,
below 0.8x and above 1.2x the slow Nyquist frequency (2x2: per entry, below).

Run::

    python benchmarks/spectral_std_aliasing.py --runs 200
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.signal import butter, lfilter

from lrmfrf import SpectralAnalysis
from lrmfrf.signals import multisine

N, F = 4800, 3


def _ratio(fits, freq, band):
    est = np.array([f for f, _ in fits])
    mc = np.sqrt(np.mean(np.abs(est - est.mean(axis=0)) ** 2, axis=0))
    predicted = np.sqrt(np.mean(np.array([s for _, s in fits]) ** 2, axis=0))
    return np.median(predicted[..., band] / mc[..., band], axis=-1)


def _siso(case, runs, rng):
    u = multisine(N, rng=0) if case == "multisine fixed" else rng.standard_normal(N)
    fits = []
    for _ in range(runs):
        if case == "white varying":
            u = rng.standard_normal(N)
        clean = lfilter([0.2, 0.1], [1, -0.5], u)[::F]
        y = clean + 0.3 * clean.std() * rng.standard_normal(clean.size)
        sa = SpectralAnalysis().fit(u, y, F)
        fits.append((sa.frf_, sa.frf_std_))
    f = sa.frequencies_
    below = (f > 0) & (f < 0.8 / (2 * F))
    above = f > 1.2 / (2 * F)
    return _ratio(fits, f, below), _ratio(fits, f, above)


def _mimo(case, runs, rng):
    def sim(u):
        return np.stack([
            lfilter([0.2, 0.1], [1, -0.5], u[0]) + lfilter([0.5], [1, -0.2], u[1]),
            lfilter([0.3], [1, -0.5], u[1]) - 0.4 * u[0],
        ])[:, ::F]

    b, a = butter(8, 0.9 / F)
    u = rng.standard_normal((2, N))
    if case == "lowpass fixed":
        u = lfilter(b, a, u)
    fits = []
    for _ in range(runs):
        if case == "white varying":
            u = rng.standard_normal((2, N))
        clean = sim(u)
        y = clean + 0.3 * clean.std() * rng.standard_normal(clean.shape)
        sa = SpectralAnalysis().fit(u, y, F)
        fits.append((sa.frf_, sa.frf_std_))
    f = sa.frequencies_
    below = (f > 0) & (f < 0.8 / (2 * F))
    return _ratio(fits, f, below).ravel()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=200)
    args = parser.parse_args(argv)
    print(f"SpectralAnalysis frf_std_ / Monte-Carlo std, {args.runs} runs")
    for case in ("white fixed", "multisine fixed", "white varying"):
        below, above = _siso(case, args.runs, np.random.default_rng(0))
        print(f"SISO {case:16s} below {below:.3f}  above {above:.3f}")
    for case in ("white fixed", "lowpass fixed", "white varying"):
        ratios = _mimo(case, args.runs, np.random.default_rng(0))
        print(f"2x2  {case:16s} below, entries 00 01 10 11: "
              + " ".join(f"{r:.3f}" for r in ratios))


if __name__ == "__main__":
    main()
