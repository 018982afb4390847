"""The simulated machine process ("plant"): sim_twin.twin.simulated_machine behind the Zenoh machine
interface, standing in for the hardware bridge (runtime/protocol/README.md).

Real-time 100 Hz loop (absolute schedule, no drift): apply the latest ValveCommand (plant-side
watchdog: none for more than 0.1 s -> neutral valves) and GripperCommand, step the physics,
publish MachineState (simulated=True; q and qd include the passive joints, as the gripper IMU
gives them; payload position and velocity), publish one ImpactReport when the payload lands,
apply SimReset requests (tools and tests; the runtime never sends one), and hold the liveliness
token keys.machine_alive(id).

What only the simulated machine does stays here, behind the machine interface:

* reloading (sim_twin.twin.twin_machine.TwinMachine.reload_if_due, called every period of the loop):
  RELOAD_AFTER_LANDING_S after its payload landed (or RELOAD_UNLOADED_S after it was lost
  without a landing) the plant loads a fresh payload at a random collision-free pose
  keeping the cabin angle, gripper closed, at rest. This stands for the operator picking up
  the next object; the machine then waits loaded, so a preview from its current state
  predicts the next throw. A loaded machine that comes to rest where no throw can start (a
  joint at its end, the gripper at the ground, e.g. after a failed throw or an E-STOP) stays
  there, as a real machine would: the operator's recovery action, the runtime's "return to the
  ready pose" (runtime.recovery), drives it back.
* one machine, one plant (runtime.zenoh_session.claim_exclusive): at start it declares a claim
  token keys.machine_claim(id, claim) and listens 1.5 s; if another plant holds
  keys.machine_alive(id) or claimed earlier (two started at once), it exits with code 3
  ("machine m1 already has a plant").
* one driver: it follows only the newest ValveCommand epoch it has seen (a runtime's claim
  epoch); commands of an older epoch are dropped and logged once per epoch.
* the valve watchdog is final: when it puts moving valves neutral (no fresh ValveCommand for
  VALVE_WATCHDOG_S) it counts a trip (MachineState.watchdog_trips: the runtime fails the running
  throw) and disarms: valve commands are held neutral until a neutral one arrives (the runtime
  sends neutral once its throw has ended). A non-neutral command whose stamp (the stamp of the
  machine state it answers, this plant's monotonic clock) is older than
  runtime.protocol.messages.STALE_COMMAND_S was
  queued somewhere (a stalled runtime) and is dropped; so is such a gripper open command.
* real time: when a period starts more than 100 ms late (sim_twin.twin.realtime.BEHIND_FAULT_S), the
  plant publishes ``machine_fault`` "behind real time by N ms" and holds the valves neutral
  until it has kept real time for 1 s (RECOVER_S, RealTimeGuard); the runtime refuses throws
  with that reason and fails a running one.

The bookkeeping between the SimulatedMachine and the wire messages, and the reloading, are
sim_twin.twin.twin_machine.TwinMachine's (used here with the wall clock); evaluation and previews
use it directly, without this process or Zenoh.

Run: ``python -m sim_twin.twin.plant --machine-id sim1 --connect tcp/127.0.0.1:7447``.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from pathlib import Path

import numpy as np

from runtime.entrypoint import module_main, stop_on_signals
from runtime.epoch_fence import EpochFence, WatchdogLatch, decode_for
from runtime.observation import PHYSICS_PERIOD_S
from runtime.protocol import keys
from runtime.protocol.messages import (
    GripperCommand,
    ImpactReport,
    MachineState,
    SimReset,
    ValveCommand,
    encode,
    stale_motion,
)
from runtime.zenoh_session import Claimed, add_session_arguments, claim_exclusive, open_session, session_options
from sim_twin.twin.drake_plant import plant_twin
from sim_twin.twin.engines import ENGINES
from sim_twin.twin.profile import RealityProfile
from sim_twin.twin.realtime import RealTimeGuard
from sim_twin.twin.twin_machine import TwinMachine

log = logging.getLogger(__name__)

VALVE_WATCHDOG_S = 0.1
"""Plant-side watchdog: valves go neutral when no ValveCommand arrived for this long (s)."""

EXIT_ALREADY_CLAIMED = 3


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
        self.latch = WatchdogLatch()
        """The watchdog's trips (published as MachineState.watchdog_trips) and, after one, neutral
        valves until a neutral ValveCommand arrives."""
        self.stale_commands = 0
        """Non-neutral ValveCommands dropped because their stamp was older than VALVE_WATCHDOG_S."""
        self.still_ticks = 0
        """Consecutive periods with neutral valves, no reset, the same gripper command and every
        joint slower than REST_QD_RADPS (plant loop state; see plant_tick)."""
        self.last_gripper = False
        self.rest_state: MachineState | None = None
        self.resting = False
        self.fence = EpochFence()  # follows the newest ValveCommand epoch seen
        self.wake = threading.Event()
        """Set by a command that may end a rest (non-neutral valves, a gripper change, a reset):
        a resting loop sleeps between its 20 Hz publications and wakes on it (see _loop)."""

    @property
    def epoch(self) -> int | None:
        """The newest ValveCommand epoch seen (None before the first with one)."""
        return self.fence.epoch

    def _decode(self, cls, sample):
        return decode_for(cls, sample.payload.to_bytes(), self.machine_id)

    def on_valve(self, sample) -> None:
        """Follow only the newest epoch: a newer one takes over (logged), older ones (and
        epoch-less commands once an epoch was seen) are dropped, logged once per epoch."""
        msg = self._decode(ValveCommand, sample)
        if msg is None:
            return
        u, now = np.asarray(msg.u, dtype=float), time.monotonic()
        with self.lock:
            if not self.fence.admit(msg):
                return
            if stale_motion(msg, now):
                self.stale_commands += 1
                if self.stale_commands == 1 or self.latch.armed:
                    log.warning("dropping a valve command %.0f ms old (queued at a stalled runtime)", (now - msg.stamp_s) * 1e3)
                return
            if not self.latch.admit(u):
                u = np.zeros(4)  # disarmed by the watchdog: neutral until the runtime sends neutral
            self.valve_u, self.valve_rx_s = u, now
        if self.valve_u.any():
            self.wake.set()  # (always: the loop may be deciding to rest right now)

    def on_gripper(self, sample) -> None:
        """The gripper command; an open (release) command answering a state older than
        runtime.protocol.messages.STALE_COMMAND_S is dropped (queued at a stalled runtime: a late release)."""
        msg = self._decode(GripperCommand, sample)
        if msg is not None and stale_motion(msg, time.monotonic()):
            log.warning("dropping a gripper open command %.0f ms old (queued at a stalled runtime)",
                        (time.monotonic() - msg.stamp_s) * 1e3)
            return
        if msg is not None:
            with self.lock:
                changed, self.gripper_open = msg.open != self.gripper_open, msg.open
            if changed:
                self.wake.set()

    def on_reset(self, sample) -> None:
        msg = self._decode(SimReset, sample)
        if msg is not None:
            with self.lock:
                self.resets.append(msg)
            self.wake.set()


def build_parser(parser: argparse.ArgumentParser) -> None:
    """Add the plant's arguments to ``parser``."""
    parser.add_argument("--machine-id", required=True, help="machine id, [A-Za-z0-9_-]{1,64}")
    parser.add_argument("--profile", default=None, help="reality profile JSON (default: nominal machine)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the start pose and release-delay jitter")
    parser.add_argument("--engine", choices=ENGINES, default="mujoco",
                        help="physics engine: mujoco (the twin) or drake (an independent engine, sim_twin.twin.drake_machine; "
                             "its states carry no payload tracking, like a real machine's)")
    parser.add_argument("--ros2", nargs="?", const="", default=None, metavar="CONFIG",
                        help="be a ROS 2 driver node (rclpy; middleware by RMW_IMPLEMENTATION) with the ROS 2 bridge's mapping "
                             "file (default: identity mapping); the runtime then reaches this plant through `slinger ros2-bridge` "
                             "(sim_twin.twin.ros2_plant)")
    parser.add_argument("--domain-id", type=int, default=None,
                        help="with --ros2: ROS_DOMAIN_ID (default: the mapping's, else the environment's ROS_DOMAIN_ID, else 0)")
    add_session_arguments(parser)


