"""The simulated machine process on either engine (``slinger plant --engine drake``, ``slinger up
--engine drake``): the machine sim_twin.twin.plant runs behind the machine interface.

The Drake machine (sim_twin.twin.drake_machine) stands for a machine the twin was not built from, so
its states look like a real machine's: joint encoders and gripper IMU, the gripper state and the
impact, but no payload tracking (``MachineState.payload_pos_m`` / ``payload_vel_mps`` are None, as
from hardware without a tracker; the runtime's telemetry then has no ``/payload`` rows). The
MuJoCo machine keeps publishing its payload, as before.
"""

from __future__ import annotations

from collections.abc import Callable

from runtime.protocol.messages import MachineState
from sim_twin.twin.engines import check_engine, make_machine
from sim_twin.twin.profile import RealityProfile
from sim_twin.twin.twin_machine import TwinMachine


class UntrackedPayloadTwin(TwinMachine):
    """A TwinMachine whose states carry no payload tracking (a real machine's, without a tracker)."""

    def state(self) -> MachineState:
        """The current MachineState without ``payload_pos_m`` / ``payload_vel_mps``."""
        return super().state().model_copy(update={"payload_pos_m": None, "payload_vel_mps": None})


def plant_twin(engine: str, profile: RealityProfile, seed: int | None, machine_id: str,
               clock: Callable[[], float] | None = None) -> TwinMachine:
    """The plant's TwinMachine on ``engine`` ("mujoco" or "drake"), at a random collision-free
    pose with the cabin at 0; the Drake one without payload tracking (module doc).

    Raises:
        ValueError: unknown engine, or a profile the engine cannot apply.
        ImportError: engine "drake" without pydrake (install the ``drake`` extra).
    """
    sim = make_machine(check_engine(engine), profile, seed=seed)
    cls = UntrackedPayloadTwin if engine == "drake" else TwinMachine
    return cls(sim, machine_id, clock=clock)
