"""Tests of the command line (through real subprocesses) and of lrmfrf.progress.

Every bad-input case runs ``python -m lrmfrf.cli`` in a subprocess and checks:
non-zero exit status, exactly one line on standard error naming the file, the
problem and the fix, and no traceback. The error cases are launched
concurrently by one module fixture to keep the run short.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import types
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from conftest import simulate_resonant

from lrmfrf import LRMBeyondNyquist
from lrmfrf.cli import main
from lrmfrf.io import FRF_COLUMNS
from lrmfrf.progress import progress, progress_enabled
from lrmfrf.signals import multisine

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "lrmfrf" / "data"
EXAMPLE_CSV = DATA / "wafer_stage_example.csv"
EXAMPLE_NPZ = DATA / "wafer_stage_example.npz"
FIT = ["--F", "3", "--sample-time", "0.5e-3"]


def run_cli(*args, cwd) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(REPO)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])
    )
    env["MPLBACKEND"] = "Agg"
    return subprocess.run(
        [sys.executable, "-m", "lrmfrf.cli", *map(str, args)],
        cwd=cwd, env=env, capture_output=True, text=True, timeout=300,
    )


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def write_csv(path: Path, u, y_column, header="u,y"):
    lines = [header]
    for a, b in zip(u, y_column, strict=True):
        lines.append(f"{float(a)!r},{'' if b is None else b}")
    path.write_text("\n".join(lines) + "\n")
    return path


def fast_column(y, F):
    col = [None] * (F * len(y))
    col[::F] = [repr(float(v)) for v in y]
    return col


@pytest.fixture(scope="module")
def records():
    rng = np.random.default_rng(21)
    u = multisine(600, rng=rng)
    y = simulate_resonant(u, 3, 1e-3, rng)
    return u, y


# --------------------------------------------------------------------------
# Bad input: one line on stderr, non-zero status, no traceback
# --------------------------------------------------------------------------

#: name -> (arguments, expected status, fragments of the one stderr line).
#: SUBPROCESS_CASES run as real subprocesses (every data and safety case of the
#: command-line issue); INPROCESS_CASES call main() in this process (usage
#: errors and the rest: same code path, much faster).
SUBPROCESS_CASES = {
    "missing file": (["fit", "nope.csv", *FIT, "--out", "o"], 1,
                     ["nope.csv", "no such file", "Check the path"]),
    "unknown format": (["fit", "data.xlsx", *FIT, "--out", "o"], 1,
                       ["data.xlsx", "unknown file format '.xlsx'", "Save the data"]),
    "unreadable npz": (["fit", "junk.npz", *FIT, "--out", "o"], 1,
                       ["junk.npz", "not a readable .npz archive", "numpy.savez"]),
    "missing column": (["fit", "good.csv", *FIT, "--output-column", "z", "--out",
                        "o"], 1,
                       ["good.csv", "no column named 'z'", "--output-column"]),
    "nan in input": (["fit", "nan_u.csv", *FIT, "--out", "o"], 1,
                     ["nan_u.csv", "input 'u' has 1 empty, NaN or inf", "line 12",
                      "fill in"]),
    "lengths do not match F": (["fit", "slow.csv", "--F", "4", "--sample-time",
                                "0.5e-3", "--out", "o"], 1,
                               ["slow.csv", "lengths do not match F=4", "N=600",
                                "M=200", "is F=3?", "Check --F"]),
    "non-numeric cell": (["fit", "text.csv", *FIT, "--out", "o"], 1,
                         ["text.csv", "non-numeric cell '0.3 V'", "line 8",
                          "Use numbers"]),
    "unreadable mat": (["fit", "junk.mat", *FIT, "--out", "o"], 1,
                       ["junk.mat", "not a readable MATLAB file", "-v7"]),
    "mat text variable": (["fit", "text.mat", *FIT, "--out", "o"], 1,
                          ["text.mat", "variable 'u' is not numeric", "Store 'u'"]),
    "nan in output": (["fit", "nan_y.csv", *FIT, "--out", "o"], 1,
                      ["nan_y.csv", "output 'y' has 1 empty, NaN or inf",
                       "line 32", "fill in"]),
    "output would replace input": (["fit", "frf.csv", *FIT, "--out", ".",
                                    "--force"], 1,
                                   ["frf.csv", "would replace the input file",
                                    "Choose another output folder"]),
}
INPROCESS_CASES = {
    "bad local degrees": (["fit", "good.csv", *FIT, "--half-window", "3", "--out",
                           "o"], 1,
                          ["good.csv", "Too few equations", "Increase --half-window"]),
    # the estimator's overlap check, in flags: it named `overlap` (the
    # parameter) next to --segment-length
    "overlap too large": (["fit", "good.csv", *FIT, "--method", "sa",
                           "--segment-length", "20", "--overlap", "30", "--out",
                           "o"], 1,
                          ["good.csv", "`--overlap` must be less than "
                           "`--segment-length`", "Got --overlap=30"]),
    "out is a file": (["fit", "good.csv", *FIT, "--out", "good.csv"], 1,
                      ["good.csv", "--out is a file"]),
    "existing output": (["fit", "good.csv", *FIT, "--out", "taken"], 1,
                        ["frf.csv", "exists already", "--force"]),
    "F is zero": (["fit", "good.csv", "--F", "0", "--sample-time", "1e-3", "--out",
                   "o"], 2, ["--F", "expected a positive integer, got '0'"]),
    "sample time missing": (["fit", "good.csv", "--F", "3", "--out", "o"], 2,
                            ["required", "--sample-time"]),
    "option of another method": (["fit", "good.csv", *FIT, "--method", "sa",
                                  "--den-degree", "3", "--out", "o"], 2,
                                 ["--den-degree", "does not apply", "--method sa"]),
    "demo negative seed": (["demo", "--seed", "-1"], 2,
                           ["--seed", "expected an integer >= 0, got '-1'"]),
    "demo snr not a number": (["demo", "--snr", "nan"], 2,
                              ["--snr", "expected a finite number"]),
    "no command": ([], 2, ["required: COMMAND"]),
    "example data exists": (["example-data", "--out", "."], 1,
                            ["wafer_stage_example.csv", "exists already",
                             "--force"]),
}


def _check_one_line(status, out, err, expected_status, fragments):
    assert status == expected_status, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith("lrmfrf")
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])
    assert out == ""


@pytest.fixture(scope="module")
def error_runs(tmp_path_factory, records):
    folder = tmp_path_factory.mktemp("cli_errors")
    u, y = records
    write_csv(folder / "good.csv", u, fast_column(y, 3))
    write_csv(folder / "slow.csv", u, [repr(float(v)) for v in y] + [None] * 400)
    u_nan = u.copy()
    u_nan[10] = np.nan
    write_csv(folder / "nan_u.csv", u_nan, fast_column(y, 3))
    y_col = fast_column(y, 3)
    y_col[30] = "nan"
    write_csv(folder / "nan_y.csv", u, y_col)
    y_col = fast_column(y, 3)
    y_col[6] = "0.3 V"
    write_csv(folder / "text.csv", u, y_col)
    write_csv(folder / "frf.csv", u, fast_column(y, 3))
    (folder / "data.xlsx").write_bytes(b"PK\x03\x04")
    (folder / "junk.npz").write_bytes(b"definitely not a zip archive")
    (folder / "junk.mat").write_bytes(b"\x00" * 300)
    scipy.io.savemat(folder / "text.mat", {"u": "volts", "y": y})
    (folder / "wafer_stage_example.csv").write_text("mine\n")
    (folder / "taken").mkdir()
    (folder / "taken" / "frf.csv").write_text("keep me\n")
    hashes = {p.name: sha256(p) for p in folder.iterdir() if p.is_file()}
    with ThreadPoolExecutor(max_workers=4) as pool:
        futures = {
            name: pool.submit(run_cli, *args, cwd=folder)
            for name, (args, _, _) in SUBPROCESS_CASES.items()
        }
        futures["debug"] = pool.submit(
            run_cli, "fit", "nope.csv", *FIT, "--out", "o", "--debug", cwd=folder
        )
        results = {name: future.result() for name, future in futures.items()}
    return folder, results, hashes


@pytest.mark.parametrize("case", sorted(SUBPROCESS_CASES))
def test_bad_input_subprocess_one_line_nonzero_status(error_runs, case):
    _, results, _ = error_runs
    _, status, fragments = SUBPROCESS_CASES[case]
    result = results[case]
    _check_one_line(result.returncode, result.stdout, result.stderr, status,
                    fragments)


@pytest.mark.parametrize("case", sorted(INPROCESS_CASES))
def test_bad_input_in_process_one_line_nonzero_status(
    error_runs, case, monkeypatch, capsys
):
    folder, _, _ = error_runs
    args, status, fragments = INPROCESS_CASES[case]
    monkeypatch.chdir(folder)
    capsys.readouterr()
    try:
        got = main(args)
    except SystemExit as exc:  # argparse usage errors
        got = exc.code
    captured = capsys.readouterr()
    _check_one_line(got, captured.out, captured.err, status, fragments)


def test_failed_runs_modify_no_file(error_runs):
    folder, _, hashes = error_runs
    after = {name: sha256(folder / name) for name in hashes}
    assert after == hashes
    assert (folder / "taken" / "frf.csv").read_text() == "keep me\n"
    assert not (folder / "o").exists() or not any((folder / "o").rglob("*.png"))
    assert not list(folder.rglob("*.tmp"))


def test_debug_shows_the_traceback(error_runs):
    result = error_runs[1]["debug"]
    assert result.returncode != 0
    assert "Traceback" in result.stderr and "DataFileError" in result.stderr


# --------------------------------------------------------------------------
# Success: the README example, outputs, safety of inputs and outputs
# --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def example_run(tmp_path_factory):
    """The README example, run with --out pointing at the input's folder."""
    if not EXAMPLE_CSV.exists():
        pytest.fail("the shipped example is missing: run scripts/make_example_data.py")
    folder = tmp_path_factory.mktemp("cli_example")
    assert main(["example-data", "--out", str(folder), "--quiet"]) == 0
    data = folder / EXAMPLE_CSV.name
    assert sha256(data) == sha256(EXAMPLE_CSV)
    assert sha256(folder / EXAMPLE_NPZ.name) == sha256(EXAMPLE_NPZ)
    before = sha256(data)
    result = run_cli("fit", data.name, *FIT, "--out", ".", cwd=folder)
    return folder, data, before, result


