"""Random collision-free initial poses with the gripper hanging still (paper Sec. III-B and the
evaluation protocol of Sec. IV-A), written for numpy and jax alike.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

from runtime.machine import clearance_violations, forward_kinematics, hanging_pitch

# Sampling box for boom, dipper, telescope (rad, rad, m): the joint ranges of machine-spec.md
# shrunk by a margin so that a throw does not start against a limit. CHOSEN.
POSE_LOW = np.array([-1.15, 0.8, 0.1])
POSE_HIGH = np.array([0.25, 2.55, 1.7])
MIN_START_HEIGHT_M = 1.2  # gripper centre at least this high at the start. CHOSEN.


def pose_from_uniform(xp: ModuleType, u3, cabin_turn):
    """(6,) joint positions from three uniform [0, 1) numbers and a cabin angle; the gripper
    hangs plumb (pitch cancels boom + dipper) and roll is 0."""
    arm = xp.asarray(POSE_LOW, dtype=u3.dtype) + u3 * xp.asarray(POSE_HIGH - POSE_LOW, dtype=u3.dtype)
    q = xp.concatenate([xp.reshape(cabin_turn, (1,)), arm, xp.zeros(2, dtype=u3.dtype)])
    pitch = hanging_pitch(q)
    return xp.concatenate([q[:4], xp.reshape(pitch, (1,)), q[5:]])


def pose_is_valid(xp: ModuleType, q):
    """True if the pose is clear of ground, cabin and limits and the gripper starts high enough."""
    pts = forward_kinematics(xp, q, xp.zeros_like(q))
    ground, cabin, limit = clearance_violations(xp, q, pts)
    return xp.logical_not(ground | cabin | limit) & (pts.gripper_centre[2] > MIN_START_HEIGHT_M)


def sample_pose(rng: np.random.Generator, cabin_turn: float | None = 0.0, max_tries: int = 1000) -> np.ndarray:
    """A random valid pose (numpy).

    Args:
        rng: random generator.
        cabin_turn: fixed cabin angle (rad), or None for uniform in [-pi, pi).
        max_tries: rejection-sampling budget.

    Raises:
        RuntimeError: if no valid pose was found (should not happen with the default box).
    """
    for _ in range(max_tries):
        yaw = rng.uniform(-np.pi, np.pi) if cabin_turn is None else cabin_turn
        q = pose_from_uniform(np, rng.uniform(size=3), np.asarray(yaw, dtype=float))
        if pose_is_valid(np, q):
            return q
    raise RuntimeError("no collision-free initial pose found")
