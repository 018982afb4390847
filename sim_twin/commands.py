"""The ``slinger`` sub-commands of the twin package: ``plant``, ``train``, ``evaluate``, ``diagnose``
and ``adapt``.

Each function here is registered in the entry-point group ``slinger.commands`` (``pyproject.toml``,
``packaging/twin/pyproject.toml``) under the sub-command's name; ``server.cli`` finds them there.
A function imports the command's module and returns it (the module has ``main(argv)``, or
``build_parser``/``run``); its docstring is the command's help line. Loading an entry point imports
only this light module, so ``slinger --help`` imports neither MuJoCo nor the training stack.
"""

from __future__ import annotations

from types import ModuleType


def plant() -> ModuleType:
    """the simulated machine"""
    import sim_twin.twin.plant as module

    return module


def train() -> ModuleType:
    """train a throwing policy (needs the 'train' extra)"""
    import sim_twin.training.train as module

    return module


def evaluate() -> ModuleType:
    """evaluate a policy version"""
    import sim_twin.evaluation.cli as module

    return module


def diagnose() -> ModuleType:
    """sim-to-real gap diagnosis of logged throws (and 'diagnose benchmark')"""
    import sim_twin.diagnosis.cli as module

    return module


def adapt() -> ModuleType:
    """a policy version adapted to a site's (fitted) reality profile"""
    import sim_twin.adaptation.adapt as module

    return module
