"""The table of what holds on which transport is one table: the same in the README and in docs/safety.md,
and every test a cell names exists, so no cell can claim a test that is not there."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from .conftest import REPO

HEADER = "| promise | serial path"


def _table(path: Path) -> list[str]:
    lines = path.read_text(encoding="utf-8").splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(HEADER))
    end = next(i for i in range(start, len(lines)) if not lines[i].startswith("|"))
    return lines[start:end]


def _tests_in(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return {n.name for n in tree.body if isinstance(n, ast.FunctionDef) and n.name.startswith("test_")}


def test_the_transport_table_is_the_same_in_the_readme_and_the_safety_guide() -> None:
    assert _table(REPO / "README.md") == _table(REPO / "docs" / "safety.md")


def test_every_test_the_transport_table_names_exists() -> None:
    rows = _table(REPO / "docs" / "safety.md")[2:]
    named = re.findall(r"`(test_[a-z0-9_]+\.py)(?:::(test_[a-z0-9_]+))?`", "\n".join(rows))
    assert len(named) >= 20
    for module, test in named:
        path = REPO / "tests" / module
        assert path.exists(), module
        if test:
            assert test in _tests_in(path), f"{module}::{test}"
    assert all(len(r.split("|")) == 8 for r in rows), "every row has its five transports"
