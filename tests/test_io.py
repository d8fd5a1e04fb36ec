"""Tests of lrmfrf.io: reading measured records, checks, atomic writing."""

from __future__ import annotations

import hashlib
import os

import numpy as np
import pytest
import scipy.io
from hypothesis import given, settings
from hypothesis import strategies as st

from lrmfrf.io import (
    FRF_COLUMNS,
    DataFileError,
    OutputExistsError,
    atomic_group,
    atomic_open,
    check_output_folder,
    check_output_path,
    file_sha256,
    frf_table,
    read_measurement,
    write_frf_csv,
    write_frf_npz,
)
from lrmfrf.io import readers as lio


def _records(rng, M=40, F=3):
    u = rng.standard_normal(F * M)
    y = rng.standard_normal(M)
    return u, y


def write_csv(path, columns: dict, *, delimiter=",", preamble=""):
    """Write columns (lists of numbers or None/str) as CSV; None is empty."""
    names = list(columns)
    n_rows = max(len(c) for c in columns.values())
    lines = [delimiter.join(names)]
    for i in range(n_rows):
        cells = []
        for name in names:
            col = columns[name]
            value = col[i] if i < len(col) else None
            if value is None or (isinstance(value, float) and np.isnan(value)):
                cells.append("")
            elif isinstance(value, str):
                cells.append(value)
            else:
                cells.append(repr(float(value)))
        lines.append(delimiter.join(cells))
    path.write_text(preamble + "\n".join(lines) + "\n", encoding="utf-8")
    return path


def fast_column(y, F):
    col = [None] * (F * len(y))
    col[::F] = list(y)
    return col


# --------------------------------------------------------------------------
# Reading: known answers
# --------------------------------------------------------------------------


def test_csv_fast_layout_recovers_records_exactly(tmp_path):
    rng = np.random.default_rng(0)
    u, y = _records(rng)
    path = write_csv(tmp_path / "d.csv", {"t": list(range(120)), "u": u,
                                          "y": fast_column(y, 3)})
    data = read_measurement(path, F=3)
    np.testing.assert_array_equal(data.u_h, u)  # repr() round-trips floats
    np.testing.assert_array_equal(data.y_l, y)
    assert data.output_layout == "fast"
    assert data.file_format == "csv"
    assert any("every F=3-th row" in c for c in data.checks)
    assert data.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()


def test_csv_slow_layout_with_padding(tmp_path):
    rng = np.random.default_rng(1)
    u, y = _records(rng, M=30, F=4)
    path = write_csv(tmp_path / "d.csv", {"y": y, "u": u})
    data = read_measurement(path, F=4)
    np.testing.assert_array_equal(data.y_l, y)
    np.testing.assert_array_equal(data.u_h, u)
    assert data.output_layout == "slow"
    assert any("90 empty cells" in c for c in data.checks)


def test_csv_semicolon_comments_bom_and_trailing_blank_lines(tmp_path):
    rng = np.random.default_rng(2)
    u, y = _records(rng, M=10, F=2)
    path = write_csv(tmp_path / "d.csv", {"in": u, "out": fast_column(y, 2)},
                     delimiter=";", preamble="# measured 2024\n\n")
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes() + b"\n\n")
    data = read_measurement(path, F=2, input_column="in", output_column="out")
    np.testing.assert_array_equal(data.u_h, u)
    np.testing.assert_array_equal(data.y_l, y)


def test_csv_nan_text_between_samples_is_accepted(tmp_path):
    rng = np.random.default_rng(3)
    u, y = _records(rng, M=8, F=3)
    col = ["nan"] * 24
    col[::3] = list(y)
    data = read_measurement(write_csv(tmp_path / "d.csv", {"u": u, "y": col}), F=3)
    np.testing.assert_array_equal(data.y_l, y)


def test_csv_one_character_cells_between_empty_cells(tmp_path):
    """Issue 12 item 1: one-character numbers and empty cells in one column
    were parsed as a '<U1' array that cut the "nan" fill to "n"."""
    path = tmp_path / "d.csv"
    path.write_text("u,y\n7,6\n3,\n0,\n1,2\n4,\n5,\n")
    data = read_measurement(path, F=3)
    np.testing.assert_array_equal(data.u_h, [7.0, 3.0, 0.0, 1.0, 4.0, 5.0])
    np.testing.assert_array_equal(data.y_l, [6.0, 2.0])
    assert data.output_layout == "fast"


