"""The simulated machine process ("plant"): sim_twin.simulated_machine behind the Zenoh machine
interface, standing in for the hardware bridge (runtime/protocol/README.md).

Real-time 100 Hz loop (absolute schedule, no drift): apply the latest ValveCommand (plant-side
watchdog: none for more than 0.1 s -> neutral valves) and GripperCommand, step the physics,
publish MachineState (simulated=True; q and qd include the passive joints, as the gripper IMU
gives them; payload position and velocity), publish one ImpactReport when the payload lands,
apply SimReset requests, and hold the liveliness token keys.machine_alive(id).

:class:`TwinMachine` is the bookkeeping between a SimulatedMachine and the wire messages (a
clock that keeps running across resets, the reset counter, the one-shot impact report). The
plant uses it with the wall clock; the twin's evaluation and preview loops use it with the
simulated clock to drive runtime.executor.ThrowExecutor directly.

Run: ``python -m sim_twin.plant --machine-id sim1 --connect tcp/127.0.0.1:7447``.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from typing import Callable

import numpy as np

from runtime.entrypoint import module_main, stop_on_signals
from runtime.observation import PHYSICS_PERIOD_S
from runtime.protocol import keys
from runtime.protocol.messages import (
    GripperCommand,
    ImpactReport,
    MachineState,
    SimReset,
    ValidationError,
    ValveCommand,
    decode,
    encode,
)
from runtime.zenoh_session import open_session
from sim_twin.initial_pose import sample_pose
from sim_twin.profile import RealityProfile
from sim_twin.simulated_machine import SimulatedMachine

log = logging.getLogger(__name__)

VALVE_WATCHDOG_S = 0.1
"""Plant-side watchdog: valves go neutral when no ValveCommand arrived for this long (s)."""


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
        self._clock = clock or self.sim_time_s
        self._impact_sent = False

    def sim_time_s(self) -> float:
        """Simulated seconds since construction, continuous across resets."""
        return self._time_offset_s + self.sim.time_s

    def state(self) -> MachineState:
        """The current MachineState (stamped with ``clock()``)."""
        pos, vel = self.sim.payload_state()
        return MachineState(
            machine_id=self.machine_id,
            stamp_s=self._clock(),
            q=self.sim.q.tolist(),
            qd=self.sim.qd.tolist(),
            gripper_open=self.sim.gripper_open,
            payload_attached=self.sim.payload_attached,
            payload_pos_m=np.asarray(pos, dtype=float).tolist(),
            payload_vel_mps=np.asarray(vel, dtype=float).tolist(),
            simulated=True,
            reset_count=self.reset_count,
        )

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
            q_active = sample_pose(rng, cabin_turn=float(self.sim.q[0]))[:4]
        self._time_offset_s += self.sim.time_s
        q = self.sim.reset(q_active=q_active)
        self.reset_count += 1
        self._impact_sent = False
        return q

    def step(self, valve_u, gripper_open: bool) -> ImpactReport | None:
        """Advance 10 ms; returns the ImpactReport the first time the payload is down."""
        self.sim.step(np.asarray(valve_u, dtype=float), bool(gripper_open))
        impact = self.sim.impact
        if impact is None or self._impact_sent:
            return None
        self._impact_sent = True
        now_sim, now = self.sim.time_s, self._clock()
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
    loop, the way evaluation and previews do: tick -> apply SimReset -> step -> impact.

    Args:
        twin: the simulated machine (simulated clock recommended).
        executor: an idle ThrowExecutor.
        request: messages.ThrowRequest.
        max_s: simulated-time budget; the throw is aborted if it is still running then.

    Returns:
        (outcome, events): the ThrowOutcome (None if the request was refused) and the list of
        PhaseEvents; if refused, events is the refusal reason (str).
    """
    refusal = executor.start(request, twin.state())
    if refusal is not None:
        return None, refusal
    events = []
    for _ in range(int(round(max_s / PHYSICS_PERIOD_S))):
        out = executor.tick(twin.state())
        events += out.events
        if out.finished is not None:
            return out.finished, events
        if out.sim_reset is not None:
            twin.apply_reset(out.sim_reset)
        report = twin.step(out.valve_u, out.gripper_open)
        if report is not None:
            out = executor.on_impact(report)
            events += out.events
            if out.finished is not None:
                return out.finished, events
    out = executor.abort(f"twin loop budget of {max_s:.0f} s exhausted")
    return out.finished, events + list(out.events)


