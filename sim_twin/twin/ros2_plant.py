"""The simulated machine as a ROS 2 machine (``slinger plant --ros2 [CONFIG]``): the plant is an
rclpy driver node (runtime.ros2.node, the middleware ``RMW_IMPLEMENTATION`` names) instead of a
peer of Slinger's machine interface, as a machine whose own control stack is ROS 2 would be; the
runtime reaches it through the ROS 2 bridge (runtime.ros2.bridge) with the same mapping file.

Node ``simulated_machine`` publishes, per plant period (100 Hz while anything moves, 20 Hz at
rest, as the plant does): ``sensor_msgs/JointState`` of the active joints (and the passive ones,
on their own topic if the mapping names one, or as a gripper ``sensor_msgs/Imu``:
runtime.ros2.imu.imu_from_joints; its linear acceleration is not simulated and reads zero), the
gripper state (``std_msgs/Bool``, true = open), the payload (``nav_msgs/Odometry``) and the fault
(``std_msgs/String``) where the mapping names topics for them, and one
``geometry_msgs/PointStamped`` per landing on the impact topic (header stamp: the landing's
wall-clock time). QoS: joint states, gripper state and fault reliable (as ros2_control's
joint_state_broadcaster), IMU and odometry best effort (sensor data), the impact reliable.

It takes valve commands (``std_msgs/Float64MultiArray``; QoS VALVE_QOS: a 0.1 s deadline and a
0.5 s liveliness lease requested, so a silent or dead commander sets the valves neutral at once)
and gripper commands (``std_msgs/Bool``) from the bridge alone: a message whose publisher (GID
checked against the ROS graph) is not the topic's only publisher, or not the mapping's bridge
node, is dropped; while a second publisher is on the graph, and FOREIGN_HOLD_S after, every
command is refused, the valves are held neutral and the fault topic says why. Units and names are the mapping's inverse.
``sim/reset`` stays on Slinger's Zenoh key (a tool of the simulated machine only); the machine's
liveliness token is the bridge's.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from runtime.machine import ACTIVE_JOINTS, PASSIVE_JOINTS
from runtime.protocol.messages import (
    GripperCommand,
    ImpactReport,
    MachineState,
    ValveCommand,
    decode,
    encode,
)
from runtime.ros2 import types as rt
from runtime.ros2.config import BridgeConfig
from runtime.ros2.imu import imu_from_joints
from runtime.ros2.node import (
    EVENT_QOS,
    SENSOR_QOS,
    STATE_QOS,
    VALVE_QOS,
    RosNode,
    gid_of,
    publishers_fault,
)

log = logging.getLogger(__name__)

NODE_NAME = "simulated_machine"
FOREIGN_HOLD_S = 2.0
"""A second command publisher stays a fault this long (s) after it was last on the graph."""


class _Payload:
    def __init__(self, data: bytes):
        self._data = data

    def to_bytes(self) -> bytes:
        return self._data


class _Sample:
    """What PlantInbox's handlers read of a Zenoh sample: ``payload.to_bytes()``."""

    def __init__(self, data: bytes):
        self.payload = _Payload(data)


