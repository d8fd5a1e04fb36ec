"""Tests of lrmfrf.plotting: Bode plots with bands, error plots."""

from __future__ import annotations

import sys

import matplotlib

matplotlib.use("Agg")

import control  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from conftest import frf_of, simulate_resonant  # noqa: E402

from lrmfrf import LRMBeyondNyquist, SpectralAnalysis  # noqa: E402
from lrmfrf.plotting import frf_curve, plot_error, plot_frf  # noqa: E402
from lrmfrf.signals import multisine  # noqa: E402


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


@pytest.fixture(scope="module")
def fitted():
    """LRM fitted on the resonant test system (N=600, F=3), with its truth."""
    rng = np.random.default_rng(11)
    u = multisine(600, rng=rng)
    y = simulate_resonant(u, 3, 1e-3, rng)
    est = LRMBeyondNyquist(half_window=15, num_degree=3, transient_degree=3,
                           den_degree=4).fit(u, y, 3, sample_time=0.5e-3)
    return est


def _band(axis):
    """The vertices of the first filled band on an axis."""
    collections = [c for c in axis.collections if c.get_paths()]
    return collections


def _nyquist_lines(axis):
    return [
        line for line in axis.get_lines()
        if np.size(line.get_xdata()) == 2 and np.ptp(line.get_xdata()) == 0
    ]


def test_plot_frf_draws_magnitude_phase_and_slow_nyquist(fitted):
    fig, axes = plot_frf(fitted, labels=["LRM"])
    assert len(axes) == 2
    assert [a.get_ylabel() for a in axes] == ["Magnitude [dB]", "Phase [deg]"]
    mag_line = axes[0].get_lines()[0]
    keep = fitted.frequencies_ > 0  # log axis leaves out 0 Hz
    np.testing.assert_allclose(mag_line.get_xdata(), fitted.frequencies_[keep])
    np.testing.assert_allclose(mag_line.get_ydata(),
                               20 * np.log10(np.abs(fitted.frf_[keep])))
    for axis in axes:
        lines = _nyquist_lines(axis)
        assert lines, "slow Nyquist line missing"
        # 1 / (2 F Ts) = 1 / (2 * 3 * 0.5e-3) Hz
        assert lines[0].get_xdata()[0] == pytest.approx(1 / (2 * 3 * 0.5e-3))
    labels = [t.get_text() for t in axes[0].get_legend().get_texts()]
    assert labels[0] == "LRM" and "slow Nyquist 333.3 Hz" in labels


def test_std_band_is_magnitude_plus_minus_k_std_in_db():
    f = np.linspace(1.0, 50.0, 50)
    G = 10.0 / (1 + 1j * f / 10)
    std = 0.05 * np.abs(G)
    std[-1] = 2.0 * np.abs(G[-1])  # band wider than |G|: lower edge unbounded
    fig, axes = plot_frf((f, G, std), std_band=2, slow_nyquist=False)
    band = _band(axes[0])
    assert len(band) == 1
    vertices = band[0].get_paths()[0].vertices
    upper = 20 * np.log10(np.abs(G) + 2 * std)
    lower = 20 * np.log10(np.abs(G[:-1]) - 2 * std[:-1])
    assert vertices[:, 1].max() == pytest.approx(upper.max())
    # The band's lower edge at the last bin lies below the visible axis.
    assert vertices[:, 1].min() < axes[0].get_ylim()[0]
    # Every finite lower edge appears among the vertices.
    ys = vertices[:, 1]
    for value in lower[::7]:
        assert np.min(np.abs(ys - value)) < 1e-9
    # Phase band: +/- arcsin(2 std/|G|) = +/- arcsin(0.1) around the phase.
    phase_band = _band(axes[1])[0].get_paths()[0].vertices
    half = np.degrees(np.arcsin(0.1))
    phase = np.angle(G[0], deg=True)
    assert np.min(np.abs(phase_band[:, 1] - (phase + half))) < 1e-9
    assert not _nyquist_lines(axes[0])


def test_no_band_when_std_band_is_zero(fitted):
    fig, axes = plot_frf(fitted, std_band=0)
    assert not _band(axes[0])


