"""No tracked file narrates development history by numbered work periods.

Product files (code, configs, manifests, reports, docs) speak of versions and dates; history goes to
CHANGELOG.md, keyed by version and date. This test greps every file ``git ls-files`` lists for
numbered work periods, numbered turns and versions named by a bare suffix letter (the patterns in
:data:`PATTERNS`, with examples below), and fails naming file and line. Zenoh and log-in sessions
("session.get", "the same session") are not matched. The patterns and examples are assembled from
pieces so that this file passes its own check.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Built from pieces so that this file does not match itself.
_S = "sess" + "ion"
PATTERNS = [
    rf"\b{_S}s? \d",  # a numbered work period, or a range of them
    rf"\b{_S}-\d",  # the same, hyphenated
    rf"(?<!-)\b(in|this|previous|earlier|next|last|that) {_S}s?\b(?![.(_:\[])",  # "in this ..." (not "in session.get")
    r"\bturns? \d+\b",  # numbered turns
    r"\bwork periods? \d",
    r"(?<![\w/-])-[a-i] polic(y|ies)\b",  # a version by its bare suffix letter: name versions in full
]
HISTORY = re.compile("|".join(f"(?:{p})" for p in PATTERNS), re.IGNORECASE)

# Third-party files kept byte for byte as published.
SKIP_SUFFIXES = (".min.js",)
SKIP_PREFIXES = ("web/vendor/", "tests/vendor/")


def tracked_text_files() -> list[Path]:
    """Tracked files that decode as UTF-8 text (binary files are skipped)."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:  # not a git checkout (e.g. an sdist)
        pytest.skip(f"git ls-files unavailable: {e}")
    files = []
    for name in out.decode().split("\0"):
        if not name or name.endswith(SKIP_SUFFIXES) or name.startswith(SKIP_PREFIXES):
            continue
        path = ROOT / name
        if path.is_file():
            files.append(path)
    return files


def history_lines(path: Path) -> list[str]:
    """``"file:line: text"`` for every line of ``path`` that matches :data:`HISTORY`."""
    raw = path.read_bytes()
    if b"\0" in raw[:8192]:
        return []
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        return []
    rel = path.relative_to(ROOT)
    return [f"{rel}:{i}: {line.strip()[:160]}" for i, line in enumerate(text.splitlines(), 1) if HISTORY.search(line)]


@pytest.mark.parametrize(
    "line",
    [
        f"as measured in {_S} 4",
        f"{_S.capitalize()}s 2-3 trained it",
        f"the {_S}-4 GPU call",
        f"re-run in this {_S}",
        "in tu" + "rn 7 we",
        "measured with the -e" + " policies",
    ],
)
def test_the_pattern_catches_history_wording(line):
    assert HISTORY.search(line)


@pytest.mark.parametrize(
    "line",
    [
        "for reply in session.get(key):",
        "LiveHub listens on Zenoh (same session)",
        "for s in sessions:",
        "return 0",
        "cabin_turn 0: the arm's plane",
        "throw2d-robust-i, 2026-11-22",
        "expiring session tokens",
        "Zenoh and log-in sessions are not matched",
    ],
)
def test_the_pattern_spares_ordinary_wording(line):
    assert not HISTORY.search(line)


def test_no_tracked_file_names_numbered_work_periods():
    hits = [h for path in tracked_text_files() for h in history_lines(path)]
    assert not hits, "development-history wording (use versions and dates; history goes to CHANGELOG.md):\n" + "\n".join(hits[:50])
