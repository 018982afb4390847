"""The machine's drawing geometry without MuJoCo: the MJCF parsed once with xml.etree into a small
kinematic chain (bodies with their pose in the parent, joints, geoms) evaluated with numpy.

The API process never imports MuJoCo (docs/deployment.md, "Workers and queue URLs"); the 3D view still draws the
twin's own geometry from the same file the twin simulates (runtime.dynamics.MJCF_PATH, which the
server's dependency slinger-runtime carries; see :func:`default_mjcf_path`).
tests/test_mjcf_chain.py checks the body and geom poses against MuJoCo's forward kinematics.

Supported MJCF (what the machine's file uses; anything else raises ValueError): nested
``<body pos quat>`` under ``<worldbody>``, ``<joint type="hinge"|"slide" axis pos>`` (``free`` and
``ball`` are not), ``<geom type="box"|"sphere"|"capsule"|"cylinder"|"plane" size pos quat
fromto rgba>``; orientations as quaternions only (so the compiler's angle unit never matters:
joint values are radians and metres, as MuJoCo's qpos).
Frames: MuJoCo's world frame = Slinger's machine frame (z up, metres).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.dynamics import MJCF_PATH

GEOM_TYPES = ("plane", "sphere", "capsule", "cylinder", "box")
_ORIENTATIONS = ("axisangle", "euler", "xyaxes", "zaxis")


def default_mjcf_path() -> Path:
    """The machine's MJCF, runtime.dynamics.MJCF_PATH (that package imports no MuJoCo).

    Raises:
        FileNotFoundError: the file is missing (a broken install).
    """
    if not MJCF_PATH.is_file():
        raise FileNotFoundError(f"no machine MJCF at {MJCF_PATH}")
    return MJCF_PATH


def quat_to_mat(wxyz) -> np.ndarray:
    """(3, 3) rotation matrix of a quaternion (w, x, y, z), normalised first (as MuJoCo does)."""
    w, x, y, z = np.asarray(wxyz, dtype=float) / np.linalg.norm(wxyz)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def mat_to_quat(mat) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a (3, 3) rotation matrix, w >= 0 (Shepperd's method)."""
    m = np.asarray(mat, dtype=float)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.zeros(4)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i], q[1 + j], q[1 + k] = 0.25 * s, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
    w, x, y, z = (float(v) for v in q * (1.0 if q[0] >= 0 else -1.0))
    return w, x, y, z