def test_true_system_and_several_estimates_share_axes(fitted):
    from conftest import resonant_system

    b, a = resonant_system()
    system = control.tf(b, a, dt=0.5e-3)
    # scipy lfilter coefficients are in powers of z^-1; as a tf in z they are
    # the same arrays when numerator and denominator have equal length.
    assert len(b) == len(a)
    sa = SpectralAnalysis(segment_length=200, overlap=100)
    rng = np.random.default_rng(12)
    u = multisine(600, rng=rng)
    sa.fit(u, simulate_resonant(u, 3, 1e-3, rng), 3, sample_time=0.5e-3)
    fig, axes = plot_frf(fitted, sa, true=system, labels=["LRM", "SA"])
    true_line = [ln for ln in axes[0].get_lines() if ln.get_label() == "true"][0]
    x = true_line.get_xdata()
    on_grid = np.isin(fitted.frequencies_, x)
    assert on_grid[1:].all()
    exact = frf_of(b, a, 600)
    index = np.searchsorted(x, fitted.frequencies_[1:])
    np.testing.assert_allclose(true_line.get_ydata()[index],
                               20 * np.log10(np.abs(exact[1:])), rtol=1e-9)


def test_frd_and_tuple_inputs():
    omega = np.linspace(1, 100, 20)
    G = 1 / (1 + 1j * omega / 30)
    frd = control.FrequencyResponseData(G, omega, dt=1e-3)
    curve = frf_curve(frd)
    np.testing.assert_allclose(curve.frequencies, omega / (2 * np.pi))
    np.testing.assert_allclose(curve.frf, G)
    assert curve.std is None and curve.sample_time == 1e-3
    fig, axes = plot_frf(frd, (omega / (2 * np.pi), G), slow_nyquist=5.0)
    assert _nyquist_lines(axes[0])[0].get_xdata()[0] == 5.0


def test_invalid_bins_leave_gaps(fitted):
    import copy

    est = copy.deepcopy(fitted)
    est.valid_ = est.valid_.copy()
    est.valid_[100:120] = False
    fig, axes = plot_frf(est)
    y = axes[0].get_lines()[0].get_ydata()
    # frequencies_ > 0 drops bin 0, so bins 100..119 are points 99..118
    assert np.isnan(y[99:119]).all() and np.isfinite(y[:99]).all()


def test_plot_into_given_axes_and_max_points(fitted):
    fig, axes = plt.subplots(2, 1)
    out_fig, out_axes = plot_frf(fitted, ax=axes, max_points=50)
    assert out_fig is fig
    n = out_axes[0].get_lines()[0].get_xdata().size
    assert 10 <= n <= 50


def test_bad_arguments(fitted):
    with pytest.raises(ValueError, match="at least one FRF"):
        plot_frf()
    with pytest.raises(ValueError, match="not fitted"):
        plot_frf(LRMBeyondNyquist())
    with pytest.raises(TypeError, match="Cannot plot an object of type str"):
        plot_frf("frf")
    with pytest.raises(ValueError, match="2 labels for 1 FRFs"):
        plot_frf(fitted, labels=["a", "b"])
    with pytest.raises(ValueError, match="std_band must be a non-negative"):
        plot_frf(fitted, std_band=-1)
    with pytest.raises(ValueError, match="xscale must be"):
        plot_frf(fitted, xscale="symlog")
    fig, axis = plt.subplots()
    with pytest.raises(ValueError, match=r"`ax` must be 2 Axes \(magnitude, phase\)"):
        plot_frf(fitted, ax=axis)
    with pytest.raises(ValueError, match="slow_nyquist must be a positive"):
        plot_frf(fitted, slow_nyquist=-3.0)
    with pytest.raises(ValueError, match="must lie on the first FRF's grid"):
        plot_frf(fitted, true=np.ones(5, complex))
    with pytest.raises(ValueError, match="1-D of equal length"):
        plot_frf((np.arange(3.0), np.ones(4)))
    # issue 13: plot_frf draws a MIMO FRD as a grid (tests/test_plotting_mimo);
    # the SISO curve conversion still refuses one
    mimo = control.FrequencyResponseData(np.ones((2, 1, 3)), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="Only SISO FRDs"):
        frf_curve(mimo)


def test_missing_matplotlib_gives_install_hint(monkeypatch, fitted):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    with pytest.raises(ImportError, match=r'pip install "lrmfrf\[plot\]"'):
        plot_frf(fitted)


# --------------------------------------------------------------------------
# plot_error
# --------------------------------------------------------------------------


def test_plot_error_relative_known_answer():
    pytest.importorskip("lrmfrf.metrics")
    f = np.linspace(0, 100, 11)
    G = np.full(11, 2.0 + 0j)
    estimate = G * 1.1
    fig, ax = plot_error(G, estimate, frequencies=f, kind="relative",
                         labels=["x"], slow_nyquist=False)
    line = ax.get_lines()[0]
    np.testing.assert_allclose(line.get_ydata(), 0.1, rtol=1e-12)
    np.testing.assert_allclose(line.get_xdata(), f[1:])


