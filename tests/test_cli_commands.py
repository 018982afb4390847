"""``slinger``'s subcommands come from the packages that own them, through the entry-point group
``slinger.commands`` (server.cli.COMMANDS), not from module names in server/cli.py: the root
pyproject.toml and the three wheels' declare them, each wheel its own package's, and every one loads
a light function whose module the import-linter contracts see."""

from __future__ import annotations

import ast
import importlib
import tomllib
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

from server import cli

ROOT = Path(__file__).resolve().parents[1]
WHEELS = {"runtime": "runtime", "twin": "sim_twin", "server": "server"}
"""packaging/<wheel>/pyproject.toml: the package whose subcommands that wheel declares."""


def _declared(pyproject: Path) -> dict[str, str]:
    return tomllib.loads(pyproject.read_text())["project"]["entry-points"][cli.COMMANDS]


def test_each_wheel_declares_its_own_packages_subcommands_and_together_the_root_ones():
    root = _declared(ROOT / "pyproject.toml")
    union: dict[str, str] = {}
    for wheel, package in WHEELS.items():
        own = _declared(ROOT / "packaging" / wheel / "pyproject.toml")
        assert own and all(v.startswith(f"{package}.commands:") for v in own.values()), wheel
        assert not set(own) & set(union), f"{wheel} declares a subcommand another wheel declares"
        union |= own
    assert union == root


def test_every_installed_subcommand_loads_with_a_help_line():
    """The installed metadata (pip install -e .) matches pyproject.toml, and each entry point loads a
    function of its package's ``commands`` module without importing the command's module."""
    declared = _declared(ROOT / "pyproject.toml")
    found = cli.sub_commands()
    assert {n: ep.value for n, ep in found.items()} == declared, "stale metadata: pip install -e ."
    for name, ep in found.items():
        loader, help_line = cli.load_command(ep)
        assert loader is not None and help_line, name
        assert loader.__module__.endswith(".commands")
    built = cli.build_parser()
    sub = next(a for a in built._actions if hasattr(a, "choices") and a.choices)  # noqa: SLF001 (argparse has no public walk)
    assert set(declared) <= set(sub.choices)


def test_loaders_return_the_commands_modules():
    loaded = 0
    for name, ep in sorted(cli.sub_commands().items()):
        loader, _ = cli.load_command(ep)
        assert loader is not None
        try:
            module = loader()
        except ModuleNotFoundError as e:  # an extra this environment lacks (torch, rclpy), not a module of ours
            assert e.name and e.name.split(".")[0] not in ("runtime", "sim_twin", "server"), f"{name}: {e}"
            continue
        assert hasattr(module, "main") or (hasattr(module, "build_parser") and hasattr(module, "run")), name
        loaded += 1
    assert loaded >= 6  # the server's four and the twin's plant and evaluate need no extra


def test_cli_names_no_module_by_string():
    """server/cli.py neither imports importlib nor names another package's module in a string."""
    tree = ast.parse((ROOT / "server" / "cli.py").read_text())
    imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert "importlib" not in imported and "importlib.metadata" in imported
    strings = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)]
    assert not [s for s in strings if s.startswith(("sim_twin.", "runtime.", "server.")) and " " not in s]


def _needs_a_missing_package():
    """a command whose module needs a package that is not installed"""
    return importlib.import_module("slinger_no_such_package_anywhere")


def _names_a_module_that_is_gone():
    """a command whose module was moved without its entry point"""
    return importlib.import_module("tests.no_such_module")


def test_a_broken_or_unsatisfied_subcommand_fails_with_a_clear_message(capsys):
    gone = EntryPoint("gone", "sim_twin.commands:no_such_command", cli.COMMANDS)
    loader, why = cli.load_command(gone)
    assert loader is None and "does not load" in why and "reinstall" in why
    assert cli._delegate(gone, [], "gone") == 2  # noqa: SLF001 (the dispatcher itself)
    assert "'gone' is unavailable" in capsys.readouterr().err
    missing = EntryPoint("needs", f"{__name__}:_needs_a_missing_package", cli.COMMANDS)
    assert cli.load_command(missing)[1] == "a command whose module needs a package that is not installed"
    assert cli._delegate(missing, [], "needs") == 2  # noqa: SLF001 (as above)
    assert "needs the missing package 'slinger_no_such_package_anywhere'" in capsys.readouterr().err
    moved = EntryPoint("moved", f"{__name__}:_names_a_module_that_is_gone", cli.COMMANDS)
    assert cli._delegate(moved, [], "moved") == 2  # noqa: SLF001 (as above)
    assert "imports tests.no_such_module, which does not exist" in capsys.readouterr().err


def test_slinger_results_runs_through_its_entry_point(capsys):
    assert cli.main(["results", "--check"]) == 0
    with pytest.raises(SystemExit) as done:  # a module with build_parser/run: its parser, named after the subcommand
        cli.main(["certs", "--help"])
    assert done.value.code == 0 and "usage: slinger certs" in capsys.readouterr().out


def test_up_names_the_twins_engines_without_importing_sim_twin():
    """``slinger up --engine`` offers sim_twin's engines, named as strings in server/cli.py (a
    server-only install has no sim_twin), and refuses another name at parse time."""
    from sim_twin.twin.engines import ENGINES

    assert cli.ENGINES == ENGINES
    tree = ast.parse((ROOT / "server" / "cli.py").read_text())
    modules = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    modules |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert not [m for m in modules if m.split(".")[0] == "sim_twin"]
    assert cli.build_parser().parse_args(["up", "--engine", "drake"]).engine == "drake"
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["up", "--engine", "bullet"])
