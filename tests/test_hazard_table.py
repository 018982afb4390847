"""The hazard table of docs/safety.md is checked against the tests: every row names at least one
pytest node id, and every id names a test that exists (its function, by parsing the file) and
that pytest collects (``pytest --collect-only -q`` on the named files; the second check starts a
Python process, so it is in the ``processes`` tier). A row without a test, or one whose test was
renamed or removed, fails the suite."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SAFETY = REPO / "docs" / "safety.md"
SECTION = "## Hazard analysis"
NODE_ID = re.compile(r"`(tests/[\w/]+\.py::[\w\[\]\-.]+)`")
COMPONENTS = ("browser", "server", "storage", "job workers", "Zenoh link", "router", "runtime",
              "plant / machine driver", "ROS 2 peers", "second server", "clocks", "disks")
"""Every component the analysis must cover (issue: browser, server, storage, job workers, Zenoh
link, router, runtime, plant or machine driver, ROS 2 peers, a second server, clocks, disks)."""


def hazard_rows(text: str) -> list[dict[str, str]]:
    """The rows of the hazard table in ``text`` (docs/safety.md): one dict per row keyed by the
    header's column names.

    Raises:
        ValueError: no hazard section, or a row with another number of cells than the header.
    """
    if SECTION not in text:
        raise ValueError(f"docs/safety.md has no section {SECTION!r}")
    lines = text.split(SECTION, 1)[1].splitlines()
    table = []
    for line in lines[1:]:
        if line.startswith("|"):
            table.append(line)
        elif table:
            break
    header = [c.strip() for c in table[0].strip("|").split("|")]
    rows = []
    for line in table[2:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) != len(header):
            raise ValueError(f"hazard row with {len(cells)} cells, the header has {len(header)}: {line[:80]}")
        rows.append(dict(zip(header, cells)))
    return rows


def _rows() -> list[dict[str, str]]:
    return hazard_rows(SAFETY.read_text())


def _ids(row: dict[str, str]) -> list[str]:
    return NODE_ID.findall(row["test"])


def test_every_row_names_a_test_and_every_component_has_rows():
    rows = _rows()
    assert len(rows) >= len(COMPONENTS)
    assert len({r["id"] for r in rows}) == len(rows), "hazard ids are unique"
    no_test = [r["id"] for r in rows if not _ids(r)]
    assert not no_test, f"hazard rows without a test: {no_test}"
    missing = [c for c in COMPONENTS if not any(r["component"] == c for r in rows)]
    assert not missing, f"components without a hazard row: {missing}"


def test_every_named_test_function_exists():
    """Fast check by parsing the files: the file and a test function of that name exist."""
    absent = []
    for row in _rows():
        for node in _ids(row):
            path, name = node.split("::", 1)
            name = name.split("[", 1)[0]
            file = REPO / path
            if not file.is_file():
                absent.append(f"{row['id']}: {node} (no file)")
                continue
            tree = ast.parse(file.read_text())
            names = {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
            if name not in names:
                absent.append(f"{row['id']}: {node}")
    assert not absent, "hazard rows name tests that do not exist:\n" + "\n".join(absent)


def test_pytest_collects_every_named_test():
    """The ids as pytest sees them (a test skipped at collection, misnamed or parametrised away
    fails here)."""
    ids = sorted({node for row in _rows() for node in _ids(row)})
    files = sorted({node.split("::", 1)[0] for node in ids})
    p = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", *files],
                       capture_output=True, text=True, cwd=REPO, timeout=600)
    collected = {line.strip() for line in p.stdout.splitlines() if "::" in line}
    uncollected = [node for node in ids
                   if node not in collected and not any(c.startswith(node + "[") for c in collected)]
    assert not uncollected, f"not collected by pytest (exit {p.returncode}):\n" + "\n".join(uncollected) + \
        "\n" + p.stdout[-2000:] + p.stderr[-2000:]


@pytest.mark.parametrize("text, error", [
    ("# no table here", "no section"),
    (f"{SECTION}\n\n| id | test |\n|---|---|\n| A1 | x | y |\n", "3 cells"),
])
def test_a_malformed_table_is_refused_with_the_reason(text, error):
    with pytest.raises(ValueError, match=error):
        hazard_rows(text)
