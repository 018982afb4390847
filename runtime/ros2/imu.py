"""The passive joints (gripper_pitch, gripper_roll) from a gripper IMU (sensor_msgs/Imu) and the
arm's active joints, as a machine whose gripper carries an IMU rather than joint encoders gives them.

The IMU is mounted in the gripper link's frame (runtime.machine: x along the telescope at zero
pitch and roll, z up). Only its tilt is used, never its yaw (a magnetometer's north is not the
cabin's x axis): the chain gives R_gripper = Rz(cabin) Ry(a) Rx(roll) with a = boom + dipper +
pitch, so the machine's z axis seen in the IMU frame, R^T z = (-sin a, cos a sin roll,
cos a cos roll), yields a and roll; the pitch is a - boom - dipper. Rates: the angular velocity
in the machine frame, R w_imu, minus the cabin's and the arm's (cabin_rate z + (boom_rate +
dipper_rate) y_cabin), leaves pitch_rate y_cabin + roll_rate x_pitched, two orthogonal axes.
Valid while |boom + dipper + pitch| < 90 deg (the gripper below its axis, as a hanging gripper is).
"""

from __future__ import annotations

import math

import numpy as np

from runtime.ros2.robot_description import quat_mul
from runtime.ros2.types import quat_axis_angle


def _matrix(q_xyzw) -> np.ndarray:
    x, y, z, w = (float(v) for v in q_xyzw)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not n > 0:
        raise ValueError("zero quaternion")
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def passive_from_imu(q_active, qd_active, orientation_xyzw, angular_velocity=None) -> tuple[list[float], list[float] | None]:
    """(gripper_pitch, gripper_roll) rad and their rates rad/s (None without ``angular_velocity``).

    Args:
        q_active, qd_active: (>=3,) cabin_turn, boom, dipper positions (rad) and rates (rad/s).
        orientation_xyzw: the IMU's orientation quaternion (any yaw reference).
        angular_velocity: (3,) the IMU's angular velocity in its own frame, rad/s, or None.

    Raises:
        ValueError: a zero quaternion.
    """
    r_imu = _matrix(orientation_xyzw)
    zx, zy, zz = r_imu[2]  # the machine's z axis in the IMU frame
    a = math.atan2(-zx, math.hypot(zy, zz))
    roll = math.atan2(zy, zz)
    pitch = a - float(q_active[1]) - float(q_active[2])
    if angular_velocity is None:
        return [pitch, roll], None
    c0, s0, ca, sa, cr, sr = (math.cos(float(q_active[0])), math.sin(float(q_active[0])), math.cos(a), math.sin(a),
                              math.cos(roll), math.sin(roll))
    rz = np.array([[c0, -s0, 0.0], [s0, c0, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[ca, 0.0, sa], [0.0, 1.0, 0.0], [-sa, 0.0, ca]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    w = rz @ ry @ rx @ np.asarray(angular_velocity, dtype=float)
    y_cabin, x_pitched = rz[:, 1], (rz @ ry)[:, 0]
    rest = w - float(qd_active[0]) * np.array([0.0, 0.0, 1.0]) - (float(qd_active[1]) + float(qd_active[2])) * y_cabin
    return [pitch, roll], [float(rest @ y_cabin), float(rest @ x_pitched)]


def imu_from_joints(q, qd) -> tuple[tuple[float, float, float, float], tuple[float, float, float]]:
    """What a gripper IMU reads at joint state ``q``, ``qd`` (6,) (rad, m, rad/s, m/s): its
    orientation (x, y, z, w) in the machine frame and its angular velocity in its own frame,
    rad/s (the inverse of :func:`passive_from_imu`; the simulated machine publishes it).
    """
    c, a, r = float(q[0]), float(q[1]) + float(q[2]) + float(q[4]), float(q[5])

    qz, qy, qx = quat_axis_angle("z", c), quat_axis_angle("y", a), quat_axis_angle("x", r)
    quat = quat_mul(qz, quat_mul(qy, qx))
    rz = _matrix(qz)
    rzy = rz @ _matrix(qy)
    w_world = float(qd[0]) * np.array([0.0, 0.0, 1.0]) + (float(qd[1]) + float(qd[2]) + float(qd[4])) * rz[:, 1] + float(qd[5]) * rzy[:, 0]
    w_body = _matrix(quat).T @ w_world
    x, y, z, w = (float(v) for v in quat)
    wx, wy, wz = (float(v) for v in w_body)
    return (x, y, z, w), (wx, wy, wz)
