"""plot_frf for MIMO FRFs (issue 13): an n_y x n_u grid of Bode magnitudes
with std bands, from a fake MIMO estimate, an FRD and the closed-loop result."""

from types import SimpleNamespace

import control
import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")

from lrmfrf import plant_from_closed_loop  # noqa: E402
from lrmfrf.plants import mimo_wafer_stage  # noqa: E402
from lrmfrf.plotting import plot_frf  # noqa: E402
from lrmfrf.simulate import frequency_grid, true_frf  # noqa: E402

N, TS = 600, 0.5e-3


@pytest.fixture(scope="module")
def stage():
    return mimo_wafer_stage()


def _fake(frf, std_fraction=0.1):
    n_y, n_u, K = frf.shape
    valid = np.isfinite(frf).all(axis=(0, 1)) & np.ones(frf.shape, bool)
    return SimpleNamespace(
        frequencies_=frequency_grid(N, TS), frf_=frf,
        frf_std_=std_fraction * np.abs(frf), valid_=valid, sample_time_=TS,
        downsampling_factor_=3, n_inputs_=n_u, n_outputs_=n_y,
    )


def _magnitude_lines(axis):
    return [line for line in axis.get_lines() if line.get_linestyle() == "-"]


def test_grid_of_magnitudes_with_bands(stage):
    """A 5 x 4 estimate: axes (5, 4); panel (o, i) draws 20 log10 |G_oi| and
    its +/- 2 std band (known from frf_std_ = 0.1 |G|: +1.58 dB / -1.94 dB)."""
    import matplotlib.pyplot as plt

    G = true_frf(stage.G, N)
    fig, axes = plot_frf(_fake(G), true=stage.G)
    assert axes.shape == (5, 4)
    for o, i in [(0, 0), (4, 3), (2, 1)]:
        axis = axes[o, i]
        line = _magnitude_lines(axis)[0]
        freq, mag = line.get_data()
        k = np.rint(freq * N * TS).astype(int)
        np.testing.assert_allclose(mag, 20 * np.log10(np.abs(G[o, i, k])), rtol=1e-12)
        band = axis.collections[0].get_paths()[0].vertices[:, 1]
        top = 20 * np.log10(np.abs(G[o, i, k]) * 1.2)
        assert np.isclose(band.max(), top.max(), rtol=1e-9)
        assert axis.get_title() == f"u{i} → y{o}"
        # the truth as a dashed black line in every panel
        assert any(line.get_linestyle() == "--" for line in axis.get_lines())
    assert axes[0, 0].get_xscale() == "log"
    plt.close(fig)


def test_labels_from_frd_and_estimator(stage):
    import matplotlib.pyplot as plt

    frd = control.frd(true_frf(stage.G, N)[:, :, 1:], 2 * np.pi *
                      frequency_grid(N, TS)[1:], dt=TS,
                      inputs=["r1", "r2", "r3", "r4"],
                      outputs=["e1", "e2", "e3", "e4", "poi"])
    fig, axes = plot_frf(frd)
    assert axes.shape == (5, 4) and axes[4, 1].get_title() == "r2 → poi"
    plt.close(fig)
    estimate = _fake(true_frf(stage.G, N))
    estimate.output_labels_ = ["a", "b", "c", "d", "e"]
    estimate.input_labels_ = ["p", "q", "r", "s"]
    fig, axes = plot_frf(estimate)
    assert axes[1, 3].get_title() == "s → b"
    plt.close(fig)


def test_closed_loop_result_and_given_axes(stage):
    import matplotlib.pyplot as plt

    result = plant_from_closed_loop(_fake(true_frf(stage.G, N)), stage.controller,
                                    (0, 1, 2, 3))
    fig, given = plt.subplots(5, 4, squeeze=False)
    out_fig, axes = plot_frf(result, _fake(true_frf(stage.plant, N)),
                             labels=["recovered", "plant"])
    assert axes.shape == (5, 4)
    plt.close(out_fig)
    same_fig, same = plot_frf(result, ax=given)
    assert same_fig is fig and same is given
    with pytest.raises(ValueError, match=r"array of Axes of shape \(n_y, n_u\)"):
        plot_frf(result, ax=given[:2])
    with pytest.raises(ValueError, match="same n_y x n_u"):
        plot_frf(result, _fake(true_frf(stage.G[:2, :2], N)))
    with pytest.raises(ValueError, match="The true system has 2 outputs"):
        plot_frf(result, true=stage.plant[:2, :2])
    plt.close(fig)