class RosPlantPorts:
    """The plant's publishers (``state.put`` / ``impact.put`` take the encoded Slinger messages,
    as sim_twin.twin.plant's loop produces them) and command subscriptions, as an rclpy node.

    Args:
        config: the bridge mapping; machine_id: the plant's machine id; inbox:
        sim_twin.twin.plant.PlantInbox that receives the commands; domain_id: ROS_DOMAIN_ID (None:
        the mapping's, else the environment's).

    Raises:
        runtime.ros2.node.DomainRefused / RosUnavailable: as RosNode.
    """

    def __init__(self, config: BridgeConfig, machine_id: str, inbox, domain_id: int | None = None):
        self.config, self.machine_id, self.inbox = config, machine_id, inbox
        self.node = RosNode(NODE_NAME, config.namespace, config.domain_id if domain_id is None else domain_id)
        t = config.topics
        self._joints = self.node.publisher(t.joint_states, rt.JOINT_STATE, STATE_QOS)
        self._imu = self.node.publisher(t.imu, rt.IMU, SENSOR_QOS) if t.imu else None
        self._passive = (self.node.publisher(t.passive_joint_states, rt.JOINT_STATE, STATE_QOS)
                         if t.passive_joint_states and not t.imu else None)
        self._gripper = self.node.publisher(t.gripper_state, rt.BOOL, STATE_QOS)
        self._payload = self.node.publisher(t.payload, rt.ODOMETRY, SENSOR_QOS) if t.payload else None
        self._fault = self.node.publisher(t.fault, rt.STRING, STATE_QOS) if t.fault else None
        self._impact = self.node.publisher(t.impact, rt.POINT_STAMPED, EVENT_QOS) if t.impact else None
        self._lock = threading.Lock()
        self._command_gids: dict[str, set[bytes]] = {t.valve_command: set(), t.gripper_command: set()}
        """Per command topic: the GIDs of its publishers on the graph, when it has one only and
        that one is the bridge's node (the mapping's node_name in its namespace); else empty."""
        self.command_fault: str | None = None
        self._command_fault_s = -np.inf
        self.refused = 0  # commands dropped: not from the bridge's node alone
        self.node.subscribe(t.valve_command, rt.FLOAT64_MULTI_ARRAY, self._on_valves, VALVE_QOS,
                            on_deadline=lambda _e: self._commander_silent("valve commands missed their deadline"),
                            on_liveliness=self._on_liveliness)
        self.node.subscribe(t.gripper_command, rt.BOOL, self._on_gripper, EVENT_QOS)
        self.state, self.impact = _Put(self._put_state), _Put(self._put_impact)

    def _wall(self, stamp_s: float) -> float:
        return time.time() - (time.monotonic() - stamp_s)

    def check_commanders(self) -> None:
        """Refresh the command topics' publisher GIDs from the ROS graph; a second publisher
        starts (or prolongs) the fault, which holds the valves neutral."""
        infos = {topic: self.node.publishers_of(topic) for topic in self._command_gids}
        bridge = (self.config.node_name, "/" + self.config.namespace.strip("/"))
        gids = {topic: {gid_of(i) for i in found if (i.node_name, i.node_namespace) == bridge} if len(found) == 1 else set()
                for topic, found in infos.items()}
        fault = next((f for f in (publishers_fault(topic, found) for topic, found in infos.items()) if f), None)
        now = time.monotonic()
        with self._lock:
            self._command_gids = gids
            started = fault is not None and self.command_fault is None
            if fault is not None:
                self.command_fault, self._command_fault_s = fault, now
            elif self.command_fault is not None and now - self._command_fault_s > FOREIGN_HOLD_S:
                log.warning("command topics have one publisher again: taking commands")
                self.command_fault = None
        if started:
            log.error("%s: valves neutral, commands refused", fault)
            self._neutral()

    def _neutral(self) -> None:
        with self.inbox.lock:
            self.inbox.valve_u, self.inbox.valve_rx_s = np.zeros(4), -np.inf

    def _commander_silent(self, why: str) -> None:
        if np.isfinite(self.inbox.valve_rx_s):
            log.warning("%s: valves neutral", why)
        self._neutral()

    def _on_liveliness(self, event) -> None:
        if event.alive_count == 0:
            self._commander_silent("valve commander lost liveliness")

    def _admit(self, topic: str, info) -> bool:
        """A command from the topic's only publisher, the bridge's node, with no command fault
        standing; a command from any other publisher is dropped (and logged)."""
        gid = gid_of(info)
        with self._lock:
            known = gid in self._command_gids[topic]
        if not known:  # a publisher the last graph check did not admit: look again now
            self.check_commanders()
        with self._lock:
            admitted, fault = gid in self._command_gids[topic], self.command_fault
        if fault is not None:
            self._neutral()
            return False
        if not admitted:
            self.refused += 1
            if self.refused in (1, 10, 100) or self.refused % 1000 == 0:
                log.error("dropped %d commands on %s from a publisher that is not the bridge node %r alone", self.refused, topic,
                          self.config.node_name)
            return False
        return True

    def _put_state(self, data: bytes) -> None:
        self.check_commanders()
        s = decode(MachineState, data)
        t = self._wall(s.stamp_s)
        both = not (self.config.topics.passive_joint_states or self.config.topics.imu)
        joints = ACTIVE_JOINTS + PASSIVE_JOINTS if both else ACTIVE_JOINTS
        names, q, qd = self.config.to_ros(joints, s.q[:len(joints)], s.qd[:len(joints)])
        if self._passive is not None:
            pn, pq, pqd = self.config.to_ros(PASSIVE_JOINTS, s.q[4:], s.qd[4:])
            self._passive.publish(rt.joint_state(t, pn, pq, pqd))
        if self._imu is not None:
            quat, omega = imu_from_joints(s.q, s.qd)
            zeros = np.zeros(9)
            self._imu.publish(rt.msg(rt.IMU, header=rt.header(t, "gripper"), orientation=rt.quaternion(quat), orientation_covariance=zeros,
                                     angular_velocity=rt.vector3(omega), angular_velocity_covariance=zeros,
                                     linear_acceleration=rt.vector3((0.0, 0.0, 0.0)), linear_acceleration_covariance=zeros))
        self._gripper.publish(rt.msg(rt.BOOL, data=s.gripper_open))
        if self._payload is not None and s.payload_pos_m is not None and s.payload_vel_mps is not None:
            self._payload.publish(rt.odometry(t, "machine", "payload", s.payload_pos_m, s.payload_vel_mps))
        if self._fault is not None:
            self._fault.publish(rt.msg(rt.STRING, data=self.command_fault or s.machine_fault or ""))
        self._joints.publish(rt.joint_state(t, names, q, qd))  # last: the bridge publishes a state on it

    def _put_impact(self, data: bytes) -> None:
        if self._impact is not None:
            r = decode(ImpactReport, data)
            self._impact.publish(rt.point_stamped(self._wall(r.impact_stamp_s), r.impact_pos_m, "machine"))

    def _on_valves(self, msg, info) -> None:
        if not self._admit(self.config.topics.valve_command, info):
            return
        u = self.config.valve_u(msg.data)
        if u is None:
            return
        u = [min(1.0, max(-1.0, v)) for v in u]
        self.inbox.on_valve(_Sample(encode(ValveCommand(machine_id=self.machine_id, stamp_s=time.monotonic(), u=u))))

    def _on_gripper(self, msg, info) -> None:
        if not self._admit(self.config.topics.gripper_command, info):
            return
        self.inbox.on_gripper(_Sample(encode(GripperCommand(machine_id=self.machine_id, stamp_s=time.monotonic(), open=bool(msg.data)))))

    def undeclare(self) -> None:
        self.node.close()


class _Put:
    def __init__(self, fn):
        self.put = fn
