"""Progress bars on long library work: off by default, on with verbose=True."""

import numpy as np
import pytest

from lrmfrf import LRMBeyondNyquist, LRMBeyondNyquistCV, multisine

pytest.importorskip("tqdm")


@pytest.fixture(scope="module")
def record():
    rng = np.random.default_rng(0)
    u = multisine(600, rng=rng)
    y = np.convolve(u, [0.3, 0.2, 0.1])[:600][::3] + 1e-3 * rng.standard_normal(200)
    return u, y


def test_cv_progress_bar(record, capsys):
    u, y = record
    grid = {"half_windows": (8, 10), "num_degrees": (1,), "den_degrees": (2,)}
    LRMBeyondNyquistCV(**grid).fit(u, y, 3)
    assert "candidates" not in capsys.readouterr().err
    LRMBeyondNyquistCV(**grid, verbose=True).fit(u, y, 3)
    assert "candidates" in capsys.readouterr().err


def test_refinement_progress_bar(record, capsys):
    u, y = record
    kwargs = {"half_window": 10, "num_degree": 1, "transient_degree": 1,
              "den_degree": 2, "sk_iterations": 2}
    LRMBeyondNyquist(**kwargs).fit(u, y, 3)
    assert "refinement" not in capsys.readouterr().err
    LRMBeyondNyquist(**kwargs, verbose=True).fit(u, y, 3)
    assert "refinement" in capsys.readouterr().err
