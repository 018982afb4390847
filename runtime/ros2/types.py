"""ROS 2 Jazzy message types, CDR (de)serialisation and type hashes, from the ``rosbags``
typestore (``Stores.ROS2_JAZZY``): no hand-written encoders.

Names are ROS 2 interface names such as ``"sensor_msgs/msg/JointState"``. Messages are the
typestore's dataclasses (:func:`msg` builds one by name); float arrays are numpy arrays.
"""

from __future__ import annotations

import functools
import math

import numpy as np

JOINT_STATE = "sensor_msgs/msg/JointState"
IMU = "sensor_msgs/msg/Imu"
FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"
BOOL = "std_msgs/msg/Bool"
STRING = "std_msgs/msg/String"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
ODOMETRY = "nav_msgs/msg/Odometry"
KEY_VALUE = "diagnostic_msgs/msg/KeyValue"


@functools.cache
def typestore():
    """The rosbags typestore of ROS 2 Jazzy (built once)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def msg(typename: str, **fields):
    """A message of ``typename`` with ``fields``.

    Raises:
        KeyError: an unknown type; TypeError: missing or unknown fields.
    """
    return typestore().types[typename](**fields)


def serialize(message, typename: str | None = None) -> bytes:
    """CDR bytes (little endian, with the 4-byte encapsulation header) of ``message``."""
    return bytes(typestore().serialize_cdr(message, typename or message.__msgtype__))


def deserialize(data: bytes | bytearray | memoryview, typename: str):
    """The message of ``typename`` in CDR ``data``.

    Raises:
        Exception: whatever rosbags raises for truncated or malformed data (callers log and drop).
    """
    return typestore().deserialize_cdr(bytes(data), typename)


@functools.cache
def type_hash(typename: str) -> str:
    """The REP-2011 type hash ``RIHS01_<64 hex>`` of ``typename`` (as rosidl generates it)."""
    return typestore().hash_rihs01(typename)


@functools.cache
def msgdef(typename: str) -> str:
    """The ``ros2msg`` schema text of ``typename`` (its .msg definition followed by those of every
    nested type, separated by lines of ``=`` as rosbag2 and MCAP expect)."""
    return typestore().generate_msgdef(typename, ros_version=2)[0]


def dds_type_name(typename: str) -> str:
    """rmw's DDS type name: ``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_``.

    Raises:
        ValueError: not a ``pkg/msg/Name`` interface name.
    """
    parts = typename.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"not a ROS 2 interface name: {typename!r}")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def stamp(t_s: float):
    """builtin_interfaces/msg/Time of ``t_s`` seconds (>= 0; negative times clamp to 0)."""
    ns = max(0, round(t_s * 1e9))
    return msg("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def stamp_s(t) -> float:
    """Seconds of a builtin_interfaces/msg/Time."""
    return t.sec + t.nanosec * 1e-9


def header(t_s: float, frame_id: str = ""):
    """std_msgs/msg/Header at ``t_s`` seconds in ``frame_id``."""
    return msg("std_msgs/msg/Header", stamp=stamp(t_s), frame_id=frame_id)


def joint_state(t_s: float, names, position=(), velocity=(), effort=()):
    """sensor_msgs/msg/JointState; arrays are float64, empty where not given."""
    def arr(v):
        return np.asarray(v, dtype=np.float64).reshape(-1)

    return msg(JOINT_STATE, header=header(t_s), name=list(names), position=arr(position), velocity=arr(velocity), effort=arr(effort))


def float64_array(values, labels=()) -> object:
    """std_msgs/msg/Float64MultiArray of ``values`` (one dimension, labelled ``",".join(labels)``)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    dim = msg("std_msgs/msg/MultiArrayDimension", label=",".join(labels), size=len(v), stride=len(v))
    return msg(FLOAT64_MULTI_ARRAY, layout=msg("std_msgs/msg/MultiArrayLayout", dim=[dim], data_offset=0), data=v)


def point_stamped(t_s: float, xyz, frame_id: str):
    """geometry_msgs/msg/PointStamped of (3,) ``xyz`` metres in ``frame_id``."""
    x, y, z = (float(v) for v in xyz)
    return msg(POINT_STAMPED, header=header(t_s, frame_id), point=msg("geometry_msgs/msg/Point", x=x, y=y, z=z))


def vector3(xyz):
    x, y, z = (float(v) for v in xyz)
    return msg("geometry_msgs/msg/Vector3", x=x, y=y, z=z)


def quaternion(xyzw):
    x, y, z, w = (float(v) for v in xyzw)
    return msg("geometry_msgs/msg/Quaternion", x=x, y=y, z=z, w=w)


def transform_stamped(t_s: float, parent: str, child: str, translation, rotation_xyzw):
    """geometry_msgs/msg/TransformStamped: ``child`` in ``parent`` (translation m, unit quaternion x, y, z, w)."""
    tf = msg("geometry_msgs/msg/Transform", translation=vector3(translation), rotation=quaternion(rotation_xyzw))
    return msg("geometry_msgs/msg/TransformStamped", header=header(t_s, parent), child_frame_id=child, transform=tf)


def odometry(t_s: float, frame_id: str, child: str, pos, vel):
    """nav_msgs/msg/Odometry with position ``pos`` (3,) m and linear velocity ``vel`` (3,) m/s in
    ``frame_id`` (orientation identity, covariances zero)."""
    pose = msg("geometry_msgs/msg/Pose", position=msg("geometry_msgs/msg/Point", **dict(zip("xyz", map(float, pos)))),
               orientation=quaternion((0.0, 0.0, 0.0, 1.0)))
    twist = msg("geometry_msgs/msg/Twist", linear=vector3(vel), angular=vector3((0.0, 0.0, 0.0)))
    zeros = np.zeros(36)
    return msg(ODOMETRY, header=header(t_s, frame_id), child_frame_id=child,
               pose=msg("geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=zeros),
               twist=msg("geometry_msgs/msg/TwistWithCovariance", twist=twist, covariance=zeros.copy()))


def quat_axis_angle(axis: str, angle_rad: float) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of a rotation by ``angle_rad`` about the x, y or z axis."""
    s, c = math.sin(angle_rad / 2), math.cos(angle_rad / 2)
    return {"x": (s, 0.0, 0.0, c), "y": (0.0, s, 0.0, c), "z": (0.0, 0.0, s, c)}[axis]
