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
