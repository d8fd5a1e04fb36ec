"""docs/method.md points at tests: every test it names must exist."""

from __future__ import annotations

import ast
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _test_names(path: pathlib.Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return {node.name for node in ast.walk(tree)
            if isinstance(node, ast.FunctionDef) and node.name.startswith("test_")}


def test_every_test_cited_in_method_md_exists():
    text = (ROOT / "docs" / "method.md").read_text(encoding="utf-8")
    cited = re.findall(r"(test_\w+\.py)::(test_\w+)", text)
    assert len(cited) >= 30  # the page cites a test for each claim
    missing = [f"{module}::{name}" for module, name in cited
               if name not in _test_names(ROOT / "tests" / module)]
    assert not missing, f"docs/method.md cites tests that do not exist: {missing}"