def test_csv_chunk_boundaries_do_not_change_result(tmp_path, monkeypatch):
    rng = np.random.default_rng(4)
    u, y = _records(rng, M=50, F=3)
    path = write_csv(tmp_path / "d.csv", {"u": u, "y": fast_column(y, 3)})
    whole = read_measurement(path, F=3)
    monkeypatch.setattr(lio, "CSV_CHUNK_ROWS", 7)
    chunked = read_measurement(path, F=3)
    np.testing.assert_array_equal(whole.u_h, chunked.u_h)
    np.testing.assert_array_equal(whole.y_l, chunked.y_l)
    # A bad cell in a later chunk is reported at its own line.
    u_text = [repr(float(v)) for v in u]
    u_text[100] = "1.2.3"
    bad = write_csv(tmp_path / "bad.csv", {"u": u_text, "y": fast_column(y, 3)})
    with pytest.raises(DataFileError, match="line 102"):
        read_measurement(bad, F=3)


def test_csv_columns_are_allocated_once_and_grow_if_needed(tmp_path, monkeypatch):
    """The columns are sized from a line count; old-Mac files (CR only) have no
    newline to count and take the growth path: same records either way."""
    rng = np.random.default_rng(14)
    u, y = _records(rng, M=50, F=3)
    path = write_csv(tmp_path / "d.csv", {"u": u, "y": fast_column(y, 3)})
    assert lio._count_lines(path) == 1 + 1 + 150  # header, rows, final newline
    mac = tmp_path / "mac.csv"
    mac.write_bytes(path.read_bytes().replace(b"\n", b"\r"))
    assert lio._count_lines(mac) == 1
    monkeypatch.setattr(lio, "CSV_CHUNK_ROWS", 16)
    for source in (path, mac):
        data = read_measurement(source, F=3)
        np.testing.assert_array_equal(data.u_h, u)
        np.testing.assert_array_equal(data.y_l, y)


@settings(max_examples=25, deadline=None)
@given(
    F=st.integers(1, 5),
    M=st.integers(2, 30),
    seed=st.integers(0, 2**32 - 1),
    fast=st.booleans(),
)
def test_csv_round_trip_property(tmp_path_factory, F, M, seed, fast):
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(F * M) * 10.0 ** rng.integers(-8, 8)
    u[0] += 1.0  # never constant
    y = rng.standard_normal(M) * 10.0 ** rng.integers(-8, 8)
    folder = tmp_path_factory.mktemp("rt")
    column = fast_column(y, F) if fast else list(y)
    data = read_measurement(write_csv(folder / "d.csv", {"u": u, "y": column}), F=F)
    np.testing.assert_array_equal(data.u_h, u)
    np.testing.assert_array_equal(data.y_l, y)


def test_npz_and_mat_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    u, y = _records(rng)
    np.savez(tmp_path / "d.npz", u=u, y=y)
    scipy.io.savemat(tmp_path / "row.mat", {"u": u, "y": y})  # (1, n) in MATLAB
    scipy.io.savemat(tmp_path / "col.mat", {"u": u[:, None], "y": y[:, None]})
    for name in ("d.npz", "row.mat", "col.mat"):
        data = read_measurement(tmp_path / name, F=3)
        np.testing.assert_array_equal(data.u_h, u)
        np.testing.assert_array_equal(data.y_l, y)
        assert data.u_h.flags.writeable and data.u_h.ndim == 1


def test_npz_fast_layout_with_nan_gaps(tmp_path):
    rng = np.random.default_rng(6)
    u, y = _records(rng)
    y_fast = np.full(u.size, np.nan)
    y_fast[::3] = y
    np.savez(tmp_path / "d.npz", u=u, y=y_fast)
    data = read_measurement(tmp_path / "d.npz", F=3)
    np.testing.assert_array_equal(data.y_l, y)
    assert data.output_layout == "fast"


def test_reading_never_modifies_the_file(tmp_path):
    rng = np.random.default_rng(7)
    u, y = _records(rng)
    path = write_csv(tmp_path / "d.csv", {"u": u, "y": fast_column(y, 3)})
    before = path.read_bytes(), os.stat(path).st_mtime_ns
    read_measurement(path, F=3)
    assert (path.read_bytes(), os.stat(path).st_mtime_ns) == before


# --------------------------------------------------------------------------
# Reading: bad input
# --------------------------------------------------------------------------


@pytest.fixture
def good(tmp_path):
    rng = np.random.default_rng(8)
    return _records(rng, M=20, F=3)


