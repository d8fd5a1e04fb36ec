"""`lrmfrf demo`: runs, writes its files, never overwrites a file it did not write."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from lrmfrf.demo import MANIFEST, run_demo

REPO = Path(__file__).resolve().parents[1]


def _cli(*args, cwd):
    env = dict(os.environ, PYTHONPATH=str(REPO), MPLBACKEND="Agg")
    return subprocess.run([sys.executable, "-m", "lrmfrf.cli", *args], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=120)


def test_run_demo_writes_table_and_files(tmp_path):
    result = run_demo(tmp_path / "out", seed=1)
    names = sorted(p.name for p in result.files)
    assert names == ["bode_G_y4.png", "bode_G_z.png", "frf_G_y4.csv", "frf_G_z.csv"]
    assert all(p.stat().st_size > 0 for p in result.files)
    assert (tmp_path / "out" / MANIFEST).exists()
    for system in ("G_y4", "G_z"):
        for method in ("LRM", "LPM", "SA"):
            assert f"| {system} | {method} |" in result.table
    header = (tmp_path / "out" / "frf_G_z.csv").read_text().splitlines()[0]
    assert header.startswith("frequency_hz,true_real,true_imag,lrm_real")
    # the demo shows what the paper shows: LRM has the lowest cumulative error
    for per_method in result.results.values():
        c = {m: s["cumulative_error_common"] for m, s in per_method.items()}
        assert c["LRM"] < c["LPM"] and c["LRM"] < c["SA"]


def test_rerun_replaces_only_its_own_files(tmp_path):
    run_demo(tmp_path, seed=1, plot=False)
    run_demo(tmp_path, seed=2, plot=False)  # own, unchanged files: replaced
    foreign = tmp_path / "frf_G_z.csv"
    foreign.write_text("a user's own file\n")
    with pytest.raises(FileExistsError, match="exists already"):
        run_demo(tmp_path, seed=3, plot=False)
    assert foreign.read_text() == "a user's own file\n"
    run_demo(tmp_path, seed=3, plot=False, overwrite=True)
    assert foreign.read_text() != "a user's own file\n"


def test_run_demo_bad_input(tmp_path):
    with pytest.raises(ValueError, match="snr_db must be a finite"):
        run_demo(tmp_path, snr_db=float("nan"))
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(ValueError, match="not a folder"):
        run_demo(afile)


def test_demo_command_line(tmp_path):
    done = _cli("demo", "--out", str(tmp_path / "d"), "--seed", "3", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "| G_z | LRM |" in done.stdout
    assert (tmp_path / "d" / "bode_G_z.png").exists()
    bad = _cli("demo", "--snr", "loud", cwd=tmp_path)
    assert bad.returncode != 0
    assert len(bad.stderr.strip().splitlines()) == 1
    assert "Traceback" not in bad.stderr


def test_refused_run_writes_nothing(tmp_path):
    """Every target is checked first: a foreign file stops the run before any
    file (or the manifest) is written."""
    foreign = tmp_path / "frf_G_z.csv"
    foreign.write_text("a user's own file\n")
    with pytest.raises(FileExistsError, match="not written by lrmfrf demo"):
        run_demo(tmp_path, seed=1, plot=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frf_G_z.csv"]
    assert foreign.read_text() == "a user's own file\n"


def test_changed_own_file_is_not_replaced(tmp_path):
    run_demo(tmp_path, seed=1, plot=False)
    edited = tmp_path / "frf_G_y4.csv"
    edited.write_text(edited.read_text() + "# my note\n")
    with pytest.raises(FileExistsError, match="or was changed since"):
        run_demo(tmp_path, seed=1, plot=False)
    assert edited.read_text().endswith("# my note\n")


def test_foreign_manifest_is_a_users_file(tmp_path):
    manifest = tmp_path / MANIFEST
    for content in ('{"frf_G_z.csv": "0"}', "not json"):
        manifest.write_text(content)
        with pytest.raises(FileExistsError, match="not written by lrmfrf demo"):
            run_demo(tmp_path, seed=1, plot=False)
        assert manifest.read_text() == content
    run_demo(tmp_path, seed=1, plot=False, overwrite=True)
    assert '"written_by": "lrmfrf demo"' in manifest.read_text()


def test_without_matplotlib_the_csvs_are_written_with_a_note(tmp_path, monkeypatch):
    # python-control (imported already) needs matplotlib today; the demo does
    # not, should control make it optional.
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    result = run_demo(tmp_path, seed=1)
    assert sorted(p.name for p in result.files) == ["frf_G_y4.csv", "frf_G_z.csv"]
    assert result.notes == [
        'Bode PNGs not drawn: matplotlib is missing (pip install "lrmfrf[plot]")'
    ]


@pytest.mark.parametrize("seed", [-1, 1.5, True])
def test_run_demo_rejects_bad_seed(tmp_path, seed):
    with pytest.raises(ValueError, match="seed must be an integer >= 0"):
        run_demo(tmp_path / "never", seed=seed)
    assert not (tmp_path / "never").exists()


def test_manifest_of_the_first_release_is_recognised(tmp_path):
    """lrmfrf 0.1 wrote the manifest as {name: sha256}: still the demo's own."""
    import json

    from lrmfrf.io import file_sha256

    run_demo(tmp_path, seed=1, plot=False)
    files = ["frf_G_y4.csv", "frf_G_z.csv"]
    legacy = {name: file_sha256(tmp_path / name) for name in files}
    (tmp_path / MANIFEST).write_text(json.dumps(legacy))
    run_demo(tmp_path, seed=2, plot=False)
    assert '"written_by": "lrmfrf demo"' in (tmp_path / MANIFEST).read_text()