def test_example_writes_csv_npz_png_and_report(example_run):
    folder, data, before, result = example_run
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""
    assert "601 of 601 bins valid" in result.stdout
    assert sha256(data) == before  # the input, in the output folder, is untouched
    csv_text = (folder / "frf.csv").read_text().splitlines()
    assert csv_text[0] == ",".join(FRF_COLUMNS)
    assert len(csv_text) == 1 + 601
    assert (folder / "bode.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = (folder / "report.txt").read_text()
    for fragment in ("Data checks", "slow Nyquist frequency: 333.333 Hz",
                     "lengths: N = F*M = 3*400 = 1200", sha256(data),
                     "method: lrm (LRMBeyondNyquist)"):
        assert fragment in report
    with np.load(folder / "frf.npz", allow_pickle=False) as saved:
        assert str(saved["method"]) == "lrm"
        assert int(saved["downsampling_factor"]) == 3
    assert not list(folder.glob(".*.tmp"))


def test_example_frf_equals_library_fit(example_run):
    """The CLI computes what the library computes on the same records."""
    folder, _, _, result = example_run
    assert result.returncode == 0, result.stderr
    with np.load(EXAMPLE_NPZ, allow_pickle=False) as twin:
        u, y = twin["u"], twin["y"]
    est = LRMBeyondNyquist().fit(u, y, 3, sample_time=0.5e-3)
    table = np.loadtxt(folder / "frf.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(table[:, 0], est.frequencies_, rtol=1e-9)
    frf = table[:, 1] + 1j * table[:, 2]
    # The CSV holds y with 10 significant digits and the FRF is written with
    # 10: a relative difference far below the estimate's own std.
    scale = np.abs(est.frf_) + est.frf_std_
    assert np.max(np.abs(frf - est.frf_) / scale) < 1e-6
    np.testing.assert_allclose(table[:, 5], est.frf_std_, rtol=1e-5)


def test_existing_output_needs_force_and_force_replaces(example_run):
    folder, data, before, _ = example_run
    report = folder / "report.txt"
    report.write_text("old report\n")
    refused = run_cli("fit", data.name, *FIT, "--out", ".", cwd=folder)
    assert refused.returncode == 1
    assert "exists already" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    assert report.read_text() == "old report\n"
    forced = run_cli("fit", data.name, *FIT, "--out", ".", "--force", "--quiet",
                     cwd=folder)
    assert forced.returncode == 0, forced.stderr
    assert forced.stdout == "" and forced.stderr == ""
    assert "Data checks" in report.read_text()
    assert sha256(data) == before


def test_several_files_get_one_subfolder_each(tmp_path, capsys):
    status = main(["fit", str(EXAMPLE_CSV), str(EXAMPLE_NPZ), *FIT, "--method",
                   "lpm", "--degree", "2", "--no-plot", "--out",
                   str(tmp_path / "out")])
    assert status == 0, capsys.readouterr().err
    folders = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert folders == ["wafer_stage_example_csv", "wafer_stage_example_npz"]
    tables = [
        np.loadtxt(tmp_path / "out" / name / "frf.csv", delimiter=",", skiprows=1)
        for name in folders
    ]
    # The CSV and NPZ twins hold the same records (CSV to 10 digits).
    frfs = [t[:, 1] + 1j * t[:, 2] for t in tables]
    assert np.max(np.abs(frfs[0] - frfs[1]) / np.abs(frfs[1])) < 1e-6
    assert not (tmp_path / "out" / folders[0] / "bode.png").exists()
    assert "degree=2" in (tmp_path / "out" / folders[0] / "report.txt").read_text()


def test_identifiability_warning_is_one_line_and_reported(
    tmp_path, records, monkeypatch, capsys
):
    u, _ = records
    # An input with energy only in the lowest band leaves the windows that see
    # the empty aliased bands rank-deficient.
    U = np.zeros(301, complex)
    U[1:60] = np.exp(2j * np.pi * np.random.default_rng(3).random(59))
    u_low = np.fft.irfft(U, 600)
    y = np.convolve(u_low, [0.5, 0.2])[:600][::3]
    write_csv(tmp_path / "low.csv", u_low, fast_column(y, 3))
    monkeypatch.chdir(tmp_path)
    status = main(["fit", "low.csv", *FIT, "--method", "lrm", "--den-degree", "1",
                   "--no-plot", "--out", "o"])
    err = capsys.readouterr().err
    assert status == 0, err
    warnings_lines = err.strip().splitlines()
    assert warnings_lines and all(
        line.startswith("lrmfrf: warning: low.csv:") for line in warnings_lines
    )
    assert "not identifiable" in (tmp_path / "o" / "report.txt").read_text()


# --------------------------------------------------------------------------
# demo subcommand wiring (in-process, with a stand-in lrmfrf.demo)
# --------------------------------------------------------------------------


def test_demo_calls_run_demo_and_prints_the_table(monkeypatch, tmp_path, capsys):
    calls = []

    def run_demo(out_dir, *, seed=0, snr_db=45.0, overwrite=False):
        calls.append((Path(out_dir), seed, snr_db, overwrite))
        return types.SimpleNamespace(table="method  error\nLRM  0.1",
                                     files=[Path(out_dir) / "a.png"])

    stub = types.ModuleType("lrmfrf.demo")
    stub.run_demo = run_demo
    monkeypatch.setitem(sys.modules, "lrmfrf.demo", stub)
    status = main(["demo", "--out", str(tmp_path), "--seed", "4", "--snr", "30",
                   "--force"])
    assert status == 0
    assert calls == [(tmp_path, 4, 30.0, True)]
    out = capsys.readouterr().out
    assert "LRM  0.1" in out and "a.png" in out


def test_demo_errors_are_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "lrmfrf.demo", None)
    assert main(["demo", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the demo is not available" in err[0]

    def failing(out_dir, **kwargs):
        raise FileExistsError(f"{out_dir}/table.csv exists. Pass --force.")

    stub = types.ModuleType("lrmfrf.demo")
    stub.run_demo = failing
    monkeypatch.setitem(sys.modules, "lrmfrf.demo", stub)
    assert main(["demo", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "table.csv exists" in err[0]


# --------------------------------------------------------------------------
# progress
# --------------------------------------------------------------------------


def _read_all(fd) -> str:
    chunks = []
    while True:
        try:
            data = os.read(fd, 4096)
        except OSError:  # EIO: the terminal's other end is closed
            break
        if not data:
            break
        chunks.append(data)
    return b"".join(chunks).decode("utf-8", "replace")


def test_cli_progress_bar_on_a_terminal_and_not_in_a_pipe(tmp_path):
    """Over several files the CLI shows a tqdm bar when standard error is a
    terminal (a real pseudo-terminal here) and none when it is a pipe."""
    pytest.importorskip("tqdm")
    if not hasattr(os, "openpty"):
        pytest.skip("no pseudo-terminals on this platform")
    args = ["fit", EXAMPLE_CSV, EXAMPLE_NPZ, *FIT, "--method", "sa", "--no-plot"]
    env = dict(os.environ, PYTHONPATH=str(REPO), MPLBACKEND="Agg")
    master, slave = os.openpty()
    try:
        import fcntl
        import struct
        import termios

        # A terminal of 24 x 100 characters (a new pty has size 0 x 0, in
        # which tqdm draws nothing).
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
        proc = subprocess.Popen(
            [sys.executable, "-m", "lrmfrf.cli", *map(str, args), "--out",
             str(tmp_path / "tty")],
            stdout=subprocess.PIPE, stderr=slave, env=env, cwd=tmp_path,
        )
        os.close(slave)
        terminal = _read_all(master)
        proc.communicate(timeout=300)
        assert proc.returncode == 0, terminal
    finally:
        os.close(master)
    assert "files: 100%" in terminal and "2/2" in terminal, terminal
    piped = run_cli(*args, "--out", tmp_path / "pipe", cwd=tmp_path)
    assert piped.returncode == 0, piped.stderr
    assert piped.stderr == ""


class _Stream:
    def __init__(self, tty):
        self.tty = tty

    def isatty(self):
        return self.tty


def test_progress_disabled_returns_the_iterable_itself():
    items = [1, 2, 3]
    assert progress(items, enabled=False) is items


def test_progress_enabled_wraps_in_tqdm_and_yields_the_same_items(monkeypatch):
    tqdm = pytest.importorskip("tqdm")
    bar = progress(range(5), enabled=True, desc="x", disable=False,
                   file=open(os.devnull, "w"))
    assert isinstance(bar, tqdm.tqdm)
    assert list(bar) == [0, 1, 2, 3, 4]


def test_progress_without_tqdm_falls_back(monkeypatch):
    monkeypatch.setitem(sys.modules, "tqdm", None)
    items = [1, 2]
    assert progress(items, enabled=True) is items


def test_progress_enabled_none_follows_the_terminal():
    assert progress_enabled(None, stream=_Stream(True)) is True
    assert progress_enabled(None, stream=_Stream(False)) is False
    assert progress_enabled(True, stream=_Stream(False)) is True
    assert progress_enabled(None, stream=object()) is False


def test_fit_without_matplotlib_writes_the_rest_and_says_why(tmp_path):
    """matplotlib is optional for `fit`: one warning line with the install hint,
    the CSV, NPZ and report are written, and the report names the skip."""
    code = ("import sys; sys.modules['matplotlib'] = None; "
            "from lrmfrf.cli import main; sys.exit(main(sys.argv[1:]))")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    done = subprocess.run(
        [sys.executable, "-c", code, "fit", str(EXAMPLE_CSV), *FIT, "--out", "o"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )
    assert done.returncode == 0, done.stderr
    hint = 'bode.png not drawn: matplotlib is missing (pip install "lrmfrf[plot]")'
    assert done.stderr.strip().splitlines() == [
        f"lrmfrf: warning: {EXAMPLE_CSV}: {hint}"]
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == [
        "frf.csv", "frf.npz", "report.txt"]
    assert hint in (tmp_path / "o" / "report.txt").read_text()


# --------------------------------------------------------------------------
# Issue 12: reading, outputs all or nothing, sample time, options
# --------------------------------------------------------------------------


def _run(args, capsys):
    """main() in this process: (status, stdout, stderr)."""
    capsys.readouterr()
    try:
        status = main([str(a) for a in args])
    except SystemExit as exc:  # argparse usage errors
        status = exc.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_one_character_cells_fit_from_the_command_line(tmp_path):
    """Item 1: one-digit cells between empty cells were refused as 'n'."""
    rng = np.random.default_rng(5)
    u = rng.integers(0, 10, 600)
    y = rng.integers(0, 10, 200)
    lines = ["u,y"] + [f"{a},{y[k // 3] if k % 3 == 0 else ''}"
                       for k, a in enumerate(u)]
    (tmp_path / "d.csv").write_text("\n".join(lines) + "\n")
    done = run_cli("fit", "d.csv", "--F", "3", "--sample-time", "1e-3", "--out",
                   "o", "--no-plot", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "non-numeric" not in done.stderr
    report = (tmp_path / "o" / "report.txt").read_text()
    assert "fast-rate column with slow samples at every F=3-th row, M=200" in report


def _scaled_npz(tmp_path, records, scale):
    u, y = records
    np.savez(tmp_path / "scaled.npz", u=u * scale, y=y * scale)
    return tmp_path / "scaled.npz"


def test_failure_at_the_last_output_leaves_no_output(tmp_path, records, capsys,
                                                     monkeypatch):
    """Item 3: everything is computed first; a failure while writing the last
    file (report.txt) leaves none of the four files, nor the folder made."""
    from lrmfrf.io import writers

    data = _scaled_npz(tmp_path, records, 1.0)
    real_write = writers.AtomicGroup.write_bytes

    def failing(self, path, content):
        if Path(path).name == "report.txt":
            raise OSError(28, "No space left on device", str(path))
        return real_write(self, path, content)

    monkeypatch.setattr(writers.AtomicGroup, "write_bytes", failing)
    status, _, err = _run(["fit", data, *FIT, "--out", tmp_path / "new" / "o"],
                          capsys)
    assert status == 1 and "No space left on device" in err
    assert not (tmp_path / "new").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scaled.npz"]


def test_failure_while_moving_the_last_output_restores_the_old_files(
        tmp_path, records, capsys, monkeypatch):
    """Item 3, commit step: with --force over an earlier run, a failing
    os.replace of report.txt puts every old file back and leaves no new one."""
    data = _scaled_npz(tmp_path, records, 1.0)
    out = tmp_path / "o"
    assert _run(["fit", data, *FIT, "--no-plot", "--out", out], capsys)[0] == 0
    before = {p.name: sha256(p) for p in out.iterdir()}
    real_replace = os.replace

    def failing(src, dst):
        if Path(dst).name == "report.txt":
            raise PermissionError(13, "Permission denied", str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", failing)
    status, _, err = _run(["fit", data, *FIT, "--method", "sa", "--out", out,
                           "--force"], capsys)
    assert status == 1 and "Permission denied" in err
    assert {p.name: sha256(p) for p in out.iterdir()} == before  # no bode.png


def test_huge_scale_gives_all_outputs_or_none(tmp_path, records, capsys):
    """Item 3: SA on data scaled by 1e300 wrote NaN tables marked valid and no
    report. Now either the run succeeds with finite valid bins, or it fails and
    writes nothing."""
    data = _scaled_npz(tmp_path, records, 1e300)
    out = tmp_path / "o"
    status, _, err = _run(["fit", data, *FIT, "--method", "sa", "--out", out],
                          capsys)
    if status == 0:
        assert sorted(p.name for p in out.iterdir()) == sorted(
            ["bode.png", "frf.csv", "frf.npz", "report.txt"])
        with np.load(out / "frf.npz") as saved:
            valid = saved["valid"]
            assert np.isfinite(saved["frf"][valid]).all()
    else:
        assert status == 1 and "not finite" in err, err
        assert not out.exists()


def test_sample_time_from_the_file_and_contradictions(tmp_path, records, capsys):
    """Item 13: a contradicting --sample-time is refused; an omitted one is the
    file's (NPZ key, CSV time column)."""
    u, y = records
    np.savez(tmp_path / "d.npz", u=u, y=y, sample_time=0.5e-3)
    status, _, err = _run(["fit", tmp_path / "d.npz", "--F", "3", "--sample-time",
                           "1e-3", "--out", tmp_path / "a"], capsys)
    assert status == 1
    assert "the sample time 0.001 s was passed but its array 'sample_time' says " \
           "0.0005 s" in err and "omit --sample-time" in err
    assert not (tmp_path / "a").exists()
    status, _, err = _run(["fit", tmp_path / "d.npz", "--F", "3", "--no-plot",
                           "--out", tmp_path / "b"], capsys)
    assert status == 0, err
    report = (tmp_path / "b" / "report.txt").read_text()
    assert "fast sample time: 0.0005 s (slow sample time 0.0015 s; read from the " \
           "file)" in report
    assert "slow Nyquist frequency: 333.333 Hz" in report

    lines = ["time,u,y"] + [f"{k * 1e-3:.3f},{float(a)!r},"
                            f"{repr(float(y[k // 3])) if k % 3 == 0 else ''}"
                            for k, a in enumerate(u)]
    (tmp_path / "t.csv").write_text("\n".join(lines) + "\n")
    status, _, err = _run(["fit", tmp_path / "t.csv", "--F", "3", "--sample-time",
                           "0.5e-3", "--out", tmp_path / "c"], capsys)
    assert status == 1 and "its time column 'time' says 0.001 s" in err
    status, _, err = _run(["fit", tmp_path / "t.csv", "--F", "3", "--sample-time",
                           "0.5e-3", "--time-column", "none", "--no-plot", "--out",
                           tmp_path / "d"], capsys)
    assert status == 0, err


def test_F_from_the_npz_and_contradiction(tmp_path, records, capsys):
    status, _, err = _run(["fit", EXAMPLE_NPZ, "--no-plot", "--out",
                           tmp_path / "a"], capsys)
    assert status == 0, err
    assert "F=3 read from its array 'downsampling_factor'" in (
        tmp_path / "a" / "report.txt").read_text()
    status, _, err = _run(["fit", EXAMPLE_NPZ, "--F", "2", "--out", tmp_path / "b"],
                          capsys)
    assert status == 1 and "F=2 was passed but its array 'downsampling_factor' " \
                           "says F=3" in err


def test_F_accepts_integral_values_like_the_api(tmp_path, capsys):
    """Item 6/19: --F 3.0 is 3 (as fit(..., F=3.0)); --F 3.5 is refused."""
    status, _, err = _run(["fit", EXAMPLE_CSV, "--F", "3.0", "--no-plot", "--out",
                           tmp_path / "a"], capsys)
    assert status == 0, err
    status, out, err = _run(["fit", EXAMPLE_CSV, "--F", "3.5", "--out",
                             tmp_path / "b"], capsys)
    _check_one_line(status, out, err, 2, ["--F", "expected a positive integer, "
                                          "got '3.5'"])


def test_out_under_a_file_and_empty_out(tmp_path, capsys):
    """Item 6: --out whose parent is a file gave a bare Errno; --out '' meant
    the current folder."""
    (tmp_path / "plain").write_text("x")
    status, out, err = _run(["fit", EXAMPLE_CSV, *FIT, "--out",
                             tmp_path / "plain" / "o"], capsys)
    _check_one_line(status, out, err, 1, ["its parent", "plain is a file, not a "
                                          "folder", "Choose a folder name"])
    assert "Errno" not in err
    status, out, err = _run(["fit", EXAMPLE_CSV, *FIT, "--out", ""], capsys)
    _check_one_line(status, out, err, 2, ["--out", "expected a folder name",
                                          "'.' for the current folder"])
    status, out, err = _run(["example-data", "--out", ""], capsys)
    assert status == 2
    for command in (["demo"], ["example-data"]):
        status, out, err = _run([*command, "--out", tmp_path / "plain" / "o"],
                                capsys)
        _check_one_line(status, out, err, 1, ["plain is a file, not a folder"])


def test_warnings_are_one_line_and_quiet_silences_them(tmp_path, capsys,
                                                       monkeypatch):
    """Item 6: a Python warning outside the fit (here from the plot) was shown
    in Python's format (file, line, source); now one line, none with --quiet."""
    import warnings

    import lrmfrf.plotting

    real = lrmfrf.plotting.plot_frf

    def warning_plot(*args, **kwargs):
        warnings.warn("the plot is crowded", UserWarning, stacklevel=2)
        return real(*args, **kwargs)

    monkeypatch.setattr(lrmfrf.plotting, "plot_frf", warning_plot)
    status, _, err = _run(["fit", EXAMPLE_CSV, *FIT, "--out", tmp_path / "a"],
                          capsys)
    assert status == 0
    assert err.strip().splitlines() == ["lrmfrf: warning: the plot is crowded"]
    status, out, err = _run(["fit", EXAMPLE_CSV, *FIT, "--quiet", "--out",
                             tmp_path / "b"], capsys)
    assert status == 0 and out == "" and err == ""


def test_quiet_silences_estimator_warnings(tmp_path, capsys):
    U = np.zeros(301, complex)
    U[1:60] = np.exp(2j * np.pi * np.random.default_rng(3).random(59))
    u_low = np.fft.irfft(U, 600)
    y = np.convolve(u_low, [0.5, 0.2])[:600][::3]
    write_csv(tmp_path / "low.csv", u_low, fast_column(y, 3))
    status, out, err = _run(["fit", tmp_path / "low.csv", *FIT, "--den-degree", "1",
                             "--no-plot", "--quiet", "--out", tmp_path / "o"],
                            capsys)
    assert status == 0 and out == "" and err == ""
    assert "not identifiable" in (tmp_path / "o" / "report.txt").read_text()


def test_existing_output_message_names_force_not_the_api(tmp_path, capsys):
    """Item 14: CLI text says --force, not (overwrite=True)."""
    assert _run(["fit", EXAMPLE_CSV, *FIT, "--no-plot", "--out", tmp_path],
                capsys)[0] == 0
    status, out, err = _run(["fit", EXAMPLE_CSV, *FIT, "--out", tmp_path], capsys)
    _check_one_line(status, out, err, 1, ["exists already", "Pass --force"])
    assert "overwrite" not in err


def test_sk_iterations_and_num_degree_reach_the_estimator(tmp_path, capsys):
    status, _, err = _run(["fit", EXAMPLE_CSV, *FIT, "--sk-iterations", "2",
                           "--num-degree", "3", "--no-plot", "--out",
                           tmp_path / "a"], capsys)
    assert status == 0, err
    report = (tmp_path / "a" / "report.txt").read_text()
    assert "set on the command line: num_degree=3, sk_iterations=2" in report
    assert "sk_iterations=2" in report.split("estimator parameters:")[1]
    status, out, err = _run(["fit", EXAMPLE_CSV, *FIT, "--method", "lpm",
                             "--sk-iterations", "1", "--out", tmp_path / "b"],
                            capsys)
    _check_one_line(status, out, err, 2, ["--sk-iterations", "does not apply",
                                          "--method lpm"])


def test_lpm_num_degree_and_deprecated_degree(tmp_path, capsys):
    """Item 8: --num-degree for LPM; --degree still works for one release with
    a deprecation line on stderr; both together are refused."""
    status, _, err = _run(["fit", EXAMPLE_CSV, *FIT, "--method", "lpm",
                           "--num-degree", "3", "--no-plot", "--out",
                           tmp_path / "a"], capsys)
    assert status == 0 and err == ""
    new = (tmp_path / "a" / "frf.csv").read_text()
    status, _, err = _run(["fit", EXAMPLE_CSV, *FIT, "--method", "lpm",
                           "--degree", "3", "--no-plot", "--out", tmp_path / "b"],
                          capsys)
    assert status == 0
    assert err.strip().splitlines() == [
        "lrmfrf: warning: --degree is deprecated and will be removed in the next "
        "release; use --num-degree"]
    assert (tmp_path / "b" / "frf.csv").read_text() == new
    status, out, err = _run(["fit", EXAMPLE_CSV, *FIT, "--method", "lpm",
                             "--degree", "3", "--num-degree", "3", "--out",
                             tmp_path / "c"], capsys)
    _check_one_line(status, out, err, 2, ["--degree and --num-degree"])


@pytest.mark.parametrize("method", ["lrm", "lpm"])
def test_select_fits_the_cv_class(tmp_path, capsys, monkeypatch, method):
    """Item 14: --select CRITERION goes through LRM/LPMBeyondNyquistCV."""
    from lrmfrf.estimators import selection

    seen = []
    name = {"lrm": "LRMBeyondNyquistCV", "lpm": "LPMBeyondNyquistCV"}[method]
    real = getattr(selection, name)

    class Spy(real):
        def fit(self, *args, **kwargs):
            seen.append(self.criterion)
            return super().fit(*args, **kwargs)

    monkeypatch.setattr(selection, name, Spy)
    status, _, err = _run(["fit", EXAMPLE_CSV, *FIT, "--method", method,
                           "--select", "gcv", "--no-plot", "--out", tmp_path],
                          capsys)
    assert status == 0, err
    assert seen == ["gcv"]
    report = (tmp_path / "report.txt").read_text()
    line = next(x for x in report.splitlines() if x.startswith("selected by gcv: "))
    assert "half_window=" in line and "transient_degree=" in line


@pytest.mark.parametrize("args, fragments", [
    (["--method", "sa", "--select", "aicc"], ["--select applies to --method lrm "
                                               "or lpm, not sa"]),
    (["--select", "aicc", "--half-window", "9"], ["--half-window does not apply "
                                                   "with --select"]),
    (["--select", "bic"], ["--select", "invalid choice"]),
    (["--freq-range", "100", "50"], ["--freq-range 100 50: LO must be below HI"]),
    (["--freq-range", "10", "100", "--no-plot"], ["--no-plot"]),
])
def test_option_combinations_refused(tmp_path, capsys, args, fragments):
    status, out, err = _run(["fit", EXAMPLE_CSV, *FIT, *args, "--out", tmp_path],
                            capsys)
    _check_one_line(status, out, err, 2, fragments)


def test_freq_range_and_units_reach_the_bode_plot(tmp_path, capsys, monkeypatch):
    import lrmfrf.plotting

    calls = []
    real = lrmfrf.plotting.plot_frf

    def spy(*args, **kwargs):
        calls.append(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(lrmfrf.plotting, "plot_frf", spy)
    status, _, err = _run(["fit", EXAMPLE_CSV, *FIT, "--freq-range", "50", "500",
                           "--units", "m/N", "--out", tmp_path], capsys)
    assert status == 0, err
    assert calls[0]["freq_range"] == (50.0, 500.0) and calls[0]["units"] == "m/N"
    assert (tmp_path / "bode.png").read_bytes()[:4] == b"\x89PNG"


def test_every_option_has_help_text():
    """Item 14: diagnose --help had no help for its column options."""
    from lrmfrf.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for command, subparser in sub.choices.items():
        for action in subparser._actions:
            assert action.help, (command, action.option_strings or action.dest)


def test_console_script_entry_point_still_resolves():
    """pyproject's `lrmfrf = "lrmfrf.cli:main"` and `python -m lrmfrf.cli`."""
    import importlib

    assert importlib.import_module("lrmfrf.cli").main is main
    done = run_cli("--version", cwd=REPO)
    assert done.returncode == 0 and done.stdout.startswith("lrmfrf ")