def test_missing_file_and_folder_and_unknown_format(tmp_path):
    with pytest.raises(DataFileError, match=r"nope\.csv: no such file\. Check"):
        read_measurement(tmp_path / "nope.csv", F=3)
    with pytest.raises(DataFileError, match="is a folder"):
        read_measurement(tmp_path, F=3)
    (tmp_path / "d.xlsx").write_bytes(b"PK")
    with pytest.raises(DataFileError, match=r"unknown file format '\.xlsx'.*\.csv"):
        read_measurement(tmp_path / "d.xlsx", F=3)


def test_missing_column_names_the_header(tmp_path, good):
    u, y = good
    path = write_csv(tmp_path / "d.csv", {"u": u, "out": fast_column(y, 3)})
    with pytest.raises(DataFileError, match=r"no column named 'y' \(the header has "
                       r"'u', 'out'\)\. Pass the right name with --output-column"):
        read_measurement(path, F=3)
    with pytest.raises(ValueError, match="both 'u'"):
        read_measurement(path, F=3, output_column="u")


def test_duplicate_column(tmp_path):
    (tmp_path / "d.csv").write_text("u,u,y\n1,2,3\n")
    with pytest.raises(DataFileError, match="names 2 columns 'u'"):
        read_measurement(tmp_path / "d.csv", F=1)


def test_nan_in_input(tmp_path, good):
    u, y = good
    u = u.copy()
    u[7] = np.nan
    path = write_csv(tmp_path / "d.csv", {"u": u, "y": fast_column(y, 3)})
    with pytest.raises(DataFileError, match=r"input 'u' has 1 empty, NaN or inf "
                       r"value\(s\), the first at line 9\. The fast input"):
        read_measurement(path, F=3)
    np.savez(tmp_path / "d.npz", u=u, y=y)
    with pytest.raises(DataFileError, match="the first at index 7"):
        read_measurement(tmp_path / "d.npz", F=3)


def test_nan_in_output(tmp_path, good):
    u, y = good
    y = y.copy()
    y[4] = np.nan
    fast = write_csv(tmp_path / "f.csv", {"u": u, "y": fast_column(y, 3)})
    with pytest.raises(DataFileError, match=r"where slow samples belong .* line 14"):
        read_measurement(fast, F=3)
    slow = write_csv(tmp_path / "s.csv", {"u": u, "y": y})
    with pytest.raises(DataFileError, match=r"inside the record, the first at line 6"):
        read_measurement(slow, F=3)
    y[4] = np.inf
    np.savez(tmp_path / "d.npz", u=u, y=y)
    with pytest.raises(DataFileError, match="index 4"):
        read_measurement(tmp_path / "d.npz", F=3)


def test_lengths_that_do_not_match_F(tmp_path, good):
    u, y = good
    path = write_csv(tmp_path / "d.csv", {"u": u, "y": y})
    with pytest.raises(DataFileError, match=r"lengths do not match F=4: input has "
                       r"N=60 samples and output 'y' M=20, but N must equal F\*M = "
                       r"80 \(N/M = 3: is F=3\?\)\. Check --F"):
        read_measurement(path, F=4)
    np.savez(tmp_path / "d.npz", u=u[:-1], y=y)
    with pytest.raises(DataFileError, match="N=59 samples"):
        read_measurement(tmp_path / "d.npz", F=3)
    np.savez(tmp_path / "fast.npz", u=u, y=u.copy())
    with pytest.raises(DataFileError, match="is it the fast-rate output"):
        read_measurement(tmp_path / "fast.npz", F=3)


def test_fast_layout_needs_multiple_of_F_and_no_values_between(tmp_path, good):
    u, y = good
    col = fast_column(y, 3)
    path = write_csv(tmp_path / "d.csv", {"u": list(u) + [0.5], "y": col + [None]})
    with pytest.raises(DataFileError, match="N=61 samples, not a multiple of F=3"):
        read_measurement(path, F=3)
    col[5] = 1.0
    path = write_csv(tmp_path / "e.csv", {"u": u, "y": col})
    with pytest.raises(DataFileError, match=r"values between the slow samples, the "
                       r"first at line 7"):
        read_measurement(path, F=3)


def test_non_numeric_cells(tmp_path, good):
    u, y = good
    u_text = [repr(float(v)) for v in u]
    u_text[3] = "12 N"
    path = write_csv(tmp_path / "d.csv", {"u": u_text, "y": fast_column(y, 3)})
    with pytest.raises(DataFileError, match=r"non-numeric cell '12 N' in column 'u' "
                       r"at line 5\. Use numbers"):
        read_measurement(path, F=3)
    y_col = fast_column([repr(float(v)) for v in y], 3)
    y_col[6] = "1,5"
    path = write_csv(tmp_path / "e.csv", {"u": u, "y": y_col}, delimiter=";")
    with pytest.raises(DataFileError, match="non-numeric cell '1,5' in column 'y'"):
        read_measurement(path, F=3)