def axis_rotation(axis, angle_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``angle_rad`` about the unit ``axis`` (Rodrigues' formula)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1.0 - np.cos(angle_rad)) * (k @ k)


def _z_to(vec) -> np.ndarray:
    """Rotation taking +z to the unit vector ``vec`` (MuJoCo's mju_quatZ2Vec convention)."""
    v = np.asarray(vec, dtype=float)
    cos = float(np.clip(v[2], -1.0, 1.0))
    axis = np.cross([0.0, 0.0, 1.0], v)
    n = np.linalg.norm(axis)
    if n < 1e-10:
        return np.eye(3) if cos > 0 else axis_rotation((1.0, 0.0, 0.0), np.pi)
    return axis_rotation(axis / n, np.arctan2(n, cos))


def _floats(el, name: str, default, n: int | None = None) -> np.ndarray:
    text = el.get(name)
    vals = np.asarray(default if text is None else [float(t) for t in text.split()], dtype=float)
    if n is not None and vals.shape != (n,):
        raise ValueError(f"<{el.tag} {name}=...> needs {n} numbers, got {text!r}")
    return vals


@dataclass(frozen=True)
class Joint:
    """A 1-DoF joint of a body: ``kind`` "hinge" (rad) or "slide" (m), unit ``axis`` and
    anchor ``pos`` (3,) in the body frame, its index ``qpos`` in the joint vector."""

    name: str
    kind: str
    axis: np.ndarray
    pos: np.ndarray
    qpos: int


@dataclass(frozen=True)
class Body:
    """A body: its ``parent`` (index, -1 = world), pose in the parent (``pos`` (3,), ``rot``
    (3, 3)) and joints (applied in order after that pose)."""

    name: str
    parent: int
    pos: np.ndarray
    rot: np.ndarray
    joints: tuple[Joint, ...]


@dataclass(frozen=True)
class Geom:
    """A drawn shape: ``kind`` in GEOM_TYPES, MuJoCo's ``size`` (3,) (box half-sizes; radius and
    half-length of capsules and cylinders; sphere radius), ``rgb`` 0-255, its ``body`` and pose
    in the body frame (``pos`` (3,), ``rot`` (3, 3); for capsules and cylinders the z axis runs
    along the shape, from ``fromto``'s end to its start as MuJoCo's compiler has it)."""

    name: str
    kind: str
    size: np.ndarray
    rgb: tuple[int, int, int]
    body: int
    pos: np.ndarray
    rot: np.ndarray


class KinematicChain:
    """Bodies, joints and geoms of an MJCF, evaluated with numpy.

    Args:
        bodies: in tree order (a parent before its children).
        geoms: every geom, planes included.
    """

    def __init__(self, bodies: list[Body], geoms: list[Geom]):
        self.bodies, self.geoms = tuple(bodies), tuple(geoms)
        self.joint_names = tuple(j.name for b in bodies for j in b.joints)

    @classmethod
    def from_mjcf(cls, path: str | Path | None = None) -> KinematicChain:
        """Parse an MJCF file (default :func:`default_mjcf_path`).

        Raises:
            ValueError: unsupported content (see the module docstring) or malformed numbers.
            FileNotFoundError, xml.etree.ElementTree.ParseError: no file / not XML.
        """
        root = ET.parse(path or default_mjcf_path()).getroot()
        world = root.find("worldbody")
        if world is None:
            raise ValueError("MJCF without <worldbody>")
        bodies: list[Body] = []
        geoms: list[Geom] = []
        counter = [0]

        def walk(el, parent: int) -> None:
            for geom in el.findall("geom"):
                geoms.append(cls._geom(geom, parent))
            for child in el.findall("body"):
                joints = []
                for j in child.findall("joint"):
                    kind = j.get("type", "hinge")
                    if kind not in ("hinge", "slide"):
                        raise ValueError(f"joint {j.get('name')!r}: type {kind!r} is not supported")
                    axis = _floats(j, "axis", (0.0, 0.0, 1.0), 3)
                    joints.append(Joint(j.get("name", f"joint{counter[0]}"), kind, axis / np.linalg.norm(axis),
                                        _floats(j, "pos", (0.0, 0.0, 0.0), 3), counter[0]))
                    counter[0] += 1
                bodies.append(Body(child.get("name", f"body{len(bodies)}"), parent, _floats(child, "pos", (0, 0, 0), 3),
                                   cls._rot(child), tuple(joints)))
                walk(child, len(bodies) - 1)

        walk(world, -1)
        return cls(bodies, geoms)

    @staticmethod
    def _rot(el) -> np.ndarray:
        for name in _ORIENTATIONS:
            if el.get(name) is not None:
                raise ValueError(f"<{el.tag} {name}=...> is not supported: give orientations as quat")
        return quat_to_mat(_floats(el, "quat", (1.0, 0.0, 0.0, 0.0), 4))

    @classmethod
    def _geom(cls, el, body: int) -> Geom:
        kind = el.get("type", "sphere")
        if kind not in GEOM_TYPES:
            raise ValueError(f"geom {el.get('name')!r}: type {kind!r} is not supported")
        size = np.zeros(3)
        given = _floats(el, "size", (0.0,))
        size[: len(given)] = given
        pos, rot = _floats(el, "pos", (0, 0, 0), 3), cls._rot(el)
        if el.get("fromto") is not None:
            if kind not in ("capsule", "cylinder"):
                raise ValueError(f"geom {el.get('name')!r}: fromto only for capsules and cylinders")
            ft = _floats(el, "fromto", None, 6)
            d = ft[3:] - ft[:3]
            length = float(np.linalg.norm(d))
            # MuJoCo's compiler points the frame's z axis from "to" back to "from"
            pos, rot, size[1] = 0.5 * (ft[:3] + ft[3:]), _z_to(-d / length), 0.5 * length
        rgba = _floats(el, "rgba", (0.5, 0.5, 0.5, 1.0), 4)
        red, green, blue = (int(255 * c) for c in rgba[:3])
        return Geom(el.get("name", ""), kind, size, (red, green, blue), body, pos, rot)

    def body_poses(self, q) -> tuple[np.ndarray, np.ndarray]:
        """World positions (nbody, 3) and rotations (nbody, 3, 3) at joint values ``q``.

        Args:
            q: (njoint,) joint values in file order (hinge rad, slide m).

        Raises:
            ValueError: ``q`` of another length or not finite.
        """
        q = np.asarray(q, dtype=float).reshape(-1)
        if q.shape != (len(self.joint_names),) or not np.all(np.isfinite(q)):
            raise ValueError(f"need {len(self.joint_names)} finite joint values, got {q.shape}")
        pos, rot = np.zeros((len(self.bodies), 3)), np.zeros((len(self.bodies), 3, 3))
        for i, b in enumerate(self.bodies):
            p0, r0 = (np.zeros(3), np.eye(3)) if b.parent < 0 else (pos[b.parent], rot[b.parent])
            p, r = p0 + r0 @ b.pos, r0 @ b.rot
            for j in b.joints:
                if j.kind == "slide":
                    p = p + r @ (j.axis * q[j.qpos])
                else:  # rotation about the joint's anchor
                    anchor = p + r @ j.pos
                    r = r @ axis_rotation(j.axis, q[j.qpos])
                    p = anchor - r @ j.pos
            pos[i], rot[i] = p, r
        return pos, rot

    def geom_poses(self, q, skip_planes: bool = True) -> list[tuple[np.ndarray, np.ndarray]]:
        """World (position (3,), rotation (3, 3)) of every geom (planes left out by default)."""
        bpos, brot = self.body_poses(q)
        out = []
        for g in self.geoms:
            if skip_planes and g.kind == "plane":
                continue
            p0, r0 = (np.zeros(3), np.eye(3)) if g.body < 0 else (bpos[g.body], brot[g.body])
            out.append((p0 + r0 @ g.pos, r0 @ g.rot))
        return out
