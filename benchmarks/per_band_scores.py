"""Per-band blend scores on 2x2 cluster stages (issue 15, item 4): offline.

``LRMBeyondNyquistCV(per_band=True)`` weighs every identifiable candidate of
the grid at each slow bin by its predicted std (``lrmfrf.estimators._bands``:
the mean log ``frf_std_`` over the bin's fast bins and the matrix entries,
averaged over 11 slow bins, weights ``exp(-sharpness (score - best))``). On
the 2x2 cluster records of ``generalisation_selection.py --per-band --mimo``
that blend is 0.925x the RMS error of the best single setting but 1.21x its
median error in the cluster of aliased modes: there it prefers wide windows
with low degrees (e.g. (36, 2, 2, x)), whose std is small and whose bias is
not in it, over the (18-24, 5-6, 5-6, 7-8) settings that separate the modes.

This script fits every identifiable candidate once per record (the same
records: ``generalisation_selection.cluster_mimo_record``) and re-scores the blend
offline with variants of the score:

- ``matrix``: the library's score (checked: it reproduces the CV's ``frf_``
  exactly); ``row`` / ``entry``: one score and weight per output row / per
  matrix entry instead of one per slow bin;
- ``misfit``: the score plus ``alpha`` times the candidate's log residual
  noise variance (``noise_variance_``, mean over the output rows) above a
  reference over the candidates (``min``, ``median`` or the 25th percentile):
  a setting that cannot fit the window shows it in its residual.

For each variant: the RMS relative error of the 2x2 matrix over the bins
against the best single setting (lowest RMS, known from the truth), and the
median error ratio in the rigid-body region and in the cluster (median over
records). The issue's target is RMS <= 0.9x and both medians <= 1.

Run::

    python benchmarks/per_band_scores.py --seeds 1-8
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import generalisation_selection as gs  # noqa: E402

from lrmfrf import LRMBeyondNyquist, LRMBeyondNyquistCV  # noqa: E402
from lrmfrf.estimators import _bands  # noqa: E402


def fit_record(seed: int, snr_db: float = 40.0) -> dict:
    """Every identifiable candidate of the default grid on the 2x2 record of
    ``seed`` (as :func:`generalisation_selection.per_band_mimo_record`)."""
    stage, freqs, system, u, y = gs.cluster_mimo_record(seed, snr_db)
    F, N = 3, u.shape[-1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cv = LRMBeyondNyquistCV(per_band=True).fit(u, y, F)
        ok = [p for p, good in zip(cv.cv_results_["params"],
                                   cv.cv_results_["identifiable"], strict=True)
              if good]
        fits = [LRMBeyondNyquist(**p).fit(u, y, F) for p in ok]
    return {
        "seed": seed, "F": F, "N": N, "freqs": freqs,
        "G": gs.true_frf(system, N),
        "f": np.arange(N // 2 + 1) / (N * stage.sample_time),
        "cv_frf": cv.frf_, "params": ok,
        "frf": np.array([e.frf_ for e in fits]),
        "std": np.array([e.frf_std_ for e in fits]),
        "valid": np.array([e.valid_ for e in fits]),
        "noise": np.array([e.noise_variance_ for e in fits]),
    }


def log_std_scores(rec: dict, mode: str) -> np.ndarray:
    """``(C, R, M//2+1)``: mean log std per slow bin, over the matrix
    (``R = 1``), per output row or per entry; ``inf`` where not valid."""
    N, F = rec["N"], rec["F"]
    M = N // F
    k = np.arange(N // 2 + 1) % M
    slow = np.where(k > M // 2, M - k, k)
    n_half = M // 2 + 1
    counts = np.bincount(slow, minlength=n_half)
    std, valid = rec["std"], rec["valid"]
    good = valid & np.isfinite(std) & (std > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_std = np.where(good, np.log(np.where(good, std, 1.0)), np.inf)
    C = log_std.shape[0]
    if mode == "matrix":
        log_std = log_std.reshape(C, 1, -1, log_std.shape[-1]).mean(axis=2)
    elif mode == "row":
        log_std = log_std.mean(axis=2)
    else:
        log_std = log_std.reshape(C, -1, log_std.shape[-1])
    out = np.empty(log_std.shape[:2] + (n_half,))
    for c in range(C):
        for r in range(log_std.shape[1]):
            v = log_std[c, r]
            total = np.bincount(slow, weights=np.where(np.isfinite(v), v, 0.0),
                                minlength=n_half)
            bad = np.bincount(slow, weights=~np.isfinite(v), minlength=n_half)
            out[c, r] = np.where(bad > 0, np.inf, total / np.maximum(counts, 1))
    return out


def misfit(rec: dict, reference: str) -> np.ndarray:
    """``(C, M//2+1)``: mean over the output rows of the log noise variance
    above the reference over the candidates (0 below it, and for ``min``)."""
    noise = rec["noise"]
    log_nv = np.log(np.where(noise > 0, noise, np.nan))
    if reference == "min":
        ref = np.nanmin(log_nv, axis=0)
    elif reference == "median":
        ref = np.nanmedian(log_nv, axis=0)
    else:
        ref = np.nanpercentile(log_nv, 25, axis=0)
    excess = np.nanmean(np.maximum(log_nv - ref, 0.0), axis=1)
    return np.where(np.isfinite(excess), excess, 0.0)


def blend(rec: dict, scores: np.ndarray, sharpness: float) -> np.ndarray:
    """The blended FRF matrix (NaN where a used fit is not valid)."""
    N, F = rec["N"], rec["F"]
    frfs, valid = rec["frf"], rec["valid"]
    n_y, n_u, _ = frfs.shape[1:]
    R = scores.shape[1]
    out = np.empty(frfs.shape[1:], dtype=complex)
    for r in range(R):
        smoothed = _bands.smooth_scores(scores[:, r], _bands.SCORE_HALF_WIDTH,
                                        N // F)
        weights = _bands.score_weights(smoothed, sharpness)
        fast = np.stack([_bands.to_fast_grid(w, N, F) for w in weights])
        if R == 1:
            part = (slice(None), slice(None))
        elif R == n_y:
            part = (r, slice(None))
        else:
            part = (r // n_u, r % n_u)
        total = np.zeros(frfs[0][part].shape, dtype=complex)
        ok = np.all(np.isfinite(fast), axis=0) & np.ones(total.shape, dtype=bool)
        for c in range(frfs.shape[0]):
            used = fast[c] > 0
            ok &= ~used | valid[c][part]
            total = total + np.where(used, fast[c] * frfs[c][part], 0.0)
        out[part] = np.where(ok, total, np.nan)
    return out


def ratios(rec: dict, frf: np.ndarray) -> tuple[float, float, float]:
    """RMS, rigid-body and cluster median error of ``frf`` over those of the
    single setting with the lowest RMS error."""
    G, f = rec["G"], rec["f"]
    size = np.sqrt(np.sum(np.abs(G) ** 2, axis=(0, 1)))
    usable = np.isfinite(size) & (size > 0)
    usable[0] = False
    every = np.concatenate([frf[None], rec["frf"]])
    rel = np.sqrt(np.sum(np.abs(every - G) ** 2, axis=(1, 2)))
    rel = rel / np.where(usable, size, 1.0)
    keep = usable & np.isfinite(rel).all(axis=0)
    rms = np.sqrt(np.mean(rel[:, keep] ** 2, axis=1))
    best = 1 + int(np.argmin(rms[1:]))
    rigid = keep & (f < 100.0)
    cluster = keep & (np.min(np.abs(f[:, None] - np.asarray(rec["freqs"])),
                             axis=1) < 15.0)
    return (rms[0] / rms[best],
            np.median(rel[0, rigid]) / np.median(rel[best, rigid]),
            np.median(rel[0, cluster]) / np.median(rel[best, cluster]))


def variants():
    for mode in ("matrix", "row", "entry"):
        for sharpness in (30.0, 10.0, 100.0):
            yield f"{mode}, sharpness {sharpness:g}", mode, None, 0.0, sharpness
    for reference in ("min", "median", "q25"):
        for alpha in (0.5, 1.0, 2.0):
            for sharpness in (30.0, 10.0):
                yield (f"misfit {reference}, alpha {alpha:g}, sharpness "
                       f"{sharpness:g}", "matrix", reference, alpha, sharpness)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="1-8")
    args = parser.parse_args(argv)
    seeds = gs._parse_seeds(args.seeds)
    records = [fit_record(int(s)) for s in seeds]
    reproduced = max(
        float(np.nanmax(np.abs(blend(r, log_std_scores(r, "matrix"),
                                     _bands.SCORE_SHARPNESS) - r["cv_frf"])))
        for r in records)
    print(f"2x2 cluster records, seeds {args.seeds} ({len(records)}); the "
          f"'matrix, sharpness 30' blend reproduces the CV's frf_ to "
          f"{reproduced:.1e}")
    print(f"{'score':44s}{'RMS mean':>9s}{'worst':>7s}{'rigid':>7s}"
          f"{'cluster':>8s}{'[min, max]':>16s}")
    for name, mode, reference, alpha, sharpness in variants():
        rows = []
        for r in records:
            scores = log_std_scores(r, mode)
            if reference is not None:
                scores = scores + alpha * misfit(r, reference)[:, None, :]
            rows.append(ratios(r, blend(r, scores, sharpness)))
        rows = np.array(rows)
        print(f"{name:44s}{rows[:, 0].mean():9.3f}{rows[:, 0].max():7.3f}"
              f"{np.median(rows[:, 1]):7.3f}{np.median(rows[:, 2]):8.3f}"
              f"   [{rows[:, 2].min():.3f}, {rows[:, 2].max():.3f}]")


if __name__ == "__main__":
    main()