def test_bad_csv_structure(tmp_path):
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(DataFileError, match="is empty"):
        read_measurement(tmp_path / "empty.csv", F=1)
    (tmp_path / "header.csv").write_text("u,y\n")
    with pytest.raises(DataFileError, match="no data rows"):
        read_measurement(tmp_path / "header.csv", F=1)
    (tmp_path / "noheader.csv").write_text("1,2\n3,4\n")
    with pytest.raises(DataFileError, match="holds numbers, not column names"):
        read_measurement(tmp_path / "noheader.csv", F=1)
    (tmp_path / "binary.csv").write_bytes(b"u,y\n\xff\xfe\x00\x01,2\n")
    with pytest.raises(DataFileError, match="is not a UTF-8 text file"):
        read_measurement(tmp_path / "binary.csv", F=1)


def test_constant_input(tmp_path):
    write_csv(tmp_path / "d.csv", {"u": [1.0] * 6, "y": [1.0, 2.0]})
    with pytest.raises(DataFileError, match="is constant"):
        read_measurement(tmp_path / "d.csv", F=3)


def test_size_limit(tmp_path, good, monkeypatch):
    u, y = good
    path = write_csv(tmp_path / "d.csv", {"u": u, "y": fast_column(y, 3)})
    monkeypatch.setattr(lio, "CSV_CHUNK_ROWS", 16)
    with pytest.raises(DataFileError, match="more than 50 data rows.*--max-samples"):
        read_measurement(path, F=3, max_samples=50)
    np.savez(tmp_path / "d.npz", u=u, y=y)
    with pytest.raises(DataFileError, match="60 elements, more than the limit 50"):
        read_measurement(tmp_path / "d.npz", F=3, max_samples=50)
    scipy.io.savemat(tmp_path / "d.mat", {"u": u, "y": y})
    with pytest.raises(DataFileError, match="60 elements, more than the limit 50"):
        read_measurement(tmp_path / "d.mat", F=3, max_samples=50)


def test_npz_is_loaded_without_pickles(tmp_path, good):
    u, y = good
    np.savez(tmp_path / "obj.npz", u=np.array([object()] * 60), y=y)
    with pytest.raises(DataFileError, match=r"array 'u' is not numeric \(type object"):
        read_measurement(tmp_path / "obj.npz", F=3)
    np.savez(tmp_path / "cplx.npz", u=u + 1j, y=y)
    with pytest.raises(DataFileError, match="array 'u' is complex"):
        read_measurement(tmp_path / "cplx.npz", F=3)
    np.savez(tmp_path / "twod.npz", u=u.reshape(6, 10), y=y)
    with pytest.raises(DataFileError, match=r"shape \(6, 10\), not a non-empty vector"):
        read_measurement(tmp_path / "twod.npz", F=3)
    np.savez(tmp_path / "names.npz", x=u, y=y)
    with pytest.raises(DataFileError, match=r"no array named 'u' \(the file has 'x', "
                       r"'y'\)\. Pass the right name with --input-column"):
        read_measurement(tmp_path / "names.npz", F=3)
    (tmp_path / "junk.npz").write_bytes(b"not a zip file at all")
    with pytest.raises(DataFileError, match="is not a readable .npz archive"):
        read_measurement(tmp_path / "junk.npz", F=3)


def test_channels_first_array_names_the_mimo_layout(tmp_path, good):
    """A MIMO record saved as one (n_u, N) array, the estimators' layout: the
    fix named only 'one record per file as a 1-D vector', which reads as 'no
    MIMO'; it now says to store one vector per channel and name them."""
    u, y = good
    np.savez(tmp_path / "mimo.npz", u=np.stack([u, -u]), y=y)
    with pytest.raises(DataFileError, match=r"shape \(2, 60\).*one vector each "
                       r"\(e.g. 'u1', 'u2'\), named with --input-column u1,u2"):
        read_measurement(tmp_path / "mimo.npz", F=3)