def test_plot_error_cumulative_matches_metrics(fitted):
    metrics = pytest.importorskip("lrmfrf.metrics")
    from conftest import resonant_system

    b, a = resonant_system()
    G = frf_of(b, a, 600)
    fig, ax = plot_error(G, fitted, kind="cumulative", labels=["LRM"])
    expected = np.asarray(metrics.cumulative_error(G, fitted.frf_, 600))
    # Known answer, eq. (CPSD): (1/N) sum_{k=1}^{n} |G - Ghat|.
    direct = np.concatenate([[0.0], np.cumsum(np.abs(G - fitted.frf_)[1:])]) / 600
    np.testing.assert_allclose(expected, direct, rtol=1e-12)
    np.testing.assert_allclose(ax.get_lines()[0].get_ydata(), expected[1:])
    assert _nyquist_lines(ax)


def test_plot_error_bad_arguments(fitted):
    with pytest.raises(ValueError, match="kind must be 'cumulative' or 'relative'"):
        plot_error(np.ones(3), np.ones(3), frequencies=np.arange(3.0), kind="abs")
    with pytest.raises(ValueError, match="at least one estimate"):
        plot_error(np.ones(3))
    pytest.importorskip("lrmfrf.metrics")
    with pytest.raises(ValueError, match="need their frequencies"):
        plot_error(np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match="Pass the true system"):
        plot_error(np.ones(3), fitted)


# --------------------------------------------------------------------------
# Readability: continuous phase, legend placement, slow-Nyquist band, order
# --------------------------------------------------------------------------

TS = 0.5e-3


def _delay(f, samples=3):
    """A pure delay of ``samples`` fast samples: phase -360 f Ts samples deg."""
    return np.exp(-2j * np.pi * f * TS * samples)


def _phase_line(axis):
    line = axis.get_lines()[0]
    x, y = np.asarray(line.get_xdata(), float), np.asarray(line.get_ydata(), float)
    keep = np.isfinite(x)  # NaN separators where the phase breaks
    return x[keep], y[keep]


def test_phase_is_unwrapped_along_frequency():
    f = np.linspace(1.0, 999.0, 500)
    fig, axes = plot_frf((f, _delay(f)), slow_nyquist=False)
    x, y = _phase_line(axes[1])
    np.testing.assert_allclose(x, f)
    np.testing.assert_allclose(y, -360.0 * f * TS * 3, atol=1e-9)  # to -539 deg
    low, high = axes[1].get_ylim()
    assert low <= y.min() and high >= y.max()


def test_wrap_option_keeps_the_principal_value():
    f = np.linspace(1.0, 999.0, 500)
    fig, axes = plot_frf((f, _delay(f)), slow_nyquist=False, phase="wrap")
    y = np.asarray(axes[1].get_lines()[0].get_ydata(), float)
    assert np.nanmax(y) <= 180 and np.nanmin(y) > -180
    assert np.isnan(y).sum() == 1  # one break, where -180 wraps to +180
    assert axes[1].get_ylim() == (-200, 200)


def test_estimates_are_drawn_within_180_degrees_of_the_truth():
    f = np.linspace(1.0, 999.0, 400)
    G = _delay(f)
    offset = np.where(np.arange(f.size) % 2, 170.0, -170.0)
    estimate = G * np.exp(1j * np.radians(offset))
    fig, axes = plot_frf((f, estimate), true=(f, G), slow_nyquist=False)
    x, y = _phase_line(axes[1])
    np.testing.assert_allclose(y, -360.0 * f * TS * 3 + offset, atol=1e-9)


def test_noisy_bins_do_not_shift_the_unwrapped_phase():
    """Bins with std > |G| carry random phases; unwrapping through them would
    add random multiples of 360 degrees to everything after them."""
    rng = np.random.default_rng(0)
    f = np.linspace(1.0, 999.0, 600)
    G = _delay(f).copy()
    std = np.full(f.size, 0.01)
    noisy = (f > 300) & (f < 500)
    G[noisy] = np.exp(2j * np.pi * rng.random(noisy.sum()))
    std[noisy] = 3.0
    fig, axes = plot_frf((f, G, std), slow_nyquist=False)
    x, y = _phase_line(axes[1])
    exact = -360.0 * f * TS * 3
    np.testing.assert_allclose(y[~noisy], exact[~noisy], atol=1e-9)
    assert np.all(np.abs(y[noisy] - exact[noisy]) <= 180.0 + 1e-9)


