"""Every ``slinger <command> --option`` the documentation shows is an option that command accepts.

Reads README.md, docs/*.md and policies/*.md (CHANGELOG.md is history: its commands may be
gone). For each ``slinger <command>`` on a line (``db``/``user`` with their subcommand), the
``--options`` up to the end of the command (a backtick, ``#``, ``&``, ``|``, ``;``, ``(`` or
"then") must be options of that command's parser or of one of its subcommands.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md"), *(ROOT / "policies").glob("*.md")])
END = re.compile(r"`|#|&|\||;|\(| then ")


def _options(parser: argparse.ArgumentParser) -> set[str]:
    """Option strings of ``parser`` and of all its subcommands (argparse has no public walk)."""
    out: set[str] = set()
    for action in parser._actions:  # noqa: SLF001 (argparse has no public walk of its options)
        out.update(action.option_strings)
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001 (as above)
            for sub in action.choices.values():
                out |= _options(sub)
    return out


def command_options() -> dict[str, set[str]]:
    """``slinger``'s commands and the options each accepts (delegated ones from their module)."""
    from server import cli

    top = cli.build_parser()
    delegated = cli.sub_commands()
    sub = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001 (as above)
    out: dict[str, set[str]] = {}
    for name, parser in sub.choices.items():
        if name in delegated:
            loader, why = cli.load_command(delegated[name])
            assert loader is not None, f"slinger {name}: {why}"
            module = loader()
            parser = argparse.ArgumentParser()
            module.build_parser(parser)
        out[name] = _options(parser) | {"-h", "--help"}
    return out


def documented() -> list[tuple[str, str, str]]:
    """(page, command, option) for every option shown after ``slinger <command>``."""
    from server import cli

    names = set(cli.sub_commands()) | {"up", "server", "db", "user"}
    rows = []
    for page in PAGES:
        for line in page.read_text().splitlines():
            for m in re.finditer(r"\bslinger ([a-z0-9-]+)", line):
                if m.group(1) not in names:
                    continue
                rest = END.split(line[m.end():], maxsplit=1)[0]
                rows += [(page.name, m.group(1), opt) for opt in re.findall(r"(?<!\S)(--[a-z0-9][a-z0-9-]*)", rest)]
    return rows


def test_the_docs_show_slinger_commands_with_options():
    rows = documented()
    assert len(rows) > 30 and {c for _, c, _ in rows} >= {"train", "evaluate", "diagnose", "runtime", "server", "results"}


def test_every_documented_option_is_accepted_by_its_command():
    pytest.importorskip("mujoco")
    known = command_options()
    wrong = sorted({f"{page}: slinger {cmd} {opt}" for page, cmd, opt in documented() if opt not in known[cmd]})
    assert wrong == [], "options the commands do not accept:\n" + "\n".join(wrong)
