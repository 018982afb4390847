"""The twin machine in process: a SimulatedMachine seen through the machine-interface messages,
and one throw of the runtime's executor driven on it in a plain loop.

:class:`TwinMachine` is the bookkeeping between a SimulatedMachine and the wire messages (a
clock that keeps running across resets, the reset counter, the one-shot impact report, the
operator stand-in that reloads a payload). The simulated machine process (sim_twin.twin.plant) uses
it with the wall clock behind Zenoh; evaluation, previews and the diagnosis datasets use it with
the simulated clock to drive runtime.executor.ThrowExecutor directly (:func:`run_throw`), with no
transport, so that they run where no Zenoh is installed.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from runtime.observation import PHYSICS_PERIOD_S
from runtime.protocol import keys
from runtime.protocol.messages import ImpactReport, MachineState, SimReset
from sim_twin.twin.initial_pose import sample_pose
from sim_twin.twin.simulated_machine import SimulatedMachine

log = logging.getLogger(__name__)

RELOAD_AFTER_LANDING_S = 1.0
"""Simulated seconds between the payload's landing and the next payload being loaded."""
RELOAD_UNLOADED_S = 8.0
"""Simulated seconds without a payload (no landing seen) before reloading anyway; longer than
the runtime's 6 s impact timeout so that a payload in flight is never taken away."""


class TwinMachine:
    """A SimulatedMachine seen through the machine-interface messages.

    Args:
        sim: the simulated machine.
        machine_id: id put into every message.
        clock: returns the stamp (s) of "now"; default: simulated time that keeps counting
            across resets (SimulatedMachine.reset sets its own time back to 0).
    """

    def __init__(self, sim: SimulatedMachine, machine_id: str, clock: Callable[[], float] | None = None):
        self.sim = sim
        self.machine_id = keys.validate_machine_id(machine_id)
        self.reset_count = 0
        self._time_offset_s = 0.0
        # None stands for sim_time_s: holding the bound method self.sim_time_s would be a reference
        # cycle, so every twin (and its MjData, ~13 MiB) would wait for the cyclic GC to be freed
        self._clock = clock
        self._impact_sent = False
        self._unloaded_since_s: float | None = None
        self.fault: str | None = None  # published as MachineState.machine_fault

    def sim_time_s(self) -> float:
        """Simulated seconds since construction, continuous across resets."""
        return self._time_offset_s + self.sim.time_s

    def now_s(self) -> float:
        """The stamp (s) of "now": ``clock()``, or :meth:`sim_time_s` without a clock."""
        return self._clock() if self._clock is not None else self.sim_time_s()

    def state(self) -> MachineState:
        """The current MachineState (stamped with ``clock()``)."""
        pos, vel = self.sim.payload_state()
        return MachineState(
            machine_id=self.machine_id,
            stamp_s=self.now_s(),
            q=self.sim.q.tolist(),
            qd=self.sim.qd.tolist(),
            gripper_open=self.sim.gripper_open,
            payload_attached=self.sim.payload_attached,
            payload_pos_m=np.asarray(pos, dtype=float).tolist(),
            payload_vel_mps=np.asarray(vel, dtype=float).tolist(),
            simulated=True,
            reset_count=self.reset_count,
            machine_fault=self.fault,
        )

    @property
    def loaded(self) -> bool:
        """A payload sits in the closed gripper."""
        return bool(self.sim.payload_attached and not self.sim.gripper_open)

    def reload_if_due(self, now_s: float | None = None) -> bool:
        """The operator stand-in: load a fresh payload (apply_reset) RELOAD_AFTER_LANDING_S
        after the payload landed, or RELOAD_UNLOADED_S after it was lost without a landing.

        Args:
            now_s: simulated seconds (default: sim_time_s()).

        Returns:
            True if it reloaded.
        """
        now = self.sim_time_s() if now_s is None else now_s
        if self.loaded:
            self._unloaded_since_s = None
            return False
        if self._unloaded_since_s is None:
            self._unloaded_since_s = now
        impact = self.sim.impact
        landed_ago = None if impact is None else self.sim.time_s - impact.impact_time_s
        if (landed_ago is not None and landed_ago >= RELOAD_AFTER_LANDING_S) or now - self._unloaded_since_s >= RELOAD_UNLOADED_S:
            q = self.apply_reset(SimReset(machine_id=self.machine_id, stamp_s=0.0))
            log.info("payload reloaded (%d): q_active %s", self.reset_count, np.round(q[:4], 3).tolist())
            return True
        return False

    def apply_reset(self, request: SimReset) -> np.ndarray:
        """Re-initialise: ``request.q_active`` or a random collision-free pose that keeps the
        current cabin angle (seeded by ``request.seed`` if given); fresh payload, gripper closed.

        Returns:
            (6,) the new joint positions.
        """
        if request.q_active is not None:
            q_active = np.asarray(request.q_active, dtype=float)
        else:
            rng = self.sim.rng if request.seed is None else np.random.default_rng(request.seed)
            q_active = sample_pose(rng, cabin_turn=float(self.sim.data.qpos[0]))[:4]
        self._time_offset_s += self.sim.time_s
        q = self.sim.reset(q_active=q_active)
        self.reset_count += 1
        self._impact_sent = False
        self._unloaded_since_s = None
        return q

    def step(self, valve_u, gripper_open: bool) -> ImpactReport | None:
        """Advance 10 ms; returns the ImpactReport the first time the payload is down."""
        self.sim.step(np.asarray(valve_u, dtype=float), bool(gripper_open))
        impact = self.sim.impact
        if impact is None or self._impact_sent:
            return None
        self._impact_sent = True
        now_sim, now = self.sim.time_s, self.now_s()
        return ImpactReport(
            machine_id=self.machine_id,
            stamp_s=now,
            impact_pos_m=impact.impact_pos_m.tolist(),
            opening_stamp_s=now - (now_sim - impact.opening_time_s),
            impact_stamp_s=now - (now_sim - impact.impact_time_s),
            release_pos_m=impact.release_pos_m.tolist(),
            release_vel_mps=impact.release_vel_mps.tolist(),
        )


def run_throw(twin: TwinMachine, executor, request, max_s: float = 30.0):
    """Drive one throw of ``executor`` (runtime.executor.ThrowExecutor) on ``twin`` in a plain
    loop, the way evaluation does: load a payload if the machine has none (the operator),
    then tick -> step -> impact.

    Args:
        twin: the simulated machine (simulated clock recommended).
        executor: an idle ThrowExecutor.
        request: messages.ThrowRequest.
        max_s: simulated-time budget; the throw is aborted if it is still running then.

    Returns:
        (outcome, events): the ThrowOutcome (None if the request was refused) and the list of
        PhaseEvents; if refused, events is the refusal reason (str).
    """
    if not twin.loaded:
        twin.apply_reset(SimReset(machine_id=twin.machine_id, stamp_s=0.0))
    refusal = executor.start(request, twin.state())
    if refusal is not None:
        return None, refusal
    events = []
    for _ in range(int(round(max_s / PHYSICS_PERIOD_S))):
        out = executor.tick(twin.state())
        events += out.events
        if out.finished is not None:
            return out.finished, events
        report = twin.step(out.valve_u, out.gripper_open)
        if report is not None:
            out = executor.on_impact(report)
            events += out.events
            if out.finished is not None:
                return out.finished, events
    out = executor.abort(f"twin loop budget of {max_s:.0f} s exhausted")
    return out.finished, events + list(out.events)
