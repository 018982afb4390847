"""The machine's robot description (URDF) and the /tf transforms of its links.

The URDF is exported from the twin's MJCF by ``sim_twin.twin.urdf`` and shipped beside this module
(``material_handler.urdf``). :class:`UrdfChain` parses its joints (xml.etree, no ROS needed) and
gives, for a joint vector in ``runtime.machine.JOINT_NAMES`` order, each link's transform in its
parent link, as robot_state_publisher would publish them on /tf (movable joints) and
/tf_static (fixed joints). Frames: the root link ``machine`` is Slinger's machine frame.
"""

from __future__ import annotations

import functools
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.ros2.types import quat_axis_angle

URDF_PATH = Path(__file__).with_name("material_handler.urdf")
ROOT_FRAME = "machine"


@functools.cache
def robot_description() -> str:
    """The machine's URDF text (read once)."""
    return URDF_PATH.read_text()


def quat_mul(a, b) -> np.ndarray:
    """Hamilton product of quaternions (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz])


def _quat_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Quaternion (x, y, z, w) of URDF rpy (fixed axes x, y, z: R = Rz(yaw) Ry(pitch) Rx(roll))."""
    return quat_mul(quat_axis_angle("z", yaw), quat_mul(quat_axis_angle("y", pitch), quat_axis_angle("x", roll)))


def _rotate(q, v) -> np.ndarray:
    """v (3,) rotated by the unit quaternion q (x, y, z, w) (v + 2 u x (u x v + w v), in floats)."""
    ux, uy, uz, w = (float(c) for c in q)
    vx, vy, vz = (float(c) for c in v)
    cx, cy, cz = uy * vz - uz * vy + w * vx, uz * vx - ux * vz + w * vy, ux * vy - uy * vx + w * vz
    return np.array([vx + 2.0 * (uy * cz - uz * cy), vy + 2.0 * (uz * cx - ux * cz), vz + 2.0 * (ux * cy - uy * cx)])


@dataclass(frozen=True)
class UrdfJoint:
    """One URDF joint: ``child`` in ``parent`` at ``xyz`` (m), ``quat`` (x, y, z, w), moving
    along/about ``axis`` (unit, child frame) for revolute, continuous and prismatic joints."""

    name: str
    kind: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    quat: tuple[float, float, float, float]
    axis: tuple[float, float, float]

    def transform(self, value: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(translation (3,), quaternion (4,) x, y, z, w) of the child in the parent at joint ``value`` (rad / m)."""
        t, q = np.array(self.xyz), np.array(self.quat)
        if self.kind in ("revolute", "continuous"):
            s = math.sin(value / 2)
            q = quat_mul(q, np.array([*(np.array(self.axis) * s), math.cos(value / 2)]))
        elif self.kind == "prismatic":
            t = t + _rotate(q, np.array(self.axis) * value)
        return t, q


class UrdfChain:
    """The joints of a URDF (default: the machine's).

    Raises:
        ValueError: a joint without parent/child or with an unsupported type (planar, floating).
    """

    def __init__(self, urdf_text: str | None = None):
        root = ET.fromstring(urdf_text or robot_description())
        self.joints: list[UrdfJoint] = []
        for j in root.iter("joint"):
            kind = j.get("type")
            if kind not in ("fixed", "revolute", "continuous", "prismatic"):
                raise ValueError(f"joint {j.get('name')}: type {kind!r} is not supported")
            origin = j.find("origin")
            xyz_values = [float(v) for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()]
            if len(xyz_values) != 3:
                raise ValueError(f"joint {j.get('name')}: origin xyz needs 3 numbers, got {len(xyz_values)}")
            xyz = (xyz_values[0], xyz_values[1], xyz_values[2])
            rpy = [float(v) for v in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()]
            axis = j.find("axis")
            ax = np.array([float(v) for v in (axis.get("xyz", "1 0 0") if axis is not None else "1 0 0").split()])
            parent, child = j.find("parent"), j.find("child")
            if parent is None or child is None:
                raise ValueError(f"joint {j.get('name')}: needs parent and child")
            name, parent_link, child_link = j.get("name"), parent.get("link"), child.get("link")
            if name is None or parent_link is None or child_link is None:
                raise ValueError(f"joint {name}: needs a name and parent and child links")
            self.joints.append(UrdfJoint(name, kind, parent_link, child_link, xyz,
                                         tuple(_quat_rpy(*rpy)), tuple(ax / np.linalg.norm(ax))))

    @property
    def fixed(self) -> list[UrdfJoint]:
        return [j for j in self.joints if j.kind == "fixed"]

    @property
    def movable(self) -> list[UrdfJoint]:
        return [j for j in self.joints if j.kind != "fixed"]

    def transforms(self, values: dict[str, float]) -> list[tuple[UrdfJoint, np.ndarray, np.ndarray]]:
        """(joint, translation, quaternion) of every movable joint's child at ``values`` (joint
        name -> rad / m; missing joints at 0)."""
        return [(j, *j.transform(float(values.get(j.name, 0.0)))) for j in self.movable]

    def link_pose(self, link: str, values: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,), quaternion (4,)) of ``link`` in the root frame at ``values``.

        Raises:
            KeyError: no such link.
        """
        by_child = {j.child: j for j in self.joints}
        chain = []
        while link in by_child:
            chain.append(by_child[link])
            link = by_child[link].parent
        p, q = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])
        for j in reversed(chain):
            t, r = j.transform(float(values.get(j.name, 0.0)))
            p, q = p + _rotate(q, t), quat_mul(q, r)
        return p, q