def test_mat_variables_are_validated(tmp_path, good):
    u, y = good
    scipy.io.savemat(tmp_path / "text.mat", {"u": "hello", "y": y})
    with pytest.raises(DataFileError, match=r"variable 'u' is not numeric \(type char"):
        read_measurement(tmp_path / "text.mat", F=3)
    scipy.io.savemat(tmp_path / "cplx.mat", {"u": u, "y": y * 1j})
    with pytest.raises(DataFileError, match="variable 'y' is complex"):
        read_measurement(tmp_path / "cplx.mat", F=3)
    scipy.io.savemat(tmp_path / "mat2d.mat", {"u": u.reshape(6, 10), "y": y})
    with pytest.raises(DataFileError, match="not a non-empty vector"):
        read_measurement(tmp_path / "mat2d.mat", F=3)
    scipy.io.savemat(tmp_path / "names.mat", {"u": u, "z": y})
    with pytest.raises(DataFileError, match=r"no variable named 'y'"):
        read_measurement(tmp_path / "names.mat", F=3)
    (tmp_path / "junk.mat").write_bytes(b"\x00" * 200)
    with pytest.raises(DataFileError, match="is not a readable MATLAB file"):
        read_measurement(tmp_path / "junk.mat", F=3)


def test_bad_downsampling_factor():
    with pytest.raises(ValueError, match="positive integer"):
        read_measurement("whatever.csv", F=0)


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------


def test_atomic_open_writes_and_refuses_to_overwrite(tmp_path):
    target = tmp_path / "a.bin"
    with atomic_open(target) as fh:
        fh.write(b"first")
    assert target.read_bytes() == b"first"
    with pytest.raises(FileExistsError, match="exists already. Pass --force"):
        with atomic_open(target) as fh:
            fh.write(b"second")
    assert target.read_bytes() == b"first"
    with atomic_open(target, overwrite=True) as fh:
        fh.write(b"second")
    assert target.read_bytes() == b"second"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"]


def test_atomic_open_leaves_target_intact_on_error(tmp_path):
    target = tmp_path / "a.bin"
    target.write_bytes(b"keep")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_open(target, overwrite=True) as fh:
            fh.write(b"partial")
            raise RuntimeError("boom")
    assert target.read_bytes() == b"keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"]


def test_protected_input_is_never_replaced(tmp_path):
    data = tmp_path / "frf.csv"
    data.write_bytes(b"input")
    with pytest.raises(ValueError, match="would replace the input file"):
        check_output_path(data, overwrite=True, protect=[data])
    with pytest.raises(ValueError, match="would replace the input file"):
        with atomic_open(tmp_path / "." / "frf.csv", overwrite=True,
                         protect=[str(data)]) as fh:
            fh.write(b"x")
    assert data.read_bytes() == b"input"
    (tmp_path / "sub").mkdir()
    with pytest.raises(ValueError, match="taken by a folder"):
        check_output_path(tmp_path / "sub", overwrite=True)


class _FakeFit:
    def __init__(self, rng):
        self.frequencies_ = np.linspace(0, 100, 11)
        self.frf_ = rng.standard_normal(11) + 1j * rng.standard_normal(11)
        self.frf_std_ = np.abs(rng.standard_normal(11))
        self.valid_ = np.ones(11, bool)
        self.valid_[3] = False
        self.frf_[3] = np.nan
        self.frf_std_[3] = np.nan


def test_frf_table_known_answers():
    fit = _FakeFit(np.random.default_rng(9))
    table = frf_table(fit)
    assert tuple(table) == FRF_COLUMNS
    np.testing.assert_allclose(table["magnitude_db"], 20 * np.log10(np.abs(fit.frf_)))
    np.testing.assert_allclose(table["phase_deg"],
                               np.degrees(np.arctan2(fit.frf_.imag, fit.frf_.real)))
    np.testing.assert_array_equal(table["valid"], fit.valid_)


def test_frf_table_does_not_share_memory_with_the_estimator():
    """frequency_hz, std and valid were views of frequencies_, frf_std_ and
    valid_: converting the table's frequencies to rad/s or masking its std
    edited the fitted estimator."""
    fit = _FakeFit(np.random.default_rng(11))
    before = {name: np.copy(getattr(fit, name))
              for name in ("frequencies_", "frf_", "frf_std_", "valid_")}
    table = frf_table(fit)
    for column in table.values():
        column[...] = 0
    for name, value in before.items():
        np.testing.assert_array_equal(getattr(fit, name), value)


