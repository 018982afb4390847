"""The ROS 2 machine bridge: a machine whose driver is a ROS 2 node, behind Slinger's machine interface.

Machine side, beside the runtime (one per machine, runtime wheel with the ``ros2`` extra)::

    slinger ros2-bridge --machine-id m1 --config bridge.toml --connect tcp/127.0.0.1:7447
    (slinger-ros2-bridge ... from the runtime wheel; python -m runtime.ros2.bridge ...)

It is an rclpy node (runtime.ros2.node: ``RMW_IMPLEMENTATION`` picks the middleware, Fast DDS
by default; discovery machine-local unless SROS2 is enforced) named ``slinger_bridge`` on the
mapping's domain, and a Zenoh peer of Slinger's network. With the topic, joint-name and unit
mapping of its configuration (runtime.ros2.config) it translates:

* ROS -> Slinger: each ``sensor_msgs/JointState`` on the joint-states topic becomes one
  ``MachineState`` on keys.state(id) (stamped with this host's monotonic clock, which the runtime
  shares), with the passive joints (same or own JointState topic, or from a gripper
  ``sensor_msgs/Imu``: runtime.ros2.imu), the gripper state, the payload
  (``nav_msgs/Odometry``, optional) and the machine's fault (``std_msgs/String``, optional); a
  ``geometry_msgs/PointStamped`` on the impact topic becomes an ``ImpactReport`` (opening = when
  the gripper state turned open; release position and velocity from the payload odometry then,
  else the impact point and zero velocity);
* Slinger -> ROS: ``ValveCommand`` -> ``std_msgs/Float64MultiArray`` (only the newest runtime
  epoch, as the simulated machine does), ``GripperCommand`` -> ``std_msgs/Bool``; a command that
  would move the arm or open the gripper and answers a state older than
  runtime.protocol.messages.STALE_COMMAND_S is dropped (queued at a stalled runtime or bridge).

Safety stays in the runtime (watchdog, E-STOP latch, signed commands). A required ROS topic
(joint states, passive joints, gripper state) older than ``stale_after_s`` stops the
MachineStates: the runtime sees a machine-link loss (a running throw fails "machine link lost",
throws are refused "machine offline"). When the runtime's valve commands stop for 0.1 s the bridge
sends one neutral command (the machine must also hold its valves neutral on its own watchdog),
holds the valves neutral until the runtime sends a neutral command, and counts a watchdog trip:
the states carry the count (``MachineState.watchdog_trips``, as the simulated machine's plant
does), so the runtime fails a throw or a return to the ready pose whose valves its watchdog put
neutral. A trip of the machine driver's own watchdog is not read.
A second publisher on the valve- or gripper-command topic (a stranger on the ROS domain) is a
machine fault for as long as it is there and FOREIGN_HOLD_S after: the states carry it (the
runtime fails a running throw and refuses throws with it) and only neutral valve commands go
out. The bridge holds the machine's liveliness token keys.machine_alive(id) (one bridge or plant
per machine, runtime.zenoh_session.claim_exclusive); with TLS it uses the certificate ``plant-<id>``.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from runtime.entrypoint import module_main, stop_on_signals
from runtime.epoch_fence import EpochFence, WatchdogLatch, decode_for
from runtime.machine import ACTIVE_JOINTS, PASSIVE_JOINTS
from runtime.protocol import keys
from runtime.protocol.messages import (
    GripperCommand,
    ImpactReport,
    MachineState,
    ValveCommand,
    encode,
    stale_motion,
)
from runtime.ros2 import types as rt
from runtime.ros2.config import BridgeConfig, ConfigError, load
from runtime.ros2.imu import passive_from_imu
from runtime.zenoh_session import (
    Claimed,
    add_session_arguments,
    claim_exclusive,
    open_session,
    session_options,
)

log = logging.getLogger(__name__)

VALVE_SILENCE_S = 0.1
"""Runtime silence (s) after which the bridge sends one neutral valve command."""
FOREIGN_HOLD_S = 2.0
"""A foreign command publisher stays a machine fault this long (s) after it was last seen."""
EXIT_ALREADY_CLAIMED = 3


class MachineBridge:
    """The translation, without I/O (tests drive it directly; :func:`run` wires it to Zenoh).

    Args:
        machine_id: the Slinger machine id.
        config: the mapping.
        send_state / send_impact: called with a MachineState / ImpactReport (Slinger side).
        send_valves / send_gripper: called with a ROS Float64MultiArray / Bool (ROS side).
        clock: monotonic seconds (the runtime's clock); wall: Unix seconds (ROS header stamps).
    """

    def __init__(self, machine_id: str, config: BridgeConfig, send_state: Callable, send_impact: Callable,
                 send_valves: Callable, send_gripper: Callable, clock: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.time):
        self.machine_id = keys.validate_machine_id(machine_id)
        self.config = config
        self.send_state, self.send_impact, self.send_valves, self.send_gripper = send_state, send_impact, send_valves, send_gripper
        self.clock, self.wall = clock, wall
        self.lock = threading.Lock()
        self.rx: dict[str, float] = {}  # topic role -> monotonic receive time
        self.active: tuple[list[float], list[float]] | None = None
        self.passive: tuple[list[float], list[float]] | None = None
        self.imu: tuple[tuple[float, float, float, float], tuple[float, float, float]] | None = None  # orientation (x, y, z, w), angular velocity (IMU frame)
        self.gripper_open: bool | None = None
        self.payload_attached: bool | None = None
        self.payload: tuple[list[float], list[float]] | None = None
        self.fault: str | None = None
        self.opening: tuple[float, list[float] | None, list[float] | None] | None = None
        self.fence = EpochFence()
        self.valve_rx_s = -np.inf
        self.valves_neutral = True
        self.latch = WatchdogLatch()
        """Times the bridge put moving valves neutral on the runtime's silence (MachineState.watchdog_trips)
        and, after one, neutral valves until a neutral valve command arrives (as the simulated machine's
        plant), so a throw whose valves were put neutral is never driven on."""
        self.stale: str | None = None  # the stale topic, logged once per episode
        self.dropped = 0
        self.stale_commands = 0
        """Valve and gripper commands dropped as stale (runtime.protocol.messages.stale_motion)."""
        self.command_fault: str | None = None  # a foreign command publisher (set_command_fault)
        self.command_fault_s = -np.inf

    # --- ROS -> Slinger -------------------------------------------------------------------
    def on_joint_state(self, msg) -> None:
        """A JointState on the joint-states topic: the active joints (and the passive ones if
        they share it); publishes one MachineState when every required topic is fresh."""
        now = self.clock()
        active = self.config.to_slinger(ACTIVE_JOINTS, list(msg.name), msg.position, msg.velocity)
        if active is None:
            self._drop(f"JointState on {self.config.topics.joint_states} lacks a mapped active joint or is not finite")
            return
        with self.lock:
            self.active, self.rx["joint_states"] = active, now
            if not (self.config.topics.passive_joint_states or self.config.topics.imu):
                self._take_passive(msg, now)
            state = self._state(now)
        if state is not None:
            self.send_state(state)

    def on_passive_joint_state(self, msg) -> None:
        """A JointState on the separate passive-joint topic (gripper IMU angles)."""
        with self.lock:
            self._take_passive(msg, self.clock())

    def on_imu(self, msg) -> None:
        """A sensor_msgs/Imu of the gripper: the passive joints, computed with the active joints
        current when a machine state is made (runtime.ros2.imu)."""
        o, w = msg.orientation, msg.angular_velocity
        quat, omega = (o.x, o.y, o.z, o.w), (w.x, w.y, w.z)
        if not (all(np.isfinite(quat + omega)) and any(quat)):
            self._drop("non-finite or zero IMU orientation")
            return
        with self.lock:
            self.imu, self.rx["passive"] = (quat, omega), self.clock()

    def _take_passive(self, msg, now: float) -> None:
        passive = self.config.to_slinger(PASSIVE_JOINTS, list(msg.name), msg.position, msg.velocity)
        if passive is None:
            self._drop(f"JointState on {self.config.passive_topic} lacks gripper_pitch/gripper_roll or is not finite")
            return
        self.passive, self.rx["passive"] = passive, now

    def on_gripper_state(self, msg) -> None:
        now = self.clock()
        with self.lock:
            opened = bool(msg.data)
            if opened and self.gripper_open is False:  # the opening: the payload is free
                self.opening = (now, *(self.payload or (None, None)))
            self.gripper_open, self.rx["gripper_state"] = opened, now

    def on_payload_attached(self, msg) -> None:
        with self.lock:
            self.payload_attached, self.rx["payload_attached"] = bool(msg.data), self.clock()

    def on_payload(self, msg) -> None:
        p, v = msg.pose.pose.position, msg.twist.twist.linear
        pos, vel = [p.x, p.y, p.z], [v.x, v.y, v.z]
        if not all(np.isfinite(pos + vel)):
            self._drop("non-finite payload odometry")
            return
        with self.lock:
            self.payload, self.rx["payload"] = (pos, vel), self.clock()

    def on_fault(self, msg) -> None:
        with self.lock:
            self.fault = (msg.data or None) and msg.data[:200]

    def on_impact(self, msg) -> None:
        """A PointStamped on the impact topic: one ImpactReport (stamps on this host's monotonic clock)."""
        pt = [msg.point.x, msg.point.y, msg.point.z]
        if not all(np.isfinite(pt)):
            self._drop("non-finite impact point")
            return
        now = self.clock()
        t_hit = now - max(0.0, self.wall() - rt.stamp_s(msg.header.stamp))
        with self.lock:
            opened_s, pos, vel = self.opening or (t_hit, None, None)
        report = ImpactReport(machine_id=self.machine_id, stamp_s=now, impact_pos_m=pt, opening_stamp_s=opened_s,
                              impact_stamp_s=t_hit, release_pos_m=pos or pt, release_vel_mps=vel or [0.0, 0.0, 0.0])
        self.send_impact(report)

    def _state(self, now: float) -> MachineState | None:
        """The MachineState now, or None while a required topic is stale (logged once)."""
        limit = self.config.stale_after_s
        required = ["joint_states", "passive", "gripper_state"] + (["payload_attached"] if self.config.topics.payload_attached else [])
        stale = next((r for r in required if now - self.rx.get(r, -np.inf) > limit), None)
        if stale is not None:
            if stale != self.stale:
                log.warning("ROS topic for %s silent for more than %.0f ms: no machine state (machine link lost)", stale, limit * 1e3)
            self.stale = stale
            return None
        if self.stale is not None:
            log.info("ROS topics fresh again: machine states resume")
            self.stale = None
        if self.active is None:
            raise RuntimeError("joint_states counted fresh but no active joint state stored")
        if self.config.topics.imu:
            if self.imu is None:
                raise RuntimeError("IMU counted fresh but no IMU reading stored")
            angles, rates = passive_from_imu(self.active[0], self.active[1], *self.imu)
            if rates is None:
                raise RuntimeError("IMU reading stored without angular velocity")
            self.passive = (angles, rates)
        if self.passive is None:
            raise RuntimeError("passive joints counted fresh but no passive joint state stored")
        q = self.active[0] + self.passive[0]
        qd = self.active[1] + self.passive[1]
        attached = self.payload_attached if self.config.topics.payload_attached else not self.gripper_open
        payload = self.payload if now - self.rx.get("payload", -np.inf) <= limit else None  # None when stale
        return MachineState(machine_id=self.machine_id, stamp_s=now, q=q, qd=qd, gripper_open=bool(self.gripper_open),
                            payload_attached=bool(attached), payload_pos_m=payload[0] if payload is not None else None,
                            payload_vel_mps=payload[1] if payload is not None else None, simulated=self.config.simulated,
                            machine_fault=self.command_fault or self.fault, watchdog_trips=self.latch.trips)

    def _drop(self, why: str) -> None:
        self.dropped += 1
        if self.dropped in (1, 10, 100) or self.dropped % 1000 == 0:
            log.warning("dropping ROS message (%d so far): %s", self.dropped, why)

    # --- Slinger -> ROS -------------------------------------------------------------------
    def on_valve_command(self, payload: bytes) -> None:
        """A ValveCommand of the runtime -> the ROS valve array (newest epoch only; a non-neutral
        one answering a state older than STALE_COMMAND_S is dropped, as the simulated machine's
        plant drops it: queued at a stalled runtime or at this bridge, it would move the arm late)."""
        msg = decode_for(ValveCommand, payload, self.machine_id)
        if msg is None:
            return
        with self.lock:
            if not self.fence.admit(msg):
                return
            if stale_motion(msg, self.clock()):
                self.stale_commands += 1
                if self.stale_commands in (1, 10, 100) or self.stale_commands % 1000 == 0:
                    log.warning("dropping a valve command %.0f ms old (%d so far): queued at a stalled runtime or bridge",
                                (self.clock() - msg.stamp_s) * 1e3, self.stale_commands)
                return
            u = [0.0] * 4 if self.command_fault else msg.u
            if not self.latch.admit(u):  # after a watchdog trip: neutral until the runtime sends neutral (its throw ended)
                u = [0.0] * 4
            self.valve_rx_s, self.valves_neutral = self.clock(), not any(u)
        self.send_valves(rt.float64_array(self.config.valve_array(u), _valve_labels(self.config)))

    def on_gripper_command(self, payload: bytes) -> None:
        """A GripperCommand of the runtime -> the ROS gripper Bool; an opening one answering a state
        older than STALE_COMMAND_S is dropped (a late release throws the payload where nobody aimed;
        the runtime's throw then fails without a release)."""
        msg = decode_for(GripperCommand, payload, self.machine_id)
        if msg is None:
            return
        if stale_motion(msg, self.clock()):
            with self.lock:
                self.stale_commands += 1
            log.error("dropping a gripper open command %.0f ms old: queued at a stalled runtime or bridge (a late release)",
                      (self.clock() - msg.stamp_s) * 1e3)
            return
        self.send_gripper(rt.msg(rt.BOOL, data=bool(msg.open)))

    def set_command_fault(self, fault: str | None) -> None:
        """The graph check's finding (runtime.ros2.node.RosNode.command_publishers_fault): a
        fault starts at once (neutral valves sent, the fault in every state from now on) and
        ends FOREIGN_HOLD_S after the last finding."""
        now = self.clock()
        with self.lock:
            started = fault is not None and self.command_fault is None
            if fault is not None:
                self.command_fault, self.command_fault_s = fault, now
            elif self.command_fault is not None and now - self.command_fault_s > FOREIGN_HOLD_S:
                log.warning("command topics have one publisher again: fault cleared")
                self.command_fault = None
            if started:
                self.valves_neutral = True
        if started:
            log.error("machine fault: %s: valves neutral, no command forwarded", fault)
            self.send_valves(rt.float64_array(self.config.valve_array([0.0] * 4), _valve_labels(self.config)))

    def check(self) -> None:
        """Periodic: one neutral valve command when the runtime fell silent with the valves open
        (a watchdog trip, counted); log a silent machine."""
        now = self.clock()
        with self.lock:
            silent = not self.valves_neutral and now - self.valve_rx_s > VALVE_SILENCE_S
            if silent:
                self.valves_neutral = True
                self.latch.trip()
            if now - self.rx.get("joint_states", -np.inf) > self.config.stale_after_s and self.stale != "joint_states":
                self.stale = "joint_states"
                log.warning("ROS topic %s silent: no machine state (machine link lost)", self.config.topics.joint_states)
        if silent:
            log.warning("no valve command for %.0f ms: neutral valves sent", VALVE_SILENCE_S * 1e3)
            self.send_valves(rt.float64_array(self.config.valve_array([0.0] * 4), _valve_labels(self.config)))


def _valve_labels(config: BridgeConfig) -> list[str]:
    names = [""] * config.valve_array_size
    for j in ACTIVE_JOINTS:
        names[config.valve(j).index] = j
    return names


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--machine-id", required=True, help="machine id, [A-Za-z0-9_-]{1,64}")
    parser.add_argument("--config", type=Path, default=None, help="topic/joint/unit mapping (.toml, .json, .yaml); default: identity")
    parser.add_argument("--domain-id", type=int, default=None,
                        help="ROS_DOMAIN_ID, 0..232 (default: the mapping's domain_id, else the environment's ROS_DOMAIN_ID, else 0)")
    parser.add_argument("--simulated", action="store_true",
                        help="the machine behind is the simulated one (slinger plant --ros2): states say simulated (as the mapping's simulated = true)")
    add_session_arguments(parser)


def load_config(path: Path | None, domain_id: int | None) -> BridgeConfig:
    """The mapping at ``path`` (identity without), its domain id replaced by ``domain_id`` if given.

    Raises:
        ConfigError: an unusable file or domain id.
    """
    config = load(path) if path else BridgeConfig()
    if domain_id is None:
        return config
    try:
        return BridgeConfig.model_validate({**config.model_dump(), "domain_id": domain_id})
    except ValueError as e:
        raise ConfigError(f"--domain-id {domain_id}: must be 0..232") from e


def run(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """Run the bridge until SIGINT/SIGTERM (or ``stop``). Returns the exit code (2: bad
    arguments, configuration or ROS 2 environment, 3: the machine already has a bridge or plant)."""
    from runtime.ros2.node import EVENT_QOS, SENSOR_QOS, VALVE_QOS, DomainRefused, RosNode, RosUnavailable

    try:
        machine_id = keys.validate_machine_id(args.machine_id)
        config = load_config(args.config, getattr(args, "domain_id", None))
        if getattr(args, "simulated", False):
            config = config.model_copy(update={"simulated": True})
        zenoh_opts = session_options(args, f"plant-{machine_id}", [machine_id])
    except (ValueError, OSError, ConfigError) as e:
        log.error("cannot start the ROS 2 bridge: %s", e)
        return 2
    stop = stop_on_signals(stop)
    with open_session(**zenoh_opts) as session:
        try:
            token, claim_token = claim_exclusive(session, keys.machine_alive(machine_id), lambda c: keys.machine_claim(machine_id, c))
        except Claimed as e:
            log.error("machine %s already has a bridge or plant (%s): not starting a second one", machine_id, e)
            return EXIT_ALREADY_CLAIMED
        try:
            node = RosNode(config.node_name, config.namespace, config.domain_id)
        except (DomainRefused, RosUnavailable) as e:
            log.error("cannot start the ROS 2 bridge: %s", e)
            token.undeclare()
            claim_token.undeclare()
            return 2
        t = config.topics
        pub_valves = node.publisher(t.valve_command, rt.FLOAT64_MULTI_ARRAY, VALVE_QOS)
        pub_gripper = node.publisher(t.gripper_command, rt.BOOL, EVENT_QOS)
        pub_state = session.declare_publisher(keys.state(machine_id))
        pub_impact = session.declare_publisher(keys.impact(machine_id))
        bridge = MachineBridge(machine_id, config, lambda m: pub_state.put(encode(m)), lambda m: pub_impact.put(encode(m)),
                               pub_valves.publish, pub_gripper.publish)
        node.subscribe(t.joint_states, rt.JOINT_STATE, bridge.on_joint_state, SENSOR_QOS)
        if t.imu:
            node.subscribe(t.imu, rt.IMU, bridge.on_imu, SENSOR_QOS)
        elif t.passive_joint_states:
            node.subscribe(t.passive_joint_states, rt.JOINT_STATE, bridge.on_passive_joint_state, SENSOR_QOS)
        node.subscribe(t.gripper_state, rt.BOOL, bridge.on_gripper_state, SENSOR_QOS)
        for topic, typename, handler, qos in ((t.payload_attached, rt.BOOL, bridge.on_payload_attached, SENSOR_QOS),
                                              (t.payload, rt.ODOMETRY, bridge.on_payload, SENSOR_QOS),
                                              (t.fault, rt.STRING, bridge.on_fault, SENSOR_QOS),
                                              (t.impact, rt.POINT_STAMPED, bridge.on_impact, EVENT_QOS)):
            if topic:
                node.subscribe(topic, typename, handler, qos)
        subs = [session.declare_subscriber(keys.valve_cmd(machine_id), lambda s: bridge.on_valve_command(s.payload.to_bytes())),
                session.declare_subscriber(keys.gripper_cmd(machine_id), lambda s: bridge.on_gripper_command(s.payload.to_bytes()))]
        log.info("ROS 2 bridge %s up: node %s on ROS_DOMAIN_ID %d over %s, %s", machine_id, node.node.get_fully_qualified_name(),
                 node.domain_id, node.rmw, node.discovery)
        try:
            while not stop.wait(0.02):
                bridge.set_command_fault(node.command_publishers_fault((t.valve_command, t.gripper_command)))
                bridge.check()
        finally:
            for s in subs:
                s.undeclare()
            node.close()
            pub_state.undeclare()
            pub_impact.undeclare()
            token.undeclare()
            claim_token.undeclare()
    log.info("ROS 2 bridge %s stopped", machine_id)
    return 0


def main(argv: list[str] | None = None) -> int:
    return module_main("slinger ros2-bridge", __doc__, build_parser, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
