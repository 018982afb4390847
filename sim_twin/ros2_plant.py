"""The simulated machine as a ROS 2 machine (``slinger plant --ros2 [CONFIG]``): the plant speaks
ROS 2 over Zenoh in rmw_zenoh's format instead of Slinger's machine interface, as a machine whose
controllers are ROS nodes would; the runtime reaches it through the ROS 2 bridge
(runtime.ros2.bridge) with the same mapping file.

It publishes, per plant period (20 Hz at rest, as the plant does): ``sensor_msgs/JointState`` of
the active joints (and the passive ones, on their own topic if the mapping names one, or as a
gripper ``sensor_msgs/Imu``: runtime.ros2.imu.imu_from_joints; its linear acceleration is not
simulated and reads zero), the
gripper state (``std_msgs/Bool``, true = open), the payload (``nav_msgs/Odometry``) and the fault
(``std_msgs/String``) where the mapping names topics for them, and one ``geometry_msgs/PointStamped``
per landing on the impact topic (header stamp: the landing's wall-clock time). It subscribes the
valve array and the gripper command. Units and names are the mapping's inverse. ``sim/reset``
stays on Slinger's key (a tool of the simulated machine only); the machine's liveliness token is
the bridge's.
"""

from __future__ import annotations

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
from runtime.ros2.rmw_zenoh import RosNode

NODE_NAME = "simulated_machine"


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
    as sim_twin.plant's loop produces them) and command subscriptions over ROS 2.

    Args:
        session: the plant's Zenoh session; config: the bridge mapping; machine_id: the plant's
        machine id; inbox: sim_twin.plant.PlantInbox that receives the commands.
    """

    def __init__(self, session, config: BridgeConfig, machine_id: str, inbox):
        self.config, self.machine_id, self.inbox = config, machine_id, inbox
        self.node = RosNode(session, NODE_NAME, config.namespace, config.domain_id)
        t = config.topics
        self._joints = self.node.publisher(t.joint_states, rt.JOINT_STATE)
        self._imu = self.node.publisher(t.imu, rt.IMU) if t.imu else None
        self._passive = self.node.publisher(t.passive_joint_states, rt.JOINT_STATE) if t.passive_joint_states and not t.imu else None
        self._gripper = self.node.publisher(t.gripper_state, rt.BOOL)
        self._payload = self.node.publisher(t.payload, rt.ODOMETRY) if t.payload else None
        self._fault = self.node.publisher(t.fault, rt.STRING) if t.fault else None
        self._impact = self.node.publisher(t.impact, rt.POINT_STAMPED) if t.impact else None
        self.node.subscribe(t.valve_command, rt.FLOAT64_MULTI_ARRAY, self._on_valves)
        self.node.subscribe(t.gripper_command, rt.BOOL, self._on_gripper)
        self.state, self.impact = _Put(self._put_state), _Put(self._put_impact)

    def _wall(self, stamp_s: float) -> float:
        return time.time() - (time.monotonic() - stamp_s)

    def _put_state(self, data: bytes) -> None:
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
            self._fault.publish(rt.msg(rt.STRING, data=s.machine_fault or ""))
        self._joints.publish(rt.joint_state(t, names, q, qd))  # last: the bridge publishes a state on it

    def _put_impact(self, data: bytes) -> None:
        if self._impact is not None:
            r = decode(ImpactReport, data)
            self._impact.publish(rt.point_stamped(self._wall(r.impact_stamp_s), r.impact_pos_m, "machine"))

    def _on_valves(self, msg) -> None:
        u = self.config.valve_u(msg.data)
        if u is None:
            return
        u = [min(1.0, max(-1.0, v)) for v in u]
        self.inbox.on_valve(_Sample(encode(ValveCommand(machine_id=self.machine_id, stamp_s=time.monotonic(), u=u))))

    def _on_gripper(self, msg) -> None:
        self.inbox.on_gripper(_Sample(encode(GripperCommand(machine_id=self.machine_id, stamp_s=time.monotonic(), open=bool(msg.data)))))

    def undeclare(self) -> None:
        self.node.close()


class _Put:
    def __init__(self, fn):
        self.put = fn