def run(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """Run the plant until SIGINT/SIGTERM (or ``stop`` is set). Returns the exit code."""
    try:
        machine_id = keys.validate_machine_id(args.machine_id)
        profile = RealityProfile.load(args.profile) if args.profile else RealityProfile()
        zenoh_opts = session_options(args, f"plant-{machine_id}", [machine_id])
    except (ValueError, OSError) as e:
        log.error("cannot start plant: %s", e)
        return 2
    try:  # random collision-free pose, cabin_turn 0, on the chosen physics engine (sim_twin.twin.drake_plant)
        twin = plant_twin(getattr(args, "engine", "mujoco"), profile, args.seed, machine_id, clock=time.monotonic)
    except (ValueError, ImportError) as e:
        log.error("cannot start plant: %s", e)
        return 2
    stop = stop_on_signals(stop)
    inbox = PlantInbox(machine_id)
    if getattr(args, "ros2", None) is not None:
        return _run_ros2(args, machine_id, zenoh_opts, twin, inbox, stop)
    with open_session(**zenoh_opts) as session:
        try:
            token, claim_token = claim_exclusive(session, keys.machine_alive(machine_id),
                                                 lambda c: keys.machine_claim(machine_id, c))
        except Claimed as e:
            log.error("machine %s already has a plant (%s): not starting a second one", machine_id, e)
            return EXIT_ALREADY_CLAIMED
        pub_state = session.declare_publisher(keys.state(machine_id))
        pub_impact = session.declare_publisher(keys.impact(machine_id))
        subs = [
            session.declare_subscriber(keys.valve_cmd(machine_id), inbox.on_valve),
            session.declare_subscriber(keys.gripper_cmd(machine_id), inbox.on_gripper),
            session.declare_subscriber(keys.sim_reset(machine_id), inbox.on_reset),
        ]
        log.info("plant %s up (profile %s)", machine_id, profile.name)
        try:
            _loop(twin, inbox, pub_state, pub_impact, stop)
        finally:
            token.undeclare()
            claim_token.undeclare()
            for sub in subs:
                sub.undeclare()
            pub_state.undeclare()
            pub_impact.undeclare()
    log.info("plant %s stopped", machine_id)
    return 0


def _run_ros2(args, machine_id: str, zenoh_opts: dict, twin: TwinMachine, inbox: PlantInbox, stop: threading.Event) -> int:
    """The plant loop behind ROS 2 topics (sim_twin.twin.ros2_plant) instead of the machine interface."""
    from runtime.ros2.bridge import load_config
    from runtime.ros2.config import ConfigError
    from runtime.ros2.node import DomainRefused, RosUnavailable
    from sim_twin.twin.ros2_plant import RosPlantPorts

    try:
        config = load_config(Path(args.ros2) if args.ros2 else None, getattr(args, "domain_id", None))
        ports = RosPlantPorts(config.model_copy(update={"simulated": True}), machine_id, inbox)
    except (ConfigError, DomainRefused, RosUnavailable) as e:
        log.error("cannot start plant: %s", e)
        return 2
    with open_session(**zenoh_opts) as session:
        reset_sub = session.declare_subscriber(keys.sim_reset(machine_id), inbox.on_reset)
        log.info("plant %s up as ROS 2 node %s on ROS_DOMAIN_ID %d over %s, %s", machine_id,
                 ports.node.node.get_fully_qualified_name(), ports.node.domain_id, ports.node.rmw, ports.node.discovery)
        try:
            _loop(twin, inbox, ports.state, ports.impact, stop)
        finally:
            reset_sub.undeclare()
            ports.undeclare()
    log.info("plant %s stopped", machine_id)
    return 0


REST_QD_RADPS = 5e-3
"""A joint slower than this (rad/s, m/s) counts as still: with neutral valves the valve model lets a
loaded arm creep at 1-3 mrad/s, which a resting simulated machine does not integrate."""
REST_TICKS = 50
"""Periods (0.5 s: longer than the valve model's transport delay and lag) of stillness with
neutral valves after which a resting machine is no longer integrated."""
REST_PUBLISH_EVERY = 5
"""A resting machine publishes its state every 5th period (20 Hz: well inside the runtime's
0.2 s link timeout and the 0.1 s valve watchdog); every period again once it moves."""


def plant_tick(twin: TwinMachine, inbox: PlantInbox, now_s: float) -> tuple[MachineState, ImpactReport | None]:
    """One 10 ms plant period at local monotonic time ``now_s``: apply pending resets, the
    latest valve command (neutral if older than VALVE_WATCHDOG_S or while ``twin.fault`` is
    set) and the gripper command, step, reload the payload when due.
    A machine at rest (REST_TICKS still periods with neutral valves, no reset, the same gripper
    command, loaded) is not integrated: its state is re-stamped, so that 20 idle simulated
    machines fit on two cores; any command or reset wakes it.

    Returns:
        (the new MachineState, an ImpactReport the first time the payload is down, else None).
    """
    with inbox.lock:
        resets, inbox.resets = inbox.resets, []
        fresh = now_s - inbox.valve_rx_s <= VALVE_WATCHDOG_S
        u = inbox.valve_u.copy() if fresh and twin.fault is None else np.zeros(4)
        if resets:
            inbox.gripper_open = False  # a fresh payload sits in a closed gripper
        gripper = inbox.gripper_open
        if not fresh and not inbox.watchdog_tripped and np.isfinite(inbox.valve_rx_s):
            log.warning("no valve command for %.0f ms: valves neutral", VALVE_WATCHDOG_S * 1e3)
            if inbox.valve_u.any():  # it stopped a moving arm: final (module docstring)
                inbox.latch.trip()
                inbox.valve_u = np.zeros(4)
        inbox.watchdog_tripped = not fresh
        trips = inbox.latch.trips
    quiet = not resets and not u.any() and gripper == inbox.last_gripper
    inbox.last_gripper = gripper
    inbox.resting = quiet and inbox.still_ticks >= REST_TICKS and inbox.rest_state is not None
    if inbox.resting and inbox.rest_state is not None:  # resting implies a rest state
        return inbox.rest_state.model_copy(update={"stamp_s": twin.now_s(), "machine_fault": twin.fault,
                                                   "watchdog_trips": trips}), None
    for r in resets:
        q = twin.apply_reset(r)
        log.info("sim reset %d: q_active %s", twin.reset_count, np.round(q[:4], 3).tolist())
    report = twin.step(u, gripper)
    if report is None and twin.reload_if_due():
        with inbox.lock:
            inbox.gripper_open = False  # the fresh payload sits in a closed gripper
    state = twin.state().model_copy(update={"watchdog_trips": trips})
    # the true joint speeds: the simulated machine knows them (the measured ones carry sensor noise)
    still = quiet and twin.loaded and float(np.max(np.abs(twin.sim.data.qvel))) < REST_QD_RADPS
    inbox.still_ticks = inbox.still_ticks + 1 if still else 0
    inbox.rest_state = state if still else None
    return state, report


def _loop(twin: TwinMachine, inbox: PlantInbox, pub_state, pub_impact, stop: threading.Event) -> None:
    """Real-time 100 Hz schedule (absolute deadlines, so the period does not drift).

    A resting machine (see plant_tick) has nothing to integrate between its 20 Hz publications:
    the loop then sleeps until the next publication period instead of waking every 10 ms, and a
    command that may end the rest (PlantInbox.wake) wakes it at once (a new schedule from then).
    How late each scheduled period starts is measured when it starts (RealTimeGuard), resting or
    not, so a plant that falls behind says so in the next published state.
    """
    next_s, n, guard = time.monotonic(), 0, RealTimeGuard()
    while not stop.is_set():
        inbox.wake.clear()
        state, report = plant_tick(twin, inbox, time.monotonic())
        n += 1
        if not inbox.resting or n % REST_PUBLISH_EVERY == 0:
            pub_state.put(encode(state))
        if report is not None:
            pub_impact.put(encode(report))
            log.info("impact at %s", np.round(report.impact_pos_m, 2).tolist())
        skip = -(n + 1) % REST_PUBLISH_EVERY if inbox.resting else 0  # resting: straight to the next publication
        n += skip
        next_s += (1 + skip) * PHYSICS_PERIOD_S
        delay = next_s - time.monotonic()
        if delay > 0 and (inbox.wake.wait(delay) if inbox.resting else stop.wait(delay)):
            if not stop.is_set():  # woken by a command: handle it now
                next_s = time.monotonic()
            continue
        now = time.monotonic()
        twin.fault = guard.update(now - next_s, now)  # how late this period starts
        if now - next_s > 0.1:
            log.warning("plant loop %.0f ms behind real time; resynchronising", (now - next_s) * 1e3)
            next_s = now


def main(argv: list[str] | None = None) -> int:
    return module_main('python -m sim_twin.twin.plant', __doc__, build_parser, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
