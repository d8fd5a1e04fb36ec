"""numba's on-disk cache of kernels that call another file's kernels
(:mod:`lrmfrf._jit_cache`)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("numba")

from lrmfrf import _compiled, _compiled_refine, _compiled_uncertainty  # noqa: E402
from lrmfrf._jit_cache import drop_stale_caches, source_digest  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

STEP = """
from numba import njit

@njit(cache=True)
def step():
    return {value}
"""

KERNEL = """
from numba import njit

import step_module

@njit(cache=True)
def kernel():
    return step_module.step() + 0

if {guard}:
    from lrmfrf._jit_cache import drop_stale_caches
    drop_stale_caches(globals(), __file__, [step_module.__file__])
"""


def _run(tmp_path: Path, module: str) -> int:
    code = f"import {module}; print({module}.kernel())"
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
        env={"PYTHONPATH": f"{tmp_path}:{ROOT}", "PATH": "/usr/bin:/bin"},
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return int(done.stdout.split()[-1])


def test_a_changed_dependency_recompiles_the_guarded_kernel(tmp_path):
    """The kernel file is unchanged, the file of the step it inlines changes:
    the plain kernel keeps its cached old code, the guarded one does not."""
    (tmp_path / "step_module.py").write_text(STEP.format(value=1))
    (tmp_path / "plain.py").write_text(KERNEL.format(guard=False))
    (tmp_path / "guarded.py").write_text(KERNEL.format(guard=True))
    assert _run(tmp_path, "plain") == 1
    assert _run(tmp_path, "guarded") == 1
    (tmp_path / "step_module.py").write_text(STEP.format(value=2))
    if _run(tmp_path, "plain") == 2:  # pragma: no cover
        pytest.skip("this numba tracks the files a cached kernel calls")
    assert _run(tmp_path, "guarded") == 2
    assert _run(tmp_path, "guarded") == 2  # and it is cached again


def test_the_package_kernels_record_their_dependency():
    """Importing the compiled modules left the digest of ``_compiled.py`` next
    to their caches; a second check finds nothing to drop."""
    for module in (_compiled_uncertainty, _compiled_refine):
        kernels = [v for v in vars(module).values()
                   if hasattr(getattr(v, "_cache", None), "cache_path")]
        assert kernels, module.__name__
        stem = Path(module.__file__).stem
        stamp = Path(kernels[0]._cache.cache_path) / f"{stem}.deps.sha256"
        if not stamp.is_file():  # pragma: no cover
            pytest.skip("read-only numba cache directory")
        assert stamp.read_text().strip() == source_digest([_compiled.__file__])
        assert not drop_stale_caches(vars(module), module.__file__,
                                     [_compiled.__file__])


def test_nothing_cached_nothing_dropped():
    assert not drop_stale_caches({"f": len}, __file__, [__file__])
