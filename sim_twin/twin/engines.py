"""The physics engines a simulated machine can run in: ``mujoco`` (the twin the policies were
trained on: sim_twin.twin.simulated_machine) and ``drake`` (an independent engine: sim_twin.twin.drake_machine,
needs the ``drake`` extra). Evaluation (``slinger evaluate --engine``), the simulated machine
process (``slinger plant --engine``, ``slinger up --engine``) and the Drake diagnosis datasets
pick the machine here."""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

if TYPE_CHECKING:  # imported where a machine is made: the command line reads ENGINES without MuJoCo
    from sim_twin.twin.profile import RealityProfile
    from sim_twin.twin.simulated_machine import SimulatedMachine

ENGINES = ("mujoco", "drake")
"""Engine names; ``mujoco`` is the default everywhere."""


def check_engine(engine: str) -> str:
    """``engine`` if it is known.

    Raises:
        ValueError: an unknown engine name (the message lists the known ones).
    """
    if engine not in ENGINES:
        raise ValueError(f"unknown physics engine {engine!r}: one of {', '.join(ENGINES)}")
    return engine


def make_machine(engine: str, profile: RealityProfile | None = None, seed: int | None = None) -> SimulatedMachine:
    """A simulated machine of ``engine`` under ``profile`` (default nominal), seeded by ``seed``.

    The Drake machine has the SimulatedMachine interface that sim_twin.twin.twin_machine and the
    plant use (duck-typed; returned under that type).

    Raises:
        ValueError: unknown engine, or a profile the engine cannot apply.
        ImportError: engine ``drake`` without pydrake installed.
    """
    from sim_twin.twin.simulated_machine import SimulatedMachine

    if check_engine(engine) == "mujoco":
        return SimulatedMachine(profile, seed=seed)
    from sim_twin.twin.drake_machine import DrakeMachine

    return cast(SimulatedMachine, DrakeMachine(profile, seed=seed))
