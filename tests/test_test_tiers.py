"""The fast tier's marking (tests/conftest.py): every listed node id names a test that exists, and
the process check recognises the Python processes it is meant to catch."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

from tests.conftest import SLOW_TESTS, SYSTEM_MARKERS, _python_argv

REPO = Path(__file__).resolve().parents[1]


def _test_names(path: Path) -> set[str]:
    return {n.name for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.FunctionDef)}


@pytest.mark.parametrize("prefix", sorted(SLOW_TESTS))
def test_every_listed_test_exists(prefix):
    file, _, rest = prefix.partition("::")
    assert (REPO / file).is_file(), f"{file} does not exist"
    assert SLOW_TESTS[prefix] in SYSTEM_MARKERS
    if rest:
        name = rest.split("[")[0]
        assert any(t.startswith(name) for t in _test_names(REPO / file)), f"no test {name!r} in {file}"


def test_python_processes_are_recognised():
    assert _python_argv([sys.executable, "-m", "server.cli", "worker"])
    assert _python_argv(["/usr/bin/python3", "-c", "pass"]) and _python_argv("slinger")
    assert not _python_argv(["git", "ls-files", "-z"]) and not _python_argv(["sqlite3", "db"]) and not _python_argv([])
