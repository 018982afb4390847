"""Loading the machine's MJCF (runtime.dynamics.MJCF_PATH) with MuJoCo, checking it against
runtime.machine, and the passive joints' effective inertia. Needs MuJoCo (the runtime wheel's
``release-check`` extra)."""

from __future__ import annotations

import copy
from functools import lru_cache
from pathlib import Path

import mujoco
import numpy as np

from runtime.dynamics import MJCF_PATH
from runtime.machine import ACTIVE_JOINTS, JOINT_NAMES, hanging_pitch


def load_model(path: str | Path = MJCF_PATH) -> mujoco.MjModel:
    """Load the MJCF and check that its joints and actuators are in Slinger's order.

    Raises:
        ValueError: if the joint or actuator order differs from runtime.machine.
    """
    model = mujoco.MjModel.from_xml_path(str(path))
    joints = tuple(model.joint(i).name for i in range(model.njnt))
    if joints != JOINT_NAMES:
        raise ValueError(f"MJCF joints {joints} differ from {JOINT_NAMES}")
    acts = tuple(model.actuator(i).name for i in range(model.nu))
    if acts != ACTIVE_JOINTS:
        raise ValueError(f"MJCF actuators {acts} differ from {ACTIVE_JOINTS}")
    return model


@lru_cache(maxsize=4)
def _parsed_model(path: str) -> mujoco.MjModel:
    return load_model(path)


def fresh_model(path: str | Path = MJCF_PATH) -> mujoco.MjModel:
    """A model of the caller's own, equal to what :func:`load_model` returns for ``path``: a copy
    (``copy.copy``, MuJoCo's mj_copyModel) of the one parsed and checked once per process. About
    0.3 ms against 1.3 ms for parsing the MJCF again, which a preview paid once per rollout.
    The caller may change the copy (reality-profile effects do); the cached model is never handed out.

    Raises:
        ValueError: as :func:`load_model`.
    """
    return copy.copy(_parsed_model(str(path)))


def passive_inertia_of(model: mujoco.MjModel, data: mujoco.MjData | None = None) -> np.ndarray:
    """(2,) effective inertia (kg m^2) of gripper_pitch and gripper_roll of ``model``: the diagonal
    of MuJoCo's joint-space mass matrix with the gripper hanging plumb at a reference arm pose.
    Used to turn the paper's friction accelerations into forces (runtime.dynamics.friction).
    ``data``: an MjData of ``model`` to compute it in (its state is overwritten: the caller resets
    it, mj_resetData), saving the allocation of one (~0.6 ms); None makes one."""
    if data is None:
        data = mujoco.MjData(model)
    q = np.array([0.0, -0.6, 1.5, 0.9, 0.0, 0.0])
    q[4] = hanging_pitch(q)
    data.qpos[:] = q
    mujoco.mj_forward(model, data)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, full)
    return np.diag(full)[4:6].copy()


@lru_cache(maxsize=4)
def passive_inertia(path: str | Path = MJCF_PATH) -> np.ndarray:
    """passive_inertia_of the MJCF at ``path`` (cached)."""
    return passive_inertia_of(load_model(path))
