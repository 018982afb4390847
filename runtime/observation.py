"""The policy's observation and action definition (paper Sec. III-D), one definition for the
machine (numpy) and the MJX training environment (jax.numpy).

Observation, 3D (65 values), in this order:

====================================  ==========  ====
joint positions q_1:6, steps k..k-3   rad / m     24
joint velocities qd_1:6, steps k..k-3 rad/s, m/s  24
previous action u_1:5 (k-1)           -           5
gripper centre position r_EE          m           3
gripper centre velocity dr_EE         m/s         3
horizontal error err_2D               m           1
3D error err_3D                       m           1
target position r*                    m           3
gripper opened (0/1)                  -           1
====================================  ==========  ====

2D (56 values): the same without the cabin_turn position, velocity and previous command
(paper Sec. III-D), and with all positions/velocities expressed in the cabin frame (the cabin is
held, so the throw is planar in that frame). 3D observations use the machine frame. The paper's
text says "a history of three time steps" while its table lists k..k-3 (four); we follow the
table. History steps are control steps (12.5 Hz).

The history's length H is a policy's own (``history_steps`` of a training config's ``env``,
default HISTORY_STEPS = 4, the paper's): the two history blocks hold ``nj * H`` values each, so a
2D observation has 16 + 10 H values and a 3D one 17 + 12 H. A manifest's ``observation_layout``
declares it (:func:`history_steps_of_layout`); the runtime keeps as many steps as the loaded policy
reads.

Action (paper eq. 2): normalised joint-velocity references of the mode's active joints in
[-1, 1] (scaled by runtime.machine.ACTIVE_VELOCITY_LIMITS), then the release command; the
gripper opens when the release command exceeds RELEASE_THRESHOLD.
"""

from __future__ import annotations

from types import ModuleType

from runtime.machine import ACTIVE_VELOCITY_LIMITS, forward_kinematics

HISTORY_STEPS = 4  # the paper's k..k-3 (Sec. III-D, its table); a policy may declare its own
MAX_HISTORY_STEPS = 25  # 2 s of control steps: the most a manifest may declare
CONTROL_PERIOD_S = 0.08  # 12.5 Hz policy (paper Sec. III-E)
PHYSICS_PERIOD_S = 0.01  # 100 Hz simulation and low-level control
SUBSTEPS = 8  # physics steps per control step
RELEASE_THRESHOLD = 0.9  # paper Sec. III-D


def num_actions(mode: str) -> int:
    """3 velocity references + release in 2D, 4 + release in 3D."""
    return {"2d": 4, "3d": 5}[mode]


def _history_joints(mode: str) -> int:
    """Joints in each history step: 5 in 2D (no cabin_turn), 6 in 3D. KeyError for another mode."""
    return {"2d": 5, "3d": 6}[mode]


def observation_layout(mode: str, history_steps: int = HISTORY_STEPS) -> list[tuple[str, int]]:
    """(name, size) blocks of the observation vector in order; sizes sum to 56 (2D) / 65 (3D) with
    the default four history steps (16 + 10 H in 2D, 17 + 12 H in 3D).

    Raises:
        KeyError: for an unknown mode.
        ValueError: ``history_steps`` outside 1..MAX_HISTORY_STEPS.
    """
    if not 1 <= history_steps <= MAX_HISTORY_STEPS:
        raise ValueError(f"history_steps must be 1..{MAX_HISTORY_STEPS}, got {history_steps}")
    nj = _history_joints(mode)
    return [
        ("joint_pos_history", nj * history_steps),
        ("joint_vel_history", nj * history_steps),
        ("previous_action", num_actions(mode)),
        ("gripper_centre_pos", 3),
        ("gripper_centre_vel", 3),
        ("error_2d", 1),
        ("error_3d", 1),
        ("target_pos", 3),
        ("gripper_opened", 1),
    ]


def observation_size(mode: str, history_steps: int = HISTORY_STEPS) -> int:
    """Length of the observation vector: sum of :func:`observation_layout`'s block sizes."""
    return sum(n for _, n in observation_layout(mode, history_steps))


