"""The machine's URDF, exported from the twin's MJCF (``sim_twin/assets/material_handler.xml``)
through MuJoCo's compiled model, so that ROS tools (robot_state_publisher, RViz, Foxglove,
Rerun) draw the same arm the twin simulates.

Mapping: MuJoCo's world body is the root link ``machine`` (Slinger's machine frame: origin on the
turn axis at ground level, z up); every other body is a link of its name; a body's joint becomes
the URDF joint (hinge -> ``revolute`` with the MJCF range, or ``continuous`` when unlimited;
slide -> ``prismatic``) from its parent's link, a body without one a ``fixed`` joint. Joint
origins are the bodies' poses in their parents (MuJoCo ``body_pos`` / ``body_quat``); geoms become
visuals (box, sphere, cylinder; a capsule a cylinder and two spheres; the ground plane is left
out). Masses and inertias are the MJCF's (``body_mass``, ``body_ipos``, ``body_inertia``).

The runtime carries the exported file as package data (``runtime/ros2/material_handler.urdf``,
runtime never imports sim_twin); ``tests/test_ros2_logs.py`` checks it equals a fresh export.
Regenerate with ``python -m sim_twin.twin.urdf > runtime/ros2/material_handler.urdf``.
"""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

ROOT_LINK = "machine"


def _f(values) -> str:
    return " ".join(f"{(0.0 if abs(float(v)) < 1e-12 else float(v)):.6g}" for v in values)


def _rpy(quat_wxyz) -> list[float]:
    """URDF roll, pitch, yaw (fixed-axis x, y, z) of a MuJoCo quaternion (w, x, y, z)."""
    w, x, y, z = quat_wxyz
    with warnings.catch_warnings():  # gimbal lock (pitch +-90 deg) is harmless: roll and yaw add up
        warnings.simplefilter("ignore", UserWarning)
        return list(Rotation.from_quat([x, y, z, w]).as_euler("xyz"))


def _origin(parent: ET.Element, pos, quat_wxyz) -> None:
    ET.SubElement(parent, "origin", xyz=_f(pos), rpy=_f(_rpy(quat_wxyz)))


def _visuals(link: ET.Element, model: mujoco.MjModel, body: int) -> None:
    for g in range(model.ngeom):
        if model.geom_bodyid[g] != body or model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            continue
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}"
        size, pos, quat, rgba = model.geom_size[g], model.geom_pos[g], model.geom_quat[g], model.geom_rgba[g]
        rot = Rotation.from_quat([quat[1], quat[2], quat[3], quat[0]])
        t = int(model.geom_type[g])
        if t == mujoco.mjtGeom.mjGEOM_BOX:
            shapes = [(pos, ("box", {"size": _f(2 * size)}))]
        elif t == mujoco.mjtGeom.mjGEOM_SPHERE:
            shapes = [(pos, ("sphere", {"radius": _f(size[:1])}))]
        elif t in (int(mujoco.mjtGeom.mjGEOM_CYLINDER), int(mujoco.mjtGeom.mjGEOM_CAPSULE)):
            shapes = [(pos, ("cylinder", {"radius": _f(size[:1]), "length": _f([2 * size[1]])}))]
            if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
                ends = [pos + rot.apply([0.0, 0.0, s * size[1]]) for s in (-1.0, 1.0)]
                shapes += [(e, ("sphere", {"radius": _f(size[:1])})) for e in ends]
        else:
            raise ValueError(f"geom {name}: MuJoCo geom type {int(t)} has no URDF visual here")
        for k, (p, (kind, attrs)) in enumerate(shapes):
            vis = ET.SubElement(link, "visual", name=name if k == 0 else f"{name}_end{k}")
            _origin(vis, p, quat)
            ET.SubElement(ET.SubElement(vis, "geometry"), kind, attrib=attrs)
            mat = ET.SubElement(vis, "material", name=f"{name}_colour")
            ET.SubElement(mat, "color", rgba=_f(rgba))


def export_urdf(model: mujoco.MjModel, robot_name: str = "material_handler") -> str:
    """URDF text of ``model`` (see module doc).

    Raises:
        ValueError: a body with more than one joint, a joint whose anchor is not at its body's
            origin, a ball or free joint, or a geom type without a URDF visual.
    """
    robot = ET.Element("robot", name=robot_name)
    ET.SubElement(robot, "link", name=ROOT_LINK)
    for b in range(1, model.nbody):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b)
        parent_id = int(model.body_parentid[b])
        parent = ROOT_LINK if parent_id == 0 else mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, parent_id)
        link = ET.SubElement(robot, "link", name=name)
        if model.body_mass[b] > 0:
            inertial = ET.SubElement(link, "inertial")
            _origin(inertial, model.body_ipos[b], model.body_iquat[b])
            ET.SubElement(inertial, "mass", value=_f([model.body_mass[b]]))
            ixx, iyy, izz = model.body_inertia[b]
            ET.SubElement(inertial, "inertia", ixx=_f([ixx]), ixy="0", ixz="0", iyy=_f([iyy]), iyz="0", izz=_f([izz]))
        _visuals(link, model, b)
        njnt = int(model.body_jntnum[b])
        if njnt > 1:
            raise ValueError(f"body {name}: {njnt} joints; URDF allows one per link")
        if njnt == 0:
            joint = ET.SubElement(robot, "joint", name=f"{parent}_to_{name}", type="fixed")
        else:
            j = int(model.body_jntadr[b])
            jname = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
            if np.any(np.abs(model.jnt_pos[j]) > 1e-9):
                raise ValueError(f"joint {jname}: anchor {model.jnt_pos[j]} is not at its body's origin")
            jt = int(model.jnt_type[j])
            if jt == mujoco.mjtJoint.mjJNT_HINGE:
                kind = "revolute" if model.jnt_limited[j] else "continuous"
            elif jt == mujoco.mjtJoint.mjJNT_SLIDE:
                kind = "prismatic"
            else:
                raise ValueError(f"joint {jname}: MuJoCo joint type {int(jt)} has no URDF equivalent here")
            joint = ET.SubElement(robot, "joint", name=jname, type=kind)
        ET.SubElement(joint, "parent", link=parent)
        ET.SubElement(joint, "child", link=name)
        _origin(joint, model.body_pos[b], model.body_quat[b])
        if njnt:
            ET.SubElement(joint, "axis", xyz=_f(model.jnt_axis[j]))
            if kind != "continuous":
                lo, hi = model.jnt_range[j] if model.jnt_limited[j] else (-1e3, 1e3)
                ET.SubElement(joint, "limit", lower=_f([lo]), upper=_f([hi]), effort="1e6", velocity="10")
    ET.indent(robot)
    header = ("<?xml version=\"1.0\"?>\n<!-- Exported from sim_twin/assets/material_handler.xml by sim_twin.twin.urdf "
              "(python -m sim_twin.twin.urdf); do not edit. -->\n")
    return header + ET.tostring(robot, encoding="unicode") + "\n"


def main() -> None:
    from sim_twin.twin.model import load_model

    print(export_urdf(load_model()), end="")


if __name__ == "__main__":
    main()
