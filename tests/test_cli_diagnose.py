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