def test_legend_outside_does_not_cover_the_axes(fitted):
    fig, axes = plot_frf(fitted, labels=["LRM"])
    fig.canvas.draw()
    legend = axes[0].get_legend().get_window_extent()
    for axis in axes:
        assert legend.x0 >= axis.get_window_extent().x1
    fig, axes = plot_frf(fitted, legend="inside")
    fig.canvas.draw()
    box = axes[0].get_window_extent()
    assert axes[0].get_legend().get_window_extent().x1 <= box.x1
    fig, axes = plot_frf(fitted, legend="none", units="m/N")
    assert axes[0].get_legend() is None
    assert axes[0].get_ylabel() == "Magnitude [dB re 1 m/N]"


def test_band_above_the_slow_nyquist_frequency_is_shaded(fitted):
    fig, axes = plot_frf(fitted)
    nyquist = 1 / (2 * 3 * TS)
    for axis in axes:
        spans = [p for p in axis.patches if hasattr(p, "get_x")]
        assert len(spans) == 1
        assert spans[0].get_x() == pytest.approx(nyquist)
        assert spans[0].get_x() + spans[0].get_width() == pytest.approx(
            fitted.frequencies_[-1])
        assert axis.get_xlim() == pytest.approx(
            (fitted.frequencies_[1], fitted.frequencies_[-1]))


def test_first_frf_is_drawn_on_top(fitted):
    f = fitted.frequencies_
    fig, axes = plot_frf(fitted, (f, fitted.frf_ * 1.1), labels=["a", "b"])
    first, second = axes[0].get_lines()[:2]
    assert first.get_zorder() > second.get_zorder()


def test_bad_readability_arguments(fitted):
    with pytest.raises(ValueError, match="phase must be 'unwrap' or 'wrap'"):
        plot_frf(fitted, phase="deg")
    with pytest.raises(ValueError, match="legend must be 'outside', 'inside'"):
        plot_frf(fitted, legend="top")
    with pytest.raises(ValueError, match="yscale must be 'log' or 'linear'"):
        plot_error(np.ones(3), np.ones(3), frequencies=np.arange(3.0),
                   yscale="symlog")


def test_plot_error_scales_and_units():
    f = np.linspace(0, 100, 11)
    G = np.full(11, 2.0 + 0j)
    fig, ax = plot_error(G, G * 1.1, frequencies=f, units="m/N",
                         slow_nyquist=False)
    assert ax.get_yscale() == "linear"
    assert ax.get_ylabel().endswith("[m/N]")
    fig, ax = plot_error(G, G * 1.1, frequencies=f, kind="relative",
                         slow_nyquist=False)
    assert ax.get_yscale() == "log" and ax.get_ylabel().endswith("[-]")


def test_freq_range_zooms_and_keeps_the_global_phase():
    f = np.linspace(1.0, 999.0, 999)
    G = _delay(f)
    fig, axes = plot_frf((f, G), true=(f, G), slow_nyquist=False,
                         xscale="linear", freq_range=(400.0, 500.0))
    x, y = _phase_line(axes[1])
    assert x.min() >= 400.0 and x.max() <= 500.0
    # the same values as in the full plot: unwrapped from 1 Hz, not from 400 Hz
    np.testing.assert_allclose(y, -360.0 * x * TS * 3, atol=1e-9)
    assert axes[0].get_xlim() == (400.0, 500.0)
    low, high = axes[1].get_ylim()
    assert low >= -360 * 500 * TS * 3 - 45 - 100 and high <= -360 * 400 * TS * 3 + 145
    with pytest.raises(ValueError, match="freq_range must be two frequencies"):
        plot_frf((f, G), freq_range=(500.0, 400.0))


# --------------------------------------------------------------------------
# One convention: several FRFs as arguments, one list or one mapping
# --------------------------------------------------------------------------


def _magnitudes(axis):
    return [(line.get_label(), line.get_ydata()) for line in axis.get_lines()
            if not line.get_label().startswith(("slow Nyquist", "_"))]