class PlantInbox:
    """Latest commands from the runtime, written by Zenoh callback threads."""

    def __init__(self, machine_id: str):
        self.machine_id = machine_id
        self.lock = threading.Lock()
        self.valve_u = np.zeros(4)
        self.valve_rx_s = -np.inf
        self.gripper_open = False
        self.resets: list[SimReset] = []
        self.watchdog_tripped = False

    def _decode(self, cls, sample):
        try:
            msg = decode(cls, sample.payload.to_bytes())
        except ValidationError as e:
            log.warning("dropping malformed %s: %s", cls.__name__, e.errors()[0]["msg"] if e.errors() else e)
            return None
        if msg.machine_id != self.machine_id:
            log.warning("dropping %s for machine %r", cls.__name__, msg.machine_id)
            return None
        return msg

    def on_valve(self, sample) -> None:
        msg = self._decode(ValveCommand, sample)
        if msg is not None:
            with self.lock:
                self.valve_u, self.valve_rx_s = np.asarray(msg.u, dtype=float), time.monotonic()

    def on_gripper(self, sample) -> None:
        msg = self._decode(GripperCommand, sample)
        if msg is not None:
            with self.lock:
                self.gripper_open = msg.open

    def on_reset(self, sample) -> None:
        msg = self._decode(SimReset, sample)
        if msg is not None:
            with self.lock:
                self.resets.append(msg)


def build_parser(parser: argparse.ArgumentParser) -> None:
    """Add the plant's arguments to ``parser``."""
    parser.add_argument("--machine-id", required=True, help="machine id, [A-Za-z0-9_-]{1,64}")
    parser.add_argument("--profile", default=None, help="reality profile JSON (default: nominal machine)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the start pose and release-delay jitter")
    parser.add_argument("--connect", action="append", default=[], help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    parser.add_argument("--listen", action="append", default=[], help="Zenoh endpoint to listen on (repeatable)")
    parser.add_argument("--mode", default="peer", choices=("peer", "client"), help="Zenoh session mode")


def run(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """Run the plant until SIGINT/SIGTERM (or ``stop`` is set). Returns the exit code."""
    try:
        machine_id = keys.validate_machine_id(args.machine_id)
        profile = RealityProfile.load(args.profile) if args.profile else RealityProfile()
    except (ValueError, OSError) as e:
        log.error("cannot start plant: %s", e)
        return 2
    stop = stop_on_signals(stop)
    sim = SimulatedMachine(profile, seed=args.seed)  # random collision-free pose, cabin_turn 0
    twin = TwinMachine(sim, machine_id, clock=time.monotonic)
    inbox = PlantInbox(machine_id)
    with open_session(args.mode, listen=args.listen, connect=args.connect) as session:
        pub_state = session.declare_publisher(keys.state(machine_id))
        pub_impact = session.declare_publisher(keys.impact(machine_id))
        subs = [
            session.declare_subscriber(keys.valve_cmd(machine_id), inbox.on_valve),
            session.declare_subscriber(keys.gripper_cmd(machine_id), inbox.on_gripper),
            session.declare_subscriber(keys.sim_reset(machine_id), inbox.on_reset),
        ]
        token = session.liveliness().declare_token(keys.machine_alive(machine_id))
        log.info("plant %s up (profile %s)", machine_id, profile.name)
        try:
            _loop(twin, inbox, pub_state, pub_impact, stop)
        finally:
            token.undeclare()
            for sub in subs:
                sub.undeclare()
            pub_state.undeclare()
            pub_impact.undeclare()
    log.info("plant %s stopped", machine_id)
    return 0


def plant_tick(twin: TwinMachine, inbox: PlantInbox, now_s: float) -> tuple[MachineState, ImpactReport | None]:
    """One 10 ms plant period at local monotonic time ``now_s``: apply pending resets, the
    latest valve command (neutral if older than VALVE_WATCHDOG_S) and the gripper command, step.

    Returns:
        (the new MachineState, an ImpactReport the first time the payload is down, else None).
    """
    with inbox.lock:
        resets, inbox.resets = inbox.resets, []
        fresh = now_s - inbox.valve_rx_s <= VALVE_WATCHDOG_S
        u = inbox.valve_u.copy() if fresh else np.zeros(4)
        if resets:
            inbox.gripper_open = False  # a fresh payload sits in a closed gripper
        gripper = inbox.gripper_open
        if not fresh and not inbox.watchdog_tripped and np.isfinite(inbox.valve_rx_s):
            log.warning("no valve command for %.0f ms: valves neutral", VALVE_WATCHDOG_S * 1e3)
        inbox.watchdog_tripped = not fresh
    for r in resets:
        q = twin.apply_reset(r)
        log.info("sim reset %d: q_active %s", twin.reset_count, np.round(q[:4], 3).tolist())
    report = twin.step(u, gripper)
    return twin.state(), report


def _loop(twin: TwinMachine, inbox: PlantInbox, pub_state, pub_impact, stop: threading.Event) -> None:
    """Real-time 100 Hz schedule (absolute deadlines, so the period does not drift)."""
    next_s = time.monotonic()
    while not stop.is_set():
        state, report = plant_tick(twin, inbox, time.monotonic())
        pub_state.put(encode(state))
        if report is not None:
            pub_impact.put(encode(report))
            log.info("impact at %s", np.round(report.impact_pos_m, 2).tolist())
        next_s += PHYSICS_PERIOD_S
        delay = next_s - time.monotonic()
        if delay > 0:
            stop.wait(delay)
        elif delay < -0.1:
            log.warning("plant loop %.0f ms behind real time; resynchronising", -delay * 1e3)
            next_s = time.monotonic()


def main(argv: list[str] | None = None) -> int:
    return module_main('python -m sim_twin.plant', __doc__, build_parser, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