def test_write_frf_csv_and_npz_round_trip(tmp_path):
    fit = _FakeFit(np.random.default_rng(10))
    table = frf_table(fit)
    csv_path = write_frf_csv(tmp_path / "frf.csv", table)
    header = csv_path.read_text().splitlines()[0]
    assert header == ",".join(FRF_COLUMNS)
    back = np.loadtxt(csv_path, delimiter=",", skiprows=1)
    for i, name in enumerate(FRF_COLUMNS):
        # 10 significant digits are written: relative error below 1e-9.
        np.testing.assert_allclose(back[:, i], table[name].astype(float),
                                   rtol=1e-9, atol=0, equal_nan=True)
    npz_path = write_frf_npz(tmp_path / "frf.npz", table,
                             metadata={"method": "lrm", "F": 3})
    with np.load(npz_path, allow_pickle=False) as saved:
        np.testing.assert_array_equal(saved["frf"], fit.frf_)
        assert str(saved["method"]) == "lrm" and int(saved["F"]) == 3
    with pytest.raises(FileExistsError):
        write_frf_csv(csv_path, table)
    with pytest.raises(TypeError, match="must be a number or a string"):
        write_frf_npz(tmp_path / "x.npz", table, metadata={"bad": object()})


def test_file_sha256_matches_hashlib(tmp_path):
    path = tmp_path / "f"
    path.write_bytes(os.urandom(3000))
    assert file_sha256(path, block_size=1000) == hashlib.sha256(
        path.read_bytes()).hexdigest()


