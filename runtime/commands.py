"""The ``slinger`` sub-commands of the runtime package: ``slinger runtime`` and ``slinger ros2-bridge``.

Each function here is registered in the entry-point group ``slinger.commands`` (``pyproject.toml``,
``packaging/runtime/pyproject.toml``) under the sub-command's name; ``server.cli`` finds them there.
A function imports the command's module and returns it (the module has ``main(argv)``, or
``build_parser``/``run``); its docstring is the command's help line. Loading an entry point imports
only this light module, so ``slinger --help`` imports none of the commands' dependencies.
"""

from __future__ import annotations

from types import ModuleType


def runtime() -> ModuleType:
    """the runtime of one machine"""
    import runtime.node as module

    return module


def ros2_bridge() -> ModuleType:
    """the ROS 2 machine bridge: a machine whose driver is a ROS 2 node, behind the machine interface"""
    import runtime.ros2.bridge as module

    return module