def history_steps_of_layout(mode: str, layout) -> int:
    """The history length H a manifest's ``observation_layout`` ([[block, size], ...]) declares:
    its ``joint_pos_history`` size over the mode's history joints, checked by rebuilding the whole
    layout for that H.

    Raises:
        ValueError: the layout is not :func:`observation_layout` (mode, H) for any H in
            1..MAX_HISTORY_STEPS (its message names what differs).
        KeyError: for an unknown mode.
    """
    nj = _history_joints(mode)
    try:
        size = int(dict((str(b), n) for b, n in layout)["joint_pos_history"])
    except (TypeError, ValueError, KeyError) as e:
        raise ValueError(f"observation_layout has no joint_pos_history block: {layout!r}") from e
    steps, rest = divmod(size, nj)
    if rest or not 1 <= steps <= MAX_HISTORY_STEPS:
        raise ValueError(f"joint_pos_history of {size} values is not 1..{MAX_HISTORY_STEPS} steps of {nj} joints")
    want = [list(b) for b in observation_layout(mode, steps)]
    if [list(b) for b in layout] != want:
        raise ValueError(f"observation_layout {layout!r} is not this runtime's for {steps} history steps ({want!r})")
    return steps


def _yaw_inverse(xp: ModuleType, v, yaw):
    """Rows of v (n, 3) turned by minus ``yaw`` about z (each row's x, y as
    ``c * x + s * y``, ``-s * x + c * y``; z kept)."""
    c, s = xp.cos(yaw), xp.sin(yaw)
    return xp.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]], axis=-1)


def build_observation(xp: ModuleType, mode: str, q_hist, qd_hist, prev_action, target_m, opened):
    """Assemble one observation vector.

    Args:
        xp: array module (numpy or jax.numpy).
        mode: "2d" or "3d".
        q_hist: (H, 6) joint positions at control steps k, k-1, ..., k-H+1 (newest first); H is
            the policy's history length (HISTORY_STEPS = 4 by default).
        qd_hist: (H, 6) joint velocities, same steps.
        prev_action: (num_actions(mode),) the previous policy action, as the policy output it
            (before clipping).
        target_m: (3,) target in the machine frame, m.
        opened: scalar 0/1, the gripper is open (payload free).

    Returns:
        (observation_size(mode, H),) vector, dtype of ``q_hist``.
    """
    dtype = q_hist.dtype
    pts = forward_kinematics(xp, q_hist[0], qd_hist[0])
    ee, ee_vel, target = pts.gripper_centre, pts.gripper_centre_vel, xp.asarray(target_m, dtype=dtype)
    if mode == "2d":
        # the three vectors turned in one (3, 3) array: per element the same arithmetic as one by one
        turned = _yaw_inverse(xp, xp.stack([ee, ee_vel, target]), q_hist[0][0])
        ee, ee_vel, target = turned[0], turned[1], turned[2]
        q_part, qd_part = q_hist[:, 1:], qd_hist[:, 1:]
    else:
        q_part, qd_part = q_hist, qd_hist
    diff = target - ee
    err_2d = xp.sqrt(diff[0] ** 2 + diff[1] ** 2)
    err_3d = xp.sqrt(err_2d**2 + diff[2] ** 2)
    return xp.concatenate(
        [
            xp.reshape(q_part, (-1,)),
            xp.reshape(qd_part, (-1,)),
            xp.asarray(prev_action, dtype=dtype),
            ee,
            ee_vel,
            xp.reshape(err_2d, (1,)),
            xp.reshape(err_3d, (1,)),
            target,
            xp.reshape(xp.asarray(opened, dtype=dtype), (1,)),
        ]
    )


def decode_action(xp: ModuleType, mode: str, action):
    """Turn a policy action into joint-velocity references and the release flag.

    Args:
        xp: array module.
        mode: "2d" or "3d".
        action: (num_actions(mode),) raw policy output.

    Returns:
        (qd_ref, release): qd_ref (4,) references of the active joints in ACTIVE_JOINTS order,
        rad/s and m/s, the cabin's being 0 in 2D; release is True when the last entry exceeds
        RELEASE_THRESHOLD.
    """
    dtype = action.dtype
    vel = xp.clip(action[:-1], -1.0, 1.0)
    if mode == "2d":
        vel = xp.concatenate([xp.zeros(1, dtype=dtype), vel])
    qd_ref = vel * xp.asarray(ACTIVE_VELOCITY_LIMITS, dtype=dtype)
    return qd_ref, action[-1] > RELEASE_THRESHOLD
