"""Which commit made a result: the one place that asks git (model cards, reports, benchmarks); and
the JSON layout of reports that carry per-throw lists (:func:`compact_json`).

Outside a git checkout (a copy of the tree on a lent GPU machine) the commit comes from the
environment variable ``SLINGER_GIT_COMMIT`` where the caller allows it.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def head_commit(repo: Path | None = None) -> tuple[str, bool] | None:
    """``(full hash of HEAD, whether tracked files differ from it)`` of the git repository at
    ``repo`` (default: this repository), or None where git or the repository is missing. Callers
    format the answer."""
    cwd = str(repo or REPO)
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=cwd, capture_output=True,
                               text=True, timeout=30, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head, bool(dirty)


def git_commit(repo: Path | None = None) -> str:
    """The repository's HEAD commit (with ``-dirty`` when the tree has changes); in a copy of the
    tree without git (a lent GPU machine) the commit named by the environment variable
    ``SLINGER_GIT_COMMIT``; else "unknown"."""
    state = head_commit(repo)
    if state is None:
        return os.environ.get("SLINGER_GIT_COMMIT", "").strip() or "unknown"
    return state[0] + ("-dirty" if state[1] else "")


def short_commit(repo: Path | None = None) -> str | None:
    """The first 7 hex digits of HEAD, or None outside a git checkout."""
    state = head_commit(repo)
    return state[0][:7] if state else None


_PLAIN_LIST = re.compile(r"\[\n\s*([^\[\]{}]*?)\n\s*\]")
_ONE_LINE_LIST = re.compile(r"\[[^\[\]{}\n]*,[^\[\]{}\n]*\]")


def compact_json(obj: object, indent: int = 1) -> str:
    """JSON of ``obj``, indented by ``indent``, with every list of plain values (per-throw data) on
    one line: about a third of the size of fully indented JSON. Only the line breaks and indents that
    ``json.dumps`` put between items go (a JSON string holds no raw line break), so the data read
    back are the same."""
    return _PLAIN_LIST.sub(lambda m: "[" + re.sub(r",\n\s*", ", ", m.group(1)) + "]", json.dumps(obj, indent=indent))


def has_one_line_lists(text: str) -> bool:
    """Whether indented JSON ``text`` keeps lists of several plain values on one line (as
    :func:`compact_json` writes them), so that a rewrite should too."""
    return "\n" in text.strip() and _ONE_LINE_LIST.search(text) is not None
