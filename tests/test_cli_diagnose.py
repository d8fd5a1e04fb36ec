"""`lrmfrf diagnose` through a real subprocess: model file + data file -> report."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lrmfrf.paper import paper_experiment
from lrmfrf.plants import wafer_stage

REPO = Path(__file__).resolve().parents[1]
MODEL = """\
from lrmfrf.plants import wafer_stage

stage = wafer_stage()
plant = stage.plant[0, 0]
controller = stage.controller
"""


def _cli(*args, cwd):
    env = dict(os.environ, PYTHONPATH=str(REPO), MPLBACKEND="Agg")
    return subprocess.run([sys.executable, "-m", "lrmfrf.cli", *args], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("diag")
    (folder / "model.py").write_text(MODEL)
    (folder / "broken.py").write_text("x = 1\n")
    rng = np.random.default_rng(3)
    experiment = paper_experiment(wafer_stage().G_y4, rng=rng)
    np.savez(folder / "data.npz", u=experiment.u_h, y=experiment.y_l)
    return folder


def test_diagnose_command_agreeing_model(files):
    """Data simulated from the model itself: no findings, gap about 1."""
    done = _cli("diagnose", "model.py", "data.npz", "--F", "3", "--sample-time",
                "0.5e-3", "--out", "out", "--quiet", cwd=files)
    assert done.returncode == 0, done.stderr
    report = json.loads((files / "out" / "diagnosis.json").read_text())
    assert report["findings"] == []
    assert report["gap_before"] < 1.5
    assert (files / "out" / "diagnosis.png").stat().st_size > 0
    assert "diagnosis" in (files / "out" / "diagnosis.txt").read_text().lower()
    again = _cli("diagnose", "model.py", "data.npz", "--F", "3", "--sample-time",
                 "0.5e-3", "--out", "out", cwd=files)
    assert again.returncode != 0 and "--force" in again.stderr


@pytest.mark.parametrize("model, match", [
    ("missing.py", "model file not found"),
    ("broken.py", "defines no `plant`"),
])
def test_diagnose_command_bad_model(files, model, match):
    done = _cli("diagnose", model, "data.npz", "--F", "3", "--sample-time",
                "0.5e-3", "--out", "bad", cwd=files)
    assert done.returncode == 1
    assert match in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert "Traceback" not in done.stderr


# --------------------------------------------------------------------------
# Issue 12: names, sample time, outputs all or nothing (in-process, stubbed)
# --------------------------------------------------------------------------


class _Report:
    def __init__(self, fail_plot=False):
        self.fail_plot = fail_plot

    def summary(self):
        return "diagnosis: nothing missing\n"

    def to_dict(self):
        return {"findings": []}

    def plot(self):
        if self.fail_plot:
            raise RuntimeError("figure failed")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots()
        return {"figure": fig, "axes": ax}


def _stub(monkeypatch, signature: str, calls: list, report=None):
    """Replace lrmfrf.discrepancy.diagnose by a stub with the given keywords."""
    namespace = {}
    exec(f"def diagnose(plant, u_h, y_l, F, *, controller=None, {signature}):\n"
         "    calls.append(dict(locals()))\n"
         "    return report\n", {"calls": calls, "report": report or _Report()},
         namespace)
    import lrmfrf.discrepancy

    monkeypatch.setattr(lrmfrf.discrepancy, "diagnose", namespace["diagnose"])


def _main(args, capsys):
    from lrmfrf.cli import main

    capsys.readouterr()
    try:
        status = main([str(a) for a in args])
    except SystemExit as exc:
        status = exc.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


@pytest.fixture
def plain_data(tmp_path):
    rng = np.random.default_rng(4)
    np.savez(tmp_path / "plain.npz", u=rng.standard_normal(600),
             y=rng.standard_normal(200))
    (tmp_path / "model.py").write_text(MODEL)
    return tmp_path


def test_diagnose_passes_the_new_names(plain_data, capsys, monkeypatch):
    """Item 8: --seed goes to rng=, --smoothing-bins to smoothing_bins=, and the
    sample time comes from the model's dt when neither flag nor file has it."""
    calls = []
    _stub(monkeypatch, "rng=None, smoothing_bins=9, sample_time=None", calls)
    status, _, err = _main(["diagnose", plain_data / "model.py",
                            plain_data / "plain.npz", "--F", "3", "--seed", "5",
                            "--smoothing-bins", "7", "--no-plot", "--out",
                            plain_data / "o"], capsys)
    assert status == 0, err
    assert calls[0]["rng"] == 5 and calls[0]["smoothing_bins"] == 7
    assert calls[0]["sample_time"] == pytest.approx(wafer_stage().plant.dt)
    assert sorted(p.name for p in (plain_data / "o").iterdir()) == [
        "diagnosis.json", "diagnosis.txt"]


