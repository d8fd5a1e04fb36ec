"""numba's on-disk cache of kernels that call another file's kernels
(:mod:`lrmfrf._jit_cache`)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("numba")

from lrmfrf import _compiled, _compiled_refine, _compiled_uncertainty  # noqa: E402
from lrmfrf._jit_cache import key_caches_on, source_digest  # noqa: E402

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
    from lrmfrf._jit_cache import key_caches_on
    key_caches_on(globals(), [step_module.__file__])
"""

# imports, says so, and computes once a line arrives on stdin
WAITING = "import {module}; print('imported', flush=True); input(); " \
          "print({module}.kernel())"

ENV = {"PYTHONPATH": "{tmp}:" + str(ROOT), "PATH": "/usr/bin:/bin"}


def _env(tmp_path: Path) -> dict:
    return {key: value.format(tmp=tmp_path) for key, value in ENV.items()}


def _run(tmp_path: Path, module: str, compute: bool = True) -> int | None:
    code = f"import {module}" + (f"; print({module}.kernel())" if compute else "")
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
        env=_env(tmp_path), timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return int(done.stdout.split()[-1]) if compute else None


def _write_modules(tmp_path: Path) -> None:
    (tmp_path / "step_module.py").write_text(STEP.format(value=1))
    (tmp_path / "plain.py").write_text(KERNEL.format(guard=False))
    (tmp_path / "guarded.py").write_text(KERNEL.format(guard=True))


def test_a_changed_dependency_recompiles_the_guarded_kernel(tmp_path):
    """The kernel file is unchanged, the file of the step it inlines changes:
    the plain kernel keeps its cached old code, the guarded one does not."""
    _write_modules(tmp_path)
    assert _run(tmp_path, "plain") == 1
    assert _run(tmp_path, "guarded") == 1
    (tmp_path / "step_module.py").write_text(STEP.format(value=2))
    if _run(tmp_path, "plain") == 2:  # pragma: no cover
        pytest.skip("this numba tracks the files a cached kernel calls")
    assert _run(tmp_path, "guarded") == 2
    assert _run(tmp_path, "guarded") == 2  # and it is cached again


@pytest.mark.parametrize("new_process_computes", [False, True])
def test_processes_of_two_versions_never_share_machine_code(
        tmp_path, new_process_computes):
    """A process that imported the old step compiles after the step's file
    changed and a new process has seen the change: the old process computes
    with the code it imported (not the new one from the cache), and a later
    process with the new code (not the old one the old process cached).
    A digest checked and written at import (the first version of this guard)
    failed both: the new process emptied the index and the old one then
    cached its old code as if it were new."""
    _write_modules(tmp_path)
    assert _run(tmp_path, "guarded") == 1
    old = subprocess.Popen(
        [sys.executable, "-c", WAITING.format(module="guarded")], cwd=tmp_path,
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        env=_env(tmp_path), text=True,
    )
    try:
        assert old.stdout.readline().strip() == "imported", old.stderr.read()
        (tmp_path / "step_module.py").write_text(STEP.format(value=2))
        if new_process_computes:
            assert _run(tmp_path, "guarded") == 2
        else:
            _run(tmp_path, "guarded", compute=False)
        out, err = old.communicate("\n", timeout=120)
    finally:
        old.kill()
    assert old.returncode == 0, err
    assert int(out.split()[-1]) == 1  # the old process: the step it imported
    assert _run(tmp_path, "guarded") == 2  # a new one: the step on disk


def test_the_package_kernels_are_keyed_on_compiled_py():
    """Every cached kernel of the two modules that inline ``_compiled``'s
    steps carries the digest of ``_compiled.py`` in its cache stamp;
    ``_compiled``'s own kernels keep numba's stamp."""
    digest = source_digest([_compiled.__file__])
    for module in (_compiled_uncertainty, _compiled_refine):
        kernels = [v for v in vars(module).values()
                   if hasattr(getattr(v, "_cache", None), "_cache_file")]
        assert kernels, module.__name__
        for kernel in kernels:
            stamp = kernel._cache._cache_file._source_stamp
            assert stamp[0] == "lrmfrf-deps" and stamp[2] == digest, kernel
        # keyed once: a second call keeps the stamps
        before = [k._cache._cache_file._source_stamp for k in kernels]
        assert key_caches_on(vars(module), [__file__]) == len(kernels)
        assert [k._cache._cache_file._source_stamp for k in kernels] == before
    own = _compiled._solve_range._cache._cache_file._source_stamp
    assert own[0] != "lrmfrf-deps"


def test_nothing_cached_nothing_keyed():
    assert key_caches_on({"f": len, "__name__": __name__}, [__file__]) == 0
