"""The README's Python example runs as written."""

from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs():
    text = README.read_text()
    blocks = [b.split("```")[0] for b in text.split("```python")[1:]]
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    assert namespace["lrm"].valid_.all()


def test_readme_mimo_example_runs():
    """The MIMO example: a 2 x 2 fit of the MIMO stage, accurate on the diagonal."""
    import numpy as np

    text = README.read_text()
    blocks = [b.split("```")[0] for b in text.split("```python")[1:]]
    mimo = [b for b in blocks if "mimo_wafer_stage" in b]
    assert len(mimo) == 1, "README has one MIMO example"
    namespace: dict = {}
    exec(compile(mimo[0], "README.md", "exec"), namespace)
    lrm = namespace["lrm"]
    assert lrm.frf_.shape == (2, 2, 1801) and lrm.frf_cov_.shape == (2, 2, 2, 1801)
    # 60 dB: the diagonal entries' median relative error is a few percent
    median = np.nanmedian(namespace["error"], axis=-1)
    assert np.all(np.diag(median) < 0.05), median