def test_plot_frf_accepts_a_list_and_a_mapping(fitted):
    """plot_frf([a, b]) and plot_frf({"LRM": a, "scaled": b}) draw what
    plot_frf(a, b) draws; a mapping's keys are the legend labels."""
    f = fitted.frequencies_
    other = (f, 1.1 * fitted.frf_)
    _, separate = plot_frf(fitted, other, labels=["LRM", "scaled"])
    _, listed = plot_frf([fitted, other], labels=["LRM", "scaled"])
    _, mapped = plot_frf({"LRM": fitted, "scaled": other})
    _, tupled = plot_frf((fitted, fitted), labels=["a", "b"])  # estimators
    expected = _magnitudes(separate[0])
    assert [label for label, _ in expected] == ["LRM", "scaled"]
    for axes in (listed, mapped):
        got = _magnitudes(axes[0])
        assert [label for label, _ in got] == ["LRM", "scaled"]
        for (_, y), (_, y_expected) in zip(got, expected, strict=True):
            np.testing.assert_array_equal(y, y_expected)
        legend = [t.get_text() for t in axes[0].get_legend().get_texts()]
        assert legend[:2] == ["LRM", "scaled"]
    assert [label for label, _ in _magnitudes(tupled[0])] == ["a", "b"]
    # Default labels of a list: the class names, as for separate arguments.
    _, axes = plot_frf([fitted])
    assert _magnitudes(axes[0])[0][0] == "LRMBeyondNyquist"


def test_plot_error_accepts_a_list_and_a_mapping(fitted):
    from conftest import resonant_system

    b, a = resonant_system()
    G = frf_of(b, a, 600)
    _, separate = plot_error(G, fitted, fitted, labels=["x", "y"])
    _, listed = plot_error(G, [fitted, fitted], labels=["x", "y"])
    _, mapped = plot_error(G, {"x": fitted, "y": fitted})
    expected = _magnitudes(separate)
    for ax in (listed, mapped):
        got = _magnitudes(ax)
        assert [label for label, _ in got] == ["x", "y"]
        for (_, y), (_, y_expected) in zip(got, expected, strict=True):
            np.testing.assert_array_equal(y, y_expected)
    # A list of numbers is still one array estimate, a list of arrays several.
    f = np.linspace(0, 100, 11)
    G = np.full(11, 2.0 + 0j)
    _, ax = plot_error(G, list(1.1 * G), frequencies=f, kind="relative",
                       slow_nyquist=False)
    assert len(_magnitudes(ax)) == 1
    np.testing.assert_allclose(ax.get_lines()[0].get_ydata(), 0.1, rtol=1e-12)
    _, ax = plot_error(G, [1.1 * G, 1.2 * G], frequencies=f, kind="relative",
                       slow_nyquist=False)
    np.testing.assert_allclose([line.get_ydata()[0] for line in ax.get_lines()],
                               [0.1, 0.2], rtol=1e-12)


def test_collections_bad_arguments(fitted):
    with pytest.raises(ValueError, match="takes its labels from its keys"):
        plot_frf({"LRM": fitted}, labels=["x"])
    with pytest.raises(TypeError, match="Got a list of FRFs and 1 more positional"):
        plot_frf([fitted], fitted)
    with pytest.raises(TypeError, match="Got a dict of estimates and 1 more"):
        plot_error(np.ones(3), fitted, {"a": fitted})
    with pytest.raises(ValueError, match="Nothing to draw: pass at least one FRF"):
        plot_frf([])
    with pytest.raises(ValueError, match="at least one estimate"):
        plot_error(np.ones(3), {})
    with pytest.raises(ValueError, match="1 labels for 2 FRFs"):
        plot_frf([fitted, fitted], labels=["a"])
    with pytest.raises(TypeError, match="Cannot plot an object of type str"):
        plot_frf([fitted, "frf"])


def test_package_layout_keeps_the_public_names():
    """plotting is a package: curve normalisation (no matplotlib) and drawing
    in two modules; the public names import from lrmfrf.plotting as before."""
    import lrmfrf.plotting as plotting
    from lrmfrf.plotting import FRFCurve, _curves, _draw

    assert plotting.plot_frf is _draw.plot_frf
    assert plotting.plot_error is _draw.plot_error
    assert plotting.frf_curve is _curves.frf_curve
    assert FRFCurve is _curves.FRFCurve
    assert sorted(plotting.__all__) == ["FRFCurve", "frf_curve", "plot_error",
                                        "plot_frf"]


def test_curves_module_does_not_need_matplotlib(monkeypatch, fitted):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    curve = frf_curve(fitted)
    assert curve.slow_nyquist == pytest.approx(1 / (2 * 3 * 0.5e-3))


@pytest.mark.parametrize("module", ["lrmfrf.plotting._draw"])
def test_docstring_examples_run(module):
    import doctest
    import importlib

    result = doctest.testmod(importlib.import_module(module),
                             optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0
    assert result.failed == 0