def test_shipped_example_is_what_the_script_simulates(tmp_path):
    """lrmfrf/data holds the output of scripts/make_example_data.py (the
    package's own simulator): regenerated, it agrees to rounding error."""
    import importlib.util
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location(
        "make_example_data", repo / "scripts" / "make_example_data.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.make_example(tmp_path)
    shipped_dir = repo / "lrmfrf" / "data"
    with np.load(tmp_path / "wafer_stage_example.npz") as new, \
            np.load(shipped_dir / "wafer_stage_example.npz") as shipped:
        assert sorted(new.files) == sorted(shipped.files)
        for key in new.files:
            np.testing.assert_allclose(new[key], shipped[key], rtol=1e-9,
                                       atol=1e-9 * np.max(np.abs(shipped[key])))
    for name in ("wafer_stage_example.csv",):
        a = read_measurement(tmp_path / name, F=3)
        b = read_measurement(shipped_dir / name, F=3)
        np.testing.assert_array_equal(a.u_h, b.u_h)
        np.testing.assert_allclose(a.y_l, b.y_l, rtol=1e-9)


# --------------------------------------------------------------------------
# Sample time and F stored in the file (issue 12 item 13)
# --------------------------------------------------------------------------


def test_npz_sample_time_and_F_are_read_and_checked(tmp_path, good):
    u, y = good
    np.savez(tmp_path / "d.npz", u=u, y=y, sample_time=0.5e-3,
             downsampling_factor=3)
    data = read_measurement(tmp_path / "d.npz")
    assert data.downsampling_factor == 3
    assert data.sample_time == 0.5e-3 and data.sample_time_source == "file"
    agreed = read_measurement(tmp_path / "d.npz", F=3.0, sample_time=0.5e-3)
    assert agreed.sample_time == 0.5e-3
    assert any("agrees with its array 'sample_time'" in c for c in agreed.checks)
    with pytest.raises(DataFileError, match=r"the sample time 0\.001 s was passed "
                       r"but its array 'sample_time' says 0\.0005 s \(ratio 2\).*"
                       r"omit --sample-time"):
        read_measurement(tmp_path / "d.npz", sample_time=1e-3)
    with pytest.raises(DataFileError, match=r"F=4 was passed but its array "
                       r"'downsampling_factor' says F=3\. Pass the file's F"):
        read_measurement(tmp_path / "d.npz", F=4)


def test_F_missing_everywhere_and_bad_stored_values(tmp_path, good):
    u, y = good
    np.savez(tmp_path / "plain.npz", u=u, y=y)
    with pytest.raises(DataFileError, match=r"no downsampling factor F was passed "
                       r"and the file stores none.*Pass F \(--F\)"):
        read_measurement(tmp_path / "plain.npz")
    assert read_measurement(tmp_path / "plain.npz", F=3).sample_time is None
    np.savez(tmp_path / "half.npz", u=u, y=y, F=2.5)
    with pytest.raises(DataFileError, match="its array 'F' is 2.5, not a positive "
                       "integer"):
        read_measurement(tmp_path / "half.npz")
    np.savez(tmp_path / "neg.npz", u=u, y=y, sample_time=-1.0)
    with pytest.raises(DataFileError, match="'sample_time' is -1.0, not a positive"):
        read_measurement(tmp_path / "neg.npz", F=3)
    np.savez(tmp_path / "vec.npz", u=u, y=y, sample_time=[1e-3, 2e-3])
    with pytest.raises(DataFileError, match="'sample_time' is not a real number"):
        read_measurement(tmp_path / "vec.npz", F=3)
    np.savez(tmp_path / "two.npz", u=u, y=y, F=3, downsampling_factor=4)
    with pytest.raises(DataFileError, match="contradicting values"):
        read_measurement(tmp_path / "two.npz")


def test_mat_sample_time_and_F_are_read(tmp_path, good):
    u, y = good
    scipy.io.savemat(tmp_path / "d.mat", {"u": u, "y": y, "sample_time": 2e-3,
                                          "F": 3})
    data = read_measurement(tmp_path / "d.mat")
    assert (data.downsampling_factor, data.sample_time) == (3, 2e-3)
    with pytest.raises(DataFileError, match="its variable 'sample_time' says"):
        read_measurement(tmp_path / "d.mat", sample_time=1e-3)


@pytest.mark.parametrize("name, scale", [("t", 1.0), ("time", 1.0), ("Time_s", 1.0),
                                         ("time_ms", 1e3), ("t_us", 1e6)])
def test_csv_time_column_gives_the_sample_time(tmp_path, good, name, scale):
    u, y = good
    time = [f"{k * 1e-3 * scale:.6f}" for k in range(u.size)]
    path = write_csv(tmp_path / "d.csv", {name: time, "u": u,
                                          "y": fast_column(y, 3)})
    data = read_measurement(path, F=3)
    assert data.sample_time == pytest.approx(1e-3, rel=1e-12)
    read_measurement(path, F=3, sample_time=1.0005e-3)  # within 0.1 %
    with pytest.raises(DataFileError, match=rf"the sample time 0\.0005 s was passed "
                       rf"but its time column '{name}' says 0\.001 s"):
        read_measurement(path, F=3, sample_time=0.5e-3)
    ignored = read_measurement(path, F=3, sample_time=0.5e-3, time_column=None)
    assert ignored.sample_time == 0.5e-3


def test_shipped_example_csv_time_column(tmp_path):
    from importlib.resources import files

    data = read_measurement(files("lrmfrf") / "data" / "wafer_stage_example.csv",
                            F=3)
    assert data.sample_time == pytest.approx(0.5e-3, rel=1e-9)


def test_csv_time_column_must_be_uniform_and_complete(tmp_path, good):
    u, y = good
    time = [k * 1e-3 + (0.5e-3 if k >= 10 else 0.0) for k in range(u.size)]
    path = write_csv(tmp_path / "d.csv", {"t": time, "u": u, "y": fast_column(y, 3)})
    with pytest.raises(DataFileError, match=r"time column 't' is not uniformly "
                       r"increasing .* the step from line 11 to the next row is "
                       r"0\.0015 s.*--time-column none"):
        read_measurement(path, F=3)
    assert read_measurement(path, F=3, time_column=None).sample_time is None
    time = [k * 1e-3 for k in range(u.size)]
    time[5] = None
    path = write_csv(tmp_path / "e.csv", {"t": time, "u": u, "y": fast_column(y, 3)})
    with pytest.raises(DataFileError, match=r"time column 't' has 1 empty.*line 7"):
        read_measurement(path, F=3)
    path = write_csv(tmp_path / "f.csv", {"clock": [k * 2e-3 for k in range(60)],
                                          "u": u, "y": fast_column(y, 3)})
    assert read_measurement(path, F=3).sample_time is None  # not a time name
    named = read_measurement(path, F=3, time_column="clock")
    assert named.sample_time == pytest.approx(2e-3)
    with pytest.raises(DataFileError, match="no column named 'when'.*--time-column"):
        read_measurement(path, F=3, time_column="when")
    with pytest.raises(DataFileError, match="is also the input or the output"):
        read_measurement(path, F=3, time_column="u")


# --------------------------------------------------------------------------
# The pandas parser and its cell-by-cell fallback agree (issue 12 item 12)
# --------------------------------------------------------------------------


def test_cells_pandas_leaves_as_text_are_parsed_as_before(tmp_path):
    """Blanks around numbers, inf/Infinity spellings and integers beyond 64 bits
    take the cell-by-cell path; the values are numpy's."""
    text = ("u,y\n 1.5 ,2\n2, 99999999999999999999999 \n-3,inf\n4,-Infinity\n"
            "5,NaN\n6,nan\n")
    path = tmp_path / "d.csv"
    path.write_text(text)
    u, y = lio._csv_columns(path, ["u", "y"], ",", 1, [0, 1], 100, capacity=8)
    np.testing.assert_array_equal(u, [1.5, 2, -3, 4, 5, 6])
    np.testing.assert_array_equal(y, [2, 1e23, np.inf, -np.inf, np.nan, np.nan])


def test_rows_shorter_or_longer_than_the_header(tmp_path):
    path = tmp_path / "d.csv"
    path.write_text("u,y\n1,5,extra\n2\n3,6\n4,,more,cells\n")
    data = read_measurement(path, F=2)
    np.testing.assert_array_equal(data.u_h, [1, 2, 3, 4])
    np.testing.assert_array_equal(data.y_l, [5, 6])


def test_huge_values_are_read_without_overflow_warnings(tmp_path, good):
    """The RMS in the checks squared the data: 1e300 overflowed with a
    RuntimeWarning; it is scaled first now (the RMS of c*x is c*RMS(x))."""
    import warnings

    u, y = good
    np.savez(tmp_path / "d.npz", u=u * 1e300, y=y * 1e300)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        data = read_measurement(tmp_path / "d.npz", F=3)
    rms = float(np.sqrt(np.mean(u**2)))
    line = next(c for c in data.checks if c.startswith("input RMS"))
    assert line.startswith(f"input RMS {rms * 1e300:.4g}, ")


def test_every_public_name_of_the_old_module_imports_from_the_package():
    """Item 11: lrmfrf/io.py became lrmfrf/io/ (readers, writers); every name
    the module exported still comes from ``lrmfrf.io``."""
    import lrmfrf.io
    from lrmfrf.io import readers, writers

    old = ["CSV_CHUNK_ROWS", "DEFAULT_MAX_SAMPLES", "FRF_COLUMNS",
           "SUPPORTED_FORMATS", "DataFileError", "Measurement", "atomic_open",
           "check_output_path", "file_sha256", "frf_table", "read_measurement",
           "write_frf_csv", "write_frf_npz"]
    assert set(old) <= set(lrmfrf.io.__all__)
    for name in lrmfrf.io.__all__:
        home = readers if name in readers.__all__ else writers
        assert getattr(lrmfrf.io, name) is getattr(home, name)


def test_atomic_group_writes_all_files_or_none(tmp_path, monkeypatch):
    folder = tmp_path / "new" / "out"
    with pytest.raises(RuntimeError, match="late failure"):
        with atomic_group() as group:
            group.write_bytes(folder / "a.txt", b"a")
            write_frf_csv(folder / "b.csv", frf_table(_FakeFit(
                np.random.default_rng(0))), group=group)
            raise RuntimeError("late failure")
    assert list(tmp_path.iterdir()) == []  # no files, no folders left
    (tmp_path / "a.txt").write_bytes(b"old a")
    (tmp_path / "b.txt").write_bytes(b"old b")
    real_replace = os.replace

    def failing(src, dst):
        if str(dst).endswith("b.txt"):
            raise PermissionError(13, "Permission denied", str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", failing)
    with pytest.raises(PermissionError):
        with atomic_group(overwrite=True) as group:
            group.write_bytes(tmp_path / "a.txt", b"new a")
            group.write_bytes(tmp_path / "b.txt", b"new b")
            group.write_bytes(tmp_path / "c.txt", b"new c")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]
    assert (tmp_path / "a.txt").read_bytes() == b"old a"
    assert (tmp_path / "b.txt").read_bytes() == b"old b"
    monkeypatch.setattr(os, "replace", real_replace)
    with pytest.raises(OutputExistsError, match="a.txt: the output file exists"):
        with atomic_group() as group:
            group.write_bytes(tmp_path / "a.txt", b"x")
    with atomic_group(overwrite=True) as group:
        group.write_bytes(tmp_path / "a.txt", b"new a")
        group.write_bytes(tmp_path / "d" / "e.txt", b"e")
    assert (tmp_path / "a.txt").read_bytes() == b"new a"
    assert (tmp_path / "d" / "e.txt").read_bytes() == b"e"
    assert not [p for p in tmp_path.rglob(".*")]  # no temporaries, no backups


def test_check_output_folder_messages(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match=r"f: --out is a file, not a folder"):
        check_output_folder(tmp_path / "f")
    with pytest.raises(ValueError, match=r"its parent .*f is a file, not a folder\. "
                       r"Choose a folder name"):
        check_output_folder(tmp_path / "f" / "g" / "h")
    with pytest.raises(ValueError, match="the output folder is the empty string"):
        check_output_folder("")
    assert check_output_folder(tmp_path / "new" / "x") == tmp_path / "new" / "x"
    assert issubclass(OutputExistsError, FileExistsError)