def test_diagnose_needs_a_sample_time_from_somewhere(plain_data, capsys,
                                                     monkeypatch):
    (plain_data / "ct.py").write_text("import control\n"
                                      "plant = control.tf([1], [1, 1])\n")
    _stub(monkeypatch, "sample_time=None, rng=None", [])
    status, out, err = _main(["diagnose", plain_data / "ct.py",
                              plain_data / "plain.npz", "--F", "3", "--out",
                              plain_data / "o"], capsys)
    assert status == 2 and out == ""
    assert "--sample-time is required" in err and len(err.splitlines()) == 1


def test_diagnose_refuses_a_contradicting_sample_time(files, capsys):
    rng = np.random.default_rng(6)
    np.savez(files / "stamped.npz", u=rng.standard_normal(600),
             y=rng.standard_normal(200), sample_time=0.5e-3)
    status, _, err = _main(["diagnose", files / "model.py", files / "stamped.npz",
                            "--F", "3", "--sample-time", "1e-3", "--out",
                            files / "contradiction"], capsys)
    assert status == 1
    assert "its array 'sample_time' says 0.0005 s" in err
    assert not (files / "contradiction").exists()


def test_diagnose_outputs_all_or_nothing(plain_data, capsys, monkeypatch):
    """Item 3: the figure is drawn before anything is written; its failure
    leaves no diagnosis.txt/.json."""
    _stub(monkeypatch, "sample_time=None, rng=None", [],
          report=_Report(fail_plot=True))
    status, _, err = _main(["diagnose", plain_data / "model.py",
                            plain_data / "plain.npz", "--F", "3", "--out",
                            plain_data / "o"], capsys)
    assert status == 1 and "figure failed" in err
    assert not (plain_data / "o").exists()


# --------------------------------------------------------------------------
# MIMO: comma-separated columns, a 2x2 plant and controller (issue 25)
# --------------------------------------------------------------------------

MIMO_MODEL = """\
from lrmfrf.discrepancy.hidden_mimo import two_by_two_stage
from lrmfrf.plants import mimo_wafer_stage

stage = two_by_two_stage(mimo_wafer_stage(downsampling_factor=3), loop="closed")
plant = stage.plant
controller = stage.controller{suffix}
"""
MIMO_COLUMNS = ("--input-column", "u1,u2", "--output-column", "y1, y2")


def _mimo_model(folder, name="mimo.py", suffix=""):
    path = folder / name
    path.write_text(MIMO_MODEL.format(suffix=suffix))
    return path


