"""Every third-party module the code imports, also inside a function (a lazy import runs only
when its path is taken: the preview's ``scipy`` once failed every preview of a plain
``pip install -e .``), comes from a distribution the base install declares, transitively;
only the training extra's own packages (torch, jax, rsl_rl, ...) may be imported beyond it,
and only by the training and fine-tuning paths that need the extra anyway; likewise the ROS 2
extra's (rclpy) by the ROS 2 nodes (runtime/ros2/node.py).

The check does not need the training extra installed: a module that no installed distribution
provides is looked up in :data:`TRAIN_MODULES` (the training extra's import names), and its
distribution must be declared in that extra (packaging/requirements/train.txt).
"""

from __future__ import annotations

import ast
import importlib.metadata as md
import re
import sys
from pathlib import Path

from packaging.requirements import Requirement

from tests.test_packaging import closure, declared

REPO = Path(__file__).resolve().parent.parent
OURS = {"runtime", "server", "sim_twin", "migrations", "tests", "packaging"}
TRAIN_MODULES = {"torch": "torch", "jax": "jax", "rsl_rl": "rsl-rl-lib", "tensordict": "tensordict",
                 "onnxscript": "onnxscript", "tensorboard": "tensorboard"}
"""Import name -> distribution of the training extra's packages that the code imports, for a
check run without the extra (the fast tier's ``pip install -e .[test]``). Where the extra is
installed, :func:`test_the_training_modules_table_matches_the_installed_distributions` checks the table."""


def imported_modules(path: Path) -> set[str]:
    """Top-level names of the absolute imports anywhere in the file at ``path``."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _train_direct() -> set[str]:
    """Normalised names of the distributions the training extra declares."""
    return {_norm(Requirement(r).name) for r in declared("root", "train")}


def test_every_imported_distribution_is_declared():
    base = closure(declared("root"))
    train_direct = (_train_direct() | {_norm(Requirement(r).name) for r in declared("root", "drake")}  # the Drake engine's extra too
                    | {_norm(Requirement(r).name) for r in declared("root", "ros2")})  # and the ROS 2 extra's (rclpy)
    owners = md.packages_distributions()
    missing: dict[str, set[str]] = {}
    for pkg in ("runtime", "server", "sim_twin"):
        for path in sorted((REPO / pkg).rglob("*.py")):
            for mod in imported_modules(path) - OURS - set(sys.stdlib_module_names):
                dists = {_norm(d) for d in owners.get(mod, [])}
                if not dists and mod in TRAIN_MODULES:  # the training extra, not installed here
                    dists = {TRAIN_MODULES[mod]}
                assert dists, (f"{path.relative_to(REPO)} imports {mod!r}, which no installed distribution provides "
                               "and which is not one of the training extra's modules (TRAIN_MODULES)")
                if not dists & (base | train_direct):
                    missing.setdefault(mod, set()).add(str(path.relative_to(REPO)))
    assert not missing, f"imported but not declared in pyproject.toml's dependencies: {missing}"


def test_the_training_modules_table_matches_the_installed_distributions():
    """Each entry of TRAIN_MODULES names a distribution of the training extra, and the one that
    provides the module where it is installed."""
    train_direct = _train_direct()
    owners = md.packages_distributions()
    for mod, dist in TRAIN_MODULES.items():
        assert dist in train_direct, f"{dist} (module {mod!r}) is not in packaging/requirements/train.txt"
        if mod in owners:
            assert dist in {_norm(d) for d in owners[mod]}, f"{mod!r} is provided by {owners[mod]}, not {dist}"


def test_the_check_sees_lazy_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("import os\n\ndef f():\n    from scipy.stats import qmc\n    import numpy.linalg\n    from . import x\n")
    assert imported_modules(f) == {"os", "scipy", "numpy"}
