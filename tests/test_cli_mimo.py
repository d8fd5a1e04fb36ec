"""MIMO records from files (issue 13 item 6): comma-separated column lists on
the command line, lists of names in :func:`lrmfrf.io.read_measurement`, and
the long-form MIMO FRF table."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.io

from lrmfrf import LRMBeyondNyquist
from lrmfrf.cli import main
from lrmfrf.io import FRF_COLUMNS, DataFileError, read_measurement
from lrmfrf.testing import in_class_mimo_data
from lrmfrf.windows import LocalModelLayout

F = 2
HALF = 10  # 21 equations for 17 parameters per output row (one experiment)


@pytest.fixture(scope="module")
def mimo():
    """One record of two inputs and two outputs, in the LRM model class."""
    layout = LocalModelLayout(F=F, half_window=HALF, num_degree=2,
                              transient_degree=2, den_degree=2, n_inputs=2)
    u, y, _, _ = in_class_mimo_data(layout, n_slow=400, n_outputs=2, rng=3)
    return u[0], y[0]  # (2, N), (2, M)


def _csv(path, u, y, fast_output=True):
    M = y.shape[1]
    header = "t,u1,u2,y1,y2"
    rows = [header]
    for k in range(u.shape[1]):
        cells = [repr(k * 1e-3), repr(float(u[0, k])), repr(float(u[1, k]))]
        if fast_output:
            slow = k % F == 0
            cells += [repr(float(y[o, k // F])) if slow else "" for o in range(2)]
        else:
            cells += [repr(float(y[o, k])) if k < M else "" for o in range(2)]
        rows.append(",".join(cells))
    path.write_text("\n".join(rows) + "\n")
    return path


def _run(args, capsys):
    capsys.readouterr()
    try:
        status = main([str(a) for a in args])
    except SystemExit as exc:
        status = exc.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


@pytest.mark.parametrize("fast_output", [True, False])
def test_read_several_columns_gives_channels_first_records(tmp_path, mimo,
                                                           fast_output):
    u, y = mimo
    path = _csv(tmp_path / "d.csv", u, y, fast_output)
    data = read_measurement(path, F=F, input_column=["u1", "u2"],
                            output_column=("y1", "y2"))
    np.testing.assert_array_equal(data.u_h, u)
    np.testing.assert_array_equal(data.y_l, y)
    assert data.input_column == ("u1", "u2") and data.input_names == ("u1", "u2")
    assert data.n_samples == u.shape[1] and data.n_slow == y.shape[1]
    assert data.sample_time == pytest.approx(1e-3)
    # a single name keeps the 1-D SISO record
    one = read_measurement(path, F=F, input_column="u2", output_column="y1")
    np.testing.assert_array_equal(one.u_h, u[1])
    np.testing.assert_array_equal(one.y_l, y[0])
    assert one.input_names == ("u2",)


def test_npz_and_mat_take_lists_of_names(tmp_path, mimo):
    u, y = mimo
    arrays = {"u1": u[0], "u2": u[1], "y1": y[0], "y2": y[1]}
    np.savez(tmp_path / "d.npz", **arrays)
    scipy.io.savemat(tmp_path / "d.mat", arrays)
    for name in ("d.npz", "d.mat"):
        data = read_measurement(tmp_path / name, F=F, input_column=["u1", "u2"],
                                output_column=["y2", "y1"])
        np.testing.assert_array_equal(data.u_h, u)
        np.testing.assert_array_equal(data.y_l, y[::-1])


def test_bad_column_lists_are_refused(tmp_path, mimo):
    u, y = mimo
    path = _csv(tmp_path / "d.csv", u, y)
    with pytest.raises(ValueError, match="names a column twice"):
        read_measurement(path, F=F, input_column=["u1", "u1"], output_column="y1")
    with pytest.raises(ValueError, match="are both 'u1'"):
        read_measurement(path, F=F, input_column=["u1", "u2"],
                         output_column=["y1", "u1"])
    with pytest.raises(ValueError, match="empty list"):
        read_measurement(path, F=F, input_column=[], output_column="y1")
    with pytest.raises(DataFileError, match="no column named 'u3'.*--input-column"):
        read_measurement(path, F=F, input_column=["u1", "u3"], output_column="y1")
    np.savez(tmp_path / "short.npz", u1=u[0], u2=u[1][:-F], y1=y[0])
    with pytest.raises(DataFileError, match="input channels have different lengths"):
        read_measurement(tmp_path / "short.npz", F=F, input_column=["u1", "u2"],
                         output_column="y1")
    slow_and_fast = np.full(u.shape[1], np.nan)
    slow_and_fast[::F] = y[1]
    np.savez(tmp_path / "mixed.npz", u=u[0], y1=y[0], y2=slow_and_fast)
    with pytest.raises(DataFileError, match="different layouts.*'y1' slow.*'y2' fast"):
        read_measurement(tmp_path / "mixed.npz", F=F, output_column=["y1", "y2"])


def test_fit_a_mimo_csv_from_the_command_line(tmp_path, mimo, capsys):
    u, y = mimo
    path = _csv(tmp_path / "d.csv", u, y)
    out = tmp_path / "out"
    status, stdout, err = _run(
        ["fit", path, "--F", str(F), "--input-column", "u1, u2",
         "--output-column", "y1,y2", "--half-window", str(HALF), "--num-degree", "2",
         "--transient-degree", "2", "--den-degree", "2", "--out", out], capsys)
    assert status == 0, err
    expected = LRMBeyondNyquist(half_window=HALF, num_degree=2, transient_degree=2,
                                den_degree=2).fit(u, y, F, sample_time=1e-3)
    K = expected.frequencies_.size
    stored = np.load(out / "frf.npz", allow_pickle=False)
    np.testing.assert_array_equal(stored["frf"], expected.frf_)
    assert stored["frf"].shape == (2, 2, K)
    assert str(stored["input_columns"]) == "u1,u2"
    table = np.genfromtxt(out / "frf.csv", delimiter=",", names=True)
    assert table.dtype.names == ("output", "input", *FRF_COLUMNS)
    assert table.size == 4 * K
    for o, i in np.ndindex(2, 2):
        rows = table[(table["output"] == o) & (table["input"] == i)]
        np.testing.assert_allclose(rows["real"] + 1j * rows["imag"],
                                   expected.frf_[o, i], rtol=1e-9, atol=0)
        np.testing.assert_array_equal(rows["valid"] == 1, expected.valid_[o, i])
    report = (out / "report.txt").read_text()
    assert "columns: input 'u1', 'u2'; output 'y1', 'y2'" in report
    assert "outputs 0=y1, 1=y2; inputs 0=u1, 1=u2" in report
    assert (out / "bode.png").stat().st_size > 0


def test_mimo_bode_grid_names_the_columns(tmp_path, mimo, capsys, monkeypatch):
    import lrmfrf.plotting

    u, y = mimo
    path = _csv(tmp_path / "d.csv", u, y)
    seen = {}
    real = lrmfrf.plotting.plot_frf

    def spy(*frfs, **kwargs):
        seen["labels"] = (frfs[0].output_labels_, frfs[0].input_labels_)
        seen["ax_shape"] = np.shape(kwargs["ax"])
        return real(*frfs, **kwargs)

    monkeypatch.setattr(lrmfrf.plotting, "plot_frf", spy)
    status, _, err = _run(
        ["fit", path, "--F", str(F), "--input-column", "u1,u2", "--output-column",
         "y2", "--half-window", str(HALF), "--num-degree", "2", "--transient-degree",
         "2", "--den-degree", "2", "--out", tmp_path / "o"], capsys)
    assert status == 0, err
    assert seen == {"labels": (["y2"], ["u1", "u2"]), "ax_shape": (1, 2)}


def test_empty_name_in_a_column_list_is_refused(tmp_path, mimo, capsys):
    u, y = mimo
    path = _csv(tmp_path / "d.csv", u, y)
    status, out, err = _run(["fit", path, "--F", str(F), "--input-column", "u1,,u2",
                             "--output-column", "y1", "--out", tmp_path / "o"], capsys)
    assert status == 2 and out == ""
    assert "has an empty name" in err and len(err.strip().splitlines()) == 1
    # diagnose takes column lists too (tests/test_cli_diagnose.py, MIMO section)


def test_too_small_window_for_a_mimo_file_names_no_python_arrays(tmp_path, mimo,
                                                                capsys):
    """Two inputs, F = 2 and num_degree 6 with the default half window (18):
    37 equations for 40 parameters. The error added the estimators' hint about 2-D arrays and 3-D stacks, which a
    command-line user does not have; it now names the half window only."""
    u, y = mimo
    path = _csv(tmp_path / "d.csv", u, y)
    status, out, err = _run(["fit", path, "--F", str(F), "--input-column", "u1,u2",
                             "--output-column", "y1,y2", "--num-degree", "6",
                             "--out", tmp_path / "o"], capsys)
    assert status == 1 and out == ""
    assert "Increase --half-window to at least" in err
    assert "2-D array" not in err and "3-D array" not in err


def test_the_window_error_speaks_in_flags_and_its_advice_works(tmp_path, mimo,
                                                               capsys):
    """The estimators' error names their parameters (``half_window``) and
    advises more experiments, which ``lrmfrf fit`` cannot take (one file, one
    experiment): the command names its flags, says so, and the half window
    it names fits."""
    import re

    u, y = mimo
    path = _csv(tmp_path / "d.csv", u, y)
    args = ["fit", path, "--F", str(F), "--input-column", "u1,u2",
            "--output-column", "y1,y2", "--num-degree", "6"]
    status, _, err = _run(args + ["--out", tmp_path / "o"], capsys)
    assert status == 1
    assert "half_window" not in err and "--half-window=18" in err
    assert "(num_degree+1)" in err  # formulas keep the parameter names
    assert "fits each file as one experiment" in err
    needed = re.search(r"Increase --half-window to at least (\d+)", err).group(1)
    status, _, err = _run(args + ["--half-window", needed, "--out", tmp_path / "p"],
                          capsys)
    assert status == 0, err