def _mimo_csv(path, u, y, F, sample_time):
    """Two fast inputs and two slow outputs on the fast grid (empty cells)."""
    rows = ["t,u1,u2,y1,y2"]
    for k in range(u.shape[1]):
        slow = [repr(float(y[o, k // F])) if k % F == 0 else "" for o in range(2)]
        rows.append(",".join([repr(k * sample_time), repr(float(u[0, k])),
                              repr(float(u[1, k])), *slow]))
    path.write_text("\n".join(rows) + "\n")
    return path


def test_diagnose_mimo_csv_names_the_hidden_gain(tmp_path, capsys, monkeypatch):
    """End to end on a 2x2 closed loop simulated by the package: a hidden gain
    of 1.15 on both inputs is named from a CSV with two input and two output
    columns; the report names the columns and the figure is the Bode grid
    with the column names. (The real diagnose, with fewer calibration runs to
    keep the test short.)"""
    import functools

    import lrmfrf.discrepancy
    from lrmfrf.discrepancy.hidden import HiddenEffect
    from lrmfrf.discrepancy.hidden_mimo import (
        mimo_hidden_effect_experiment,
        two_by_two_stage,
    )
    from lrmfrf.discrepancy.report import DiagnosisReport
    from lrmfrf.plants import mimo_wafer_stage

    stage = two_by_two_stage(mimo_wafer_stage(downsampling_factor=3),
                             loop="closed")
    experiment = mimo_hidden_effect_experiment(
        HiddenEffect("gain", {"gain": 1.15}), stage=stage, rng=7, n_samples=900)
    data = _mimo_csv(tmp_path / "d.csv", experiment.u_h[0], experiment.y_l[0],
                     experiment.F, experiment.sample_time)
    model = _mimo_model(tmp_path)
    monkeypatch.setattr(lrmfrf.discrepancy, "diagnose", functools.partial(
        lrmfrf.discrepancy.diagnose, calibration_runs=2, debias_rounds=0))
    grids = []
    real_grid = DiagnosisReport.plot_grid

    def spy(self, **kwargs):
        grids.append(kwargs)
        return real_grid(self, **kwargs)

    monkeypatch.setattr(DiagnosisReport, "plot_grid", spy)
    out = tmp_path / "out"
    status, stdout, err = _main(["diagnose", model, data, "--F", "3", *MIMO_COLUMNS,
                                 "--out", out], capsys)
    assert status == 0, err
    report = json.loads((out / "diagnosis.json").read_text())
    assert [f["effect"] for f in report["findings"]] == ["gain"]
    assert report["findings"][0]["parameters"]["gain"] == pytest.approx(1.15,
                                                                        rel=0.03)
    assert report["gap_before"] > 3 and report["gap_after"] < 1.5
    assert report["calibration"]["n_entries"] == 4
    assert (report["n_outputs"], report["n_inputs"]) == (2, 2)
    assert report["output_columns"] == ["y1", "y2"]
    assert report["input_columns"] == ["u1", "u2"]
    text = (out / "diagnosis.txt").read_text()
    assert text == stdout.rstrip("\n")
    assert ("entries: 2 outputs x 2 inputs, outputs 0=y1, 1=y2; inputs 0=u1, "
            "1=u2") in text.splitlines()[2]
    assert grids == [{"output_labels": ("y1", "y2"), "input_labels": ("u1", "u2")}]
    assert (out / "diagnosis.png").read_bytes()[:4] == b"\x89PNG"


@pytest.fixture(scope="module")
def mimo_files(tmp_path_factory):
    """Random 2x2 records (never diagnosed: the errors come first)."""
    folder = tmp_path_factory.mktemp("mimo_errors")
    rng = np.random.default_rng(8)
    np.savez(folder / "d.npz", u=rng.standard_normal(600),
             y=rng.standard_normal(200), u1=rng.standard_normal(600),
             u2=rng.standard_normal(600), y1=rng.standard_normal(200),
             y2=rng.standard_normal(200), sample_time=0.5e-3)
    _mimo_model(folder)
    _mimo_model(folder, "row.py", suffix="[0, :]")  # 1 output, 2 inputs
    (folder / "siso.py").write_text(MODEL)
    (folder / "one_by_two.py").write_text(
        MIMO_MODEL.format(suffix="").replace("plant = stage.plant",
                                             "plant = stage.plant[0, :]"))
    return folder


def _not_reached(*args, **kwargs):
    raise AssertionError("diagnose should not run")


@pytest.mark.parametrize("model, columns, counts, example", [
    # a 2x2 plant with the default (one) column each
    ("mimo.py", (), "`plant` has 2 outputs and 2 inputs, but --output-column 'y' "
     "and --input-column 'u' name 1 output column and 1 input column",
     "--output-column y1,y2 --input-column u1,u2"),
    # a SISO plant with two columns each
    ("siso.py", MIMO_COLUMNS, "`plant` has 1 output and 1 input, but "
     "--output-column 'y1,y2' and --input-column 'u1,u2' name 2 output columns "
     "and 2 input columns", "--output-column y1 --input-column u1"),
    # a 1x2 plant with two output columns
    ("one_by_two.py", MIMO_COLUMNS, "`plant` has 1 output and 2 inputs, but "
     "--output-column 'y1,y2' and --input-column 'u1,u2' name 2 output columns",
     "--output-column y1 --input-column u1,u2"),
])
def test_diagnose_columns_must_match_the_plant(mimo_files, capsys, monkeypatch,
                                               model, columns, counts, example):
    import lrmfrf.discrepancy

    monkeypatch.setattr(lrmfrf.discrepancy, "diagnose", _not_reached)
    status, out, err = _main(["diagnose", mimo_files / model, mimo_files / "d.npz",
                              "--F", "3", *columns, "--out", mimo_files / "o"],
                             capsys)
    assert status == 2 and out == ""
    assert counts in err and example in err and "in the plant's order" in err
    assert len(err.strip().splitlines()) == 1
    assert not (mimo_files / "o").exists()


def test_diagnose_controller_must_fit_the_plant(mimo_files, capsys, monkeypatch):
    """A 2x2 plant needs a controller with 2 outputs and 2 inputs; --open-loop
    ignores it."""
    import lrmfrf.discrepancy

    monkeypatch.setattr(lrmfrf.discrepancy, "diagnose", _not_reached)
    args = ["diagnose", mimo_files / "row.py", mimo_files / "d.npz", "--F", "3",
            *MIMO_COLUMNS, "--out", mimo_files / "c"]
    status, out, err = _main(args, capsys)
    assert status == 1 and out == ""
    assert ("`controller` has 1 output and 2 inputs, but with a plant of 2 outputs "
            "and 2 inputs it must have 2 outputs (the plant's inputs) and 2 inputs "
            "(the plant's outputs): u = r - C y") in err
    assert "--open-loop" in err and len(err.strip().splitlines()) == 1
    calls = []
    _stub(monkeypatch, "sample_time=None, rng=None", calls)
    status, _, err = _main([*args, "--open-loop", "--no-plot"], capsys)
    assert status == 0, err
    assert calls[0]["controller"] is None
    assert np.shape(calls[0]["u_h"]) == (2, 600)
    assert np.shape(calls[0]["y_l"]) == (2, 200)


def test_diagnose_column_lists_have_fits_syntax(mimo_files, capsys):
    """An empty name in a list is refused as by `lrmfrf fit`; the help says
    how to name several columns."""
    status, out, err = _main(["diagnose", mimo_files / "mimo.py",
                              mimo_files / "d.npz", "--F", "3", "--input-column",
                              "u1,,u2", "--output-column", "y1,y2", "--out",
                              mimo_files / "e"], capsys)
    assert status == 2 and out == ""
    assert "the column list 'u1,,u2' has an empty name" in err
    status, out, _ = _main(["diagnose", "--help"], capsys)
    assert status == 0
    assert "several comma separated (e.g. u1,u2)" in " ".join(out.split())


def _synthetic_report(shape):
    """A DiagnosisReport with made-up arrays of ``shape + (K,)`` (no fit)."""
    from lrmfrf.discrepancy.report import DiagnosisReport

    f = np.linspace(10.0, 900.0, 50)
    model = np.ones(shape + f.shape) / (1 + 1j * f / 100.0)
    return DiagnosisReport(
        findings=[], gap_before=2.0, gap_after=1.0, updated_plant=None, plant=None,
        frequencies=f, measured=1.1 * model, std=0.05 * np.abs(model),
        model_before=model, model_after=1.1 * model,
        spectrum_before=np.full(f.size, 3.0), spectrum_after=np.ones(f.size),
        threshold_before=2.0, threshold_after=2.0, p_value_before=1e-6,
        p_value_after=0.5, slow_nyquist=333.3, closed_loop=False)


def test_plot_grid_draws_every_entry_with_the_column_names():
    """The figure of a MIMO diagnosis.png: n_y x n_u magnitude and phase axes
    (here 1 output x 2 inputs) and one discrepancy axis; SISO gives 1 x 1."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    report = _synthetic_report((1, 2))
    fig, (mag, phase, disc) = report.plot_grid(output_labels=["y2"],
                                               input_labels=["u1", "u2"],
                                               units="m/N")
    try:
        assert mag.shape == phase.shape == (1, 2)
        assert [a.get_title() for a in mag[0]] == ["u1 → y2", "u2 → y2"]
        assert mag[0, 0].get_ylabel() == "|G| [dB re 1 m/N]"
        assert "mean over the 2 entries" in disc.get_title()
        assert "gap over all 2 entries: 2 before, 1 after" in fig._suptitle.get_text()
        # the updated model of entry (0, 1) is drawn in its own panel
        np.testing.assert_allclose(mag[0, 1].get_lines()[2].get_ydata(),
                                   20 * np.log10(np.abs(report.model_after[0, 1])))
    finally:
        plt.close(fig)
    with pytest.raises(ValueError, match="`input_labels` must have 2 names"):
        report.plot_grid(input_labels=["u1"])
    plt.close("all")
    fig, (mag, _, _) = _synthetic_report(()).plot_grid()
    assert mag.shape == (1, 1) and mag[0, 0].get_title() == "u0 → y0"
    plt.close(fig)


def test_summary_names_the_mimo_closed_loop():
    """The summary's ``compared:`` line gives the loop that was measured: the
    matrix ``P (I + C P)^-1`` for MIMO, ``P/(1+CP)`` for SISO."""
    import dataclasses

    mimo = dataclasses.replace(_synthetic_report((2, 2)), closed_loop=True)
    siso = dataclasses.replace(_synthetic_report(()), closed_loop=True)
    assert "compared: closed loop P (I + C P)^-1," in mimo.summary()
    assert "compared: closed loop P/(1+CP)," in siso.summary()
    assert "compared: open loop (plant)," in _synthetic_report((2, 2)).summary()


def test_diagnose_steady_state_flag(plain_data, capsys, monkeypatch):
    """--steady-state reaches diagnose(steady_state=True); without it the
    keyword is not passed (diagnose's default, a start from rest)."""
    calls = []
    _stub(monkeypatch, "rng=None, sample_time=None, steady_state=False", calls)
    for flag, out in ((["--steady-state"], "a"), ([], "b")):
        status, _, err = _main(["diagnose", plain_data / "model.py",
                                plain_data / "plain.npz", "--F", "3", *flag,
                                "--no-plot", "--out", plain_data / out], capsys)
        assert status == 0, err
    assert [c["steady_state"] for c in calls] == [True, False]


def test_per_channel_findings_name_the_data_column(mimo_files, capsys, monkeypatch):
    """The library calls input j ``u{j}`` (0-based); the data's columns are
    often 1-based (``u1,u2``), so "input u1 (actuator)" alone pointed at the
    wrong column (the figure's ``u1`` panel is input 0). diagnosis.txt and
    diagnosis.json now add the column after the description (stubbed
    diagnose: a finding on input 1)."""
    import dataclasses

    from lrmfrf.discrepancy.report import Finding

    finding = Finding(effect="input_gain", parameters={"input": 1, "gain": 1.2},
                      band=(10.0, 900.0), statistic=50.0, p_value=1e-9,
                      description="input u1 (actuator) gain is 1.2 times the "
                      "model's")
    sensor = dataclasses.replace(finding, effect="output_gain",
                                 parameters={"output": 0, "gain": 0.9},
                                 description="output y0 (sensor) gain is 0.9 "
                                 "times the model's")
    report = dataclasses.replace(_synthetic_report((2, 2)),
                                 findings=[finding, sensor])
    _stub(monkeypatch, "sample_time=None, rng=None", [], report=report)
    out = mimo_files / "columns"
    status, _, err = _main(["diagnose", mimo_files / "mimo.py", mimo_files / "d.npz",
                            "--F", "3", *MIMO_COLUMNS, "--open-loop", "--no-plot",
                            "--out", out], capsys)
    assert status == 0, err
    text = (out / "diagnosis.txt").read_text()
    assert ("1. input_gain: input u1 (actuator) gain is 1.2 times the model's "
            "(input 1 is data column 'u2')") in text
    assert ("2. output_gain: output y0 (sensor) gain is 0.9 times the model's "
            "(output 0 is data column 'y1')") in text
    saved = json.loads((out / "diagnosis.json").read_text())["findings"]
    assert saved[0]["description"].endswith("(input 1 is data column 'u2')")
    assert saved[0]["parameters"] == {"input": 1, "gain": 1.2}
    assert report.findings[0] is finding  # the report itself is not changed


@pytest.mark.parametrize("suffix, accepted", [("[:, 0]", True), ("[0, :]", False)])
def test_diagnose_controller_of_a_non_square_plant(mimo_files, capsys, monkeypatch,
                                                   suffix, accepted):
    """A plant of 1 output and 2 inputs needs a controller of 2 outputs and 1
    input (u = r - C y): the square 2x2 cases above cannot tell the check from
    its transpose, which accepted the 1 x 2 controller and refused the 2 x 1."""
    model = mimo_files / f"one_by_two_{'ok' if accepted else 'bad'}.py"
    model.write_text(MIMO_MODEL.format(suffix=suffix).replace(
        "plant = stage.plant", "plant = stage.plant[0, :]"))
    calls = []
    _stub(monkeypatch, "sample_time=None, rng=None", calls)
    out = mimo_files / f"nonsquare_{accepted}"
    status, _, err = _main(["diagnose", model, mimo_files / "d.npz", "--F", "3",
                            "--output-column", "y1", "--input-column", "u1,u2",
                            "--no-plot", "--out", out], capsys)
    if accepted:
        assert status == 0, err
        assert np.shape(calls[0]["u_h"]) == (2, 600)
        assert np.shape(calls[0]["y_l"])[-1] == 200
        assert calls[0]["controller"].ninputs == 1
    else:
        assert status == 1 and not calls
        assert ("`controller` has 1 output and 2 inputs, but with a plant of 1 "
                "output and 2 inputs it must have 2 outputs (the plant's inputs) "
                "and 1 input (the plant's outputs)") in err
