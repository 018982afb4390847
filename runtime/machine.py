"""The material handler's kinematic description, shared by the runtime and the twin.

Everything here is written against an array module ``xp`` (``numpy`` on the machine,
``jax.numpy`` in the MJX training environment) so that the very same arithmetic runs in both
places. Functions take one machine's state (no batch axis); the training environment maps them
over its environments with ``jax.vmap``.

Frames and units follow docs/architecture.md: machine frame with its origin on the
cabin-turn axis at ground level, x forward when ``cabin_turn = 0``, z up; metres, radians.

Sources: joint offsets, ranges and masses from the HEAP URDF parameters quoted in
``shared/reference/machine-spec.md`` (leggedrobotics/rsl_heap, mm_parameters.urdf.xacro). The
same numbers are written in ``runtime/dynamics/assets/material_handler.xml``; ``tests/test_machine.py``
checks that this module's forward kinematics agrees with MuJoCo's on that file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np

from runtime import float_xp

JOINT_NAMES: tuple[str, ...] = (
    "cabin_turn",
    "boom",
    "dipper",
    "telescope",
    "gripper_pitch",
    "gripper_roll",
)
"""Joints in chain order; every joint vector in Slinger uses this order."""

ACTIVE_JOINTS: tuple[str, ...] = JOINT_NAMES[:4]
PASSIVE_JOINTS: tuple[str, ...] = JOINT_NAMES[4:]
NUM_JOINTS = 6
NUM_ACTIVE = 4

MODE_ACTIVE_JOINTS: dict[str, tuple[str, ...]] = {
    "2d": ("boom", "dipper", "telescope"),
    "3d": ("cabin_turn", "boom", "dipper", "telescope"),
}
"""Active joints each throwing mode drives (paper Sec. III: the 2D policy holds the cabin)."""

# --- geometry (metres), machine-spec.md table "Kinematic chain" -------------------------------
CHASSIS_HEIGHT_M = 1.5  # base above ground in the URDF (prismatic helper joint at z = 1.5)
CABIN_OFFSET_M = (0.0, 0.0, 0.516)  # base -> cabin
BOOM_OFFSET_M = (0.703, -0.292, 0.5494)  # cabin -> boom pivot
DIPPER_OFFSET_M = (2.84, 0.0, 0.0)  # boom -> dipper pivot
TELESCOPE_OFFSET_M = (0.0, 0.0, 0.369)  # dipper -> telescope slide origin
HANGER_OFFSET_M = (2.0266, 0.0, 0.0)  # telescope -> gripper_pitch axis
GRIPPER_CENTRE_DROP_M = 1.0  # gripper centre below the pitch/roll axes (spec: 0.8-1.2 m, chosen)

# --- joint limits, machine-spec.md; cabin_turn and the passive joints are unlimited ----------
JOINT_LOWER = np.array([-np.inf, -1.34, 0.58, 0.0, -np.inf, -np.inf])
JOINT_UPPER = np.array([np.inf, 0.44, 2.78, 1.8, np.inf, np.inf])

# Joint speed limits of the active joints (rad/s, rad/s, rad/s, m/s). machine-spec.md gives
# orders of magnitude from the cylinder speeds and lever geometry: boom 0.3-0.5, dipper ~0.6,
# telescope 0.75 m/s, cabin 1.0 rad/s. We take boom 0.45 (middle of the range).
ACTIVE_VELOCITY_LIMITS = np.array([1.0, 0.45, 0.6, 0.75])

# --- clearance zone used to end a throw as failed (simplified collision geometry) -----------
GROUND_CLEARANCE_GRIPPER_M = 0.5  # gripper jaws reach ~0.5 m below the gripper centre
GROUND_CLEARANCE_ARM_M = 0.3  # half-thickness of the dipper/telescope section
CABIN_RADIUS_M = 2.0  # cylinder around the turn axis the gripper must stay out of ...
CABIN_TOP_M = 3.6  # ... below this height (chassis 1.5 + cabin ~2.1)


@dataclass(frozen=True)
class ChainPoints:
    """Key points of the chain for one state, machine frame, metres.

    Attributes:
        boom_pivot: (3,) boom joint origin.
        dipper_pivot: (3,) dipper joint origin (boom tip).
        hanger: (3,) gripper_pitch axis origin (telescope tip).
        gripper_centre: (3,) centre of the gripper, where the payload sits.
        gripper_centre_vel: (3,) its velocity, m/s.
    """

    boom_pivot: Any
    dipper_pivot: Any
    hanger: Any
    gripper_centre: Any
    gripper_centre_vel: Any


def _rot(xp: ModuleType, a, axis: str):
    """Rotation matrix (3, 3) by angle a (rad) about x, y or z. NumPy scalars take a fast path
    (one array from a tuple instead of nested stacks); other modules (jax) stack."""
    c, s = xp.cos(a), xp.sin(a)
    if xp is np and np.ndim(a) == 0:
        c, s = float(c), float(s)
        rows = {"x": ((1.0, 0.0, 0.0), (0.0, c, -s), (0.0, s, c)),
                "y": ((c, 0.0, s), (0.0, 1.0, 0.0), (-s, 0.0, c)),
                "z": ((c, -s, 0.0), (s, c, 0.0), (0.0, 0.0, 1.0))}[axis]
        return np.array(rows, dtype=np.result_type(a, np.float64))
    z, o = xp.zeros_like(a), xp.ones_like(a)
    rows = {"x": ((o, z, z), (z, c, -s), (z, s, c)), "y": ((c, z, s), (z, o, z), (-s, z, c)),
            "z": ((c, -s, z), (s, c, z), (z, z, o))}[axis]
    return xp.stack([xp.stack(list(r)) for r in rows])


def _rot_z(xp: ModuleType, a):
    return _rot(xp, a, "z")


def _rot_y(xp: ModuleType, a):
    return _rot(xp, a, "y")


def _rot_x(xp: ModuleType, a):
    return _rot(xp, a, "x")


def _cross(xp: ModuleType, a, b):
    """a x b of two (3,) vectors; written out because numpy's general cross costs ~30 us a call
    (the executor runs forward kinematics every 10 ms tick, previews hundreds of times)."""
    return xp.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def forward_kinematics(xp: ModuleType, q, qd) -> ChainPoints:
    """Positions of the chain's key points and the gripper centre's velocity.

    Args:
        xp: array module (``numpy`` or ``jax.numpy``).
        q: (6,) joint positions in JOINT_NAMES order, rad and m (telescope).
        qd: (6,) joint velocities, rad/s and m/s.

    Returns:
        ChainPoints in the machine frame. The velocity is J(q) @ qd with the geometric Jacobian
        columns a_i x (p - o_i) for revolute and a_i for prismatic joints.

    A single NumPy state (the executor every 10 ms tick, every preview rollout) takes
    :func:`_forward_kinematics_scalar` in plain floats (~8x faster), batches and jax the general
    array path; the two are deliberately different derivations (the planar closed form in the
    cabin frame against rotation matrices and Jacobian columns), so tests/test_machine_fk.py's
    agreement to 1e-12 is an independent check of both, not a copy of one.
    """
    if xp is np and np.ndim(q) == 1 and np.ndim(qd) == 1:
        return _forward_kinematics_scalar(q, qd)
    return _forward_kinematics_array(xp, q, qd)


def _floats6(v) -> list[float]:
    """The first six entries of ``v`` as Python floats (ndarray.tolist for a float array: the same
    values as float() of each, without a generator)."""
    if isinstance(v, np.ndarray) and v.dtype.kind == "f":
        return v[:6].tolist()
    return [float(x) for x in v[:6]]


def _forward_kinematics_scalar(q, qd) -> ChainPoints:
    """forward_kinematics of one NumPy state (6,), (6,) in floats. The boom, dipper and
    gripper-pitch axes are parallel (cabin y), so the arm is planar in the cabin frame: the
    chain is built there (x forward, y left, z up) and turned by the cabin angle at the end."""
    q0, q1, q2, q3, q4, q5 = _floats6(q)
    d0, d1, d2, d3, d4, d5 = _floats6(qd)
    a12, a124 = q1 + q2, q1 + q2 + q4
    s1, c1 = math.sin(q1), math.cos(q1)
    s12, c12 = math.sin(a12), math.cos(a12)
    s124, c124 = math.sin(a124), math.cos(a124)
    s5, c5 = math.sin(q5), math.cos(q5)
    h = CHASSIS_HEIGHT_M + CABIN_OFFSET_M[2]
    boom = (BOOM_OFFSET_M[0], BOOM_OFFSET_M[1], h + BOOM_OFFSET_M[2])
    dx = DIPPER_OFFSET_M[0]
    dip = (boom[0] + dx * c1, boom[1], boom[2] - dx * s1)
    tz, length = TELESCOPE_OFFSET_M[2], q3 + HANGER_OFFSET_M[0]
    hang = (dip[0] + tz * s12 + length * c12, dip[1], dip[2] + tz * c12 - length * s12)
    g = GRIPPER_CENTRE_DROP_M
    pc = (hang[0] - g * c5 * s124, hang[1] + g * s5, hang[2] - g * c5 * c124)
    # J qd in the cabin frame: cabin turn z x (p - o_turn); boom, dipper, pitch y x (p - o);
    # telescope along the dipper's x; roll along the pitched gripper's x
    vx = -pc[1] * d0
    vy = pc[0] * d0
    vz = 0.0
    for origin, rate in ((boom, d1), (dip, d2), (hang, d4)):  # y x r = (r_z, 0, -r_x)
        vx += (pc[2] - origin[2]) * rate
        vz -= (pc[0] - origin[0]) * rate
    vx += c12 * d3
    vz -= s12 * d3
    rx, ry, rz = pc[0] - hang[0], pc[1] - hang[1], pc[2] - hang[2]  # (c124, 0, -s124) x r
    vx += (s124 * ry) * d5
    vy += (-s124 * rx - c124 * rz) * d5
    vz += (c124 * ry) * d5
    c0, s0 = math.cos(q0), math.sin(q0)
    dtype: Any
    if isinstance(q, np.ndarray) and q.dtype == np.float64:  # the executor's state: no type promotion to work out
        dtype = np.float64
    else:
        dtype = np.result_type(q, np.float64) if np.asarray(q).dtype.kind == "f" else np.float64

    # the five points turned into the machine frame in one (5, 3) array (one NumPy call); its rows
    # do not overlap, so each field is an array of its own as far as a caller can tell
    rows = np.array([(c0 * p[0] - s0 * p[1], s0 * p[0] + c0 * p[1], p[2]) for p in (boom, dip, hang, pc, (vx, vy, vz))],
                    dtype=dtype)
    return ChainPoints(rows[0], rows[1], rows[2], rows[3], rows[4])


def _forward_kinematics_array(xp: ModuleType, q, qd) -> ChainPoints:
    """forward_kinematics on arrays of any module (jax included): rotation matrices and the
    geometric Jacobian's columns."""
    dtype = q.dtype
    e_x = xp.asarray([1.0, 0.0, 0.0], dtype=dtype)
    e_y = xp.asarray([0.0, 1.0, 0.0], dtype=dtype)
    e_z = xp.asarray([0.0, 0.0, 1.0], dtype=dtype)

    def vec(t):
        return xp.asarray(t, dtype=dtype)

    o_turn = vec((0.0, 0.0, CHASSIS_HEIGHT_M + CABIN_OFFSET_M[2]))
    r_cabin = _rot_z(xp, q[0])
    o_boom = o_turn + r_cabin @ vec(BOOM_OFFSET_M)
    r_boom = r_cabin @ _rot_y(xp, q[1])
    o_dipper = o_boom + r_boom @ vec(DIPPER_OFFSET_M)
    r_dipper = r_boom @ _rot_y(xp, q[2])
    o_tele = o_dipper + r_dipper @ vec(TELESCOPE_OFFSET_M)
    o_hanger = o_tele + r_dipper @ (e_x * (q[3] + HANGER_OFFSET_M[0]))
    r_pitch = r_dipper @ _rot_y(xp, q[4])
    r_grip = r_pitch @ _rot_x(xp, q[5])
    p_c = o_hanger + r_grip @ vec((0.0, 0.0, -GRIPPER_CENTRE_DROP_M))

    axes = (e_z, r_cabin @ e_y, r_boom @ e_y, r_dipper @ e_x, r_dipper @ e_y, r_pitch @ e_x)
    origins = (o_turn, o_boom, o_dipper, None, o_hanger, o_hanger)
    vel = xp.zeros(3, dtype=dtype)
    for i, (axis, origin) in enumerate(zip(axes, origins)):
        col = axis if origin is None else _cross(xp, axis, p_c - origin)
        vel = vel + col * qd[i]
    return ChainPoints(o_boom, o_dipper, o_hanger, p_c, vel)


def hanging_pitch(q_active) -> float:
    """gripper_pitch angle (rad) at which the gripper hangs plumb for the given arm pose.

    Args:
        q_active: (4,) or (6,) joint positions; only boom and dipper are read.

    The boom and dipper both turn about y, so the telescope's pitch is boom + dipper and the
    gripper hangs plumb when gripper_pitch cancels it.
    """
    return -(q_active[1] + q_active[2])


def clearance_violations(xp: ModuleType, q, points: ChainPoints):
    """Flags for the ways a state ends a throw as failed.

    Args:
        xp: array module (``numpy`` or ``jax.numpy``).
        q: (6,) joint positions in JOINT_NAMES order, rad and m.
        points: forward_kinematics(xp, q, qd) of the same state (machine frame, m).

    Returns:
        (ground, cabin, joint_limit): three booleans. Ground: gripper centre below
        GROUND_CLEARANCE_GRIPPER_M (0.5 m, the jaws' reach) or the lower of hanger and dipper pivot
        below GROUND_CLEARANCE_ARM_M (0.3 m, the arm's half-thickness); cabin: gripper centre or
        hanger (telescope tip) strictly inside the cylinder of CABIN_RADIUS_M about the turn axis
        and below CABIN_TOP_M; joint_limit: boom, dipper or telescope at or beyond its range less
        1 mrad / 1 mm (``<=`` / ``>=``). A NaN coordinate or joint raises no flag (every
        comparison with NaN is false; the executor rejects non-finite states before this).
        Python bools for a float64 NumPy state, else the module's 0-d booleans (numpy.bool_,
        jax arrays). Geometry sources: the constants above (machine-spec.md).

    The flags are :func:`_clearance_flags`, written once against ``xp``: jax (vmapped over the
    training environments) and float32 states run it on arrays, a float64 NumPy state (the
    executor every 10 ms tick, every preview step) on its Python floats with runtime.float_xp
    (the same comparisons on the same doubles, about a quarter of the array path's time;
    tests/test_machine_fk.py compares the two, edge cases included).
    """
    if (xp is np and isinstance(q, np.ndarray) and q.ndim == 1 and q.dtype == np.float64
            and points.gripper_centre.dtype == np.float64):
        return _clearance_flags(float_xp, points.gripper_centre.tolist(), points.hanger.tolist(), points.dipper_pivot.item(2),
                                q.tolist(), _LIMIT_LO, _LIMIT_HI)
    return _clearance_violations_array(xp, q, points)


def _clearance_violations_array(xp: ModuleType, q, points: ChainPoints):
    """:func:`_clearance_flags` on arrays of any module, the thresholds in q's dtype."""
    lo = xp.asarray(JOINT_LOWER[1:4], dtype=q.dtype) + 1e-3
    hi = xp.asarray(JOINT_UPPER[1:4], dtype=q.dtype) - 1e-3
    return _clearance_flags(xp, points.gripper_centre, points.hanger, points.dipper_pivot[2], q, lo, hi)


_LIMIT_LO = (JOINT_LOWER[1:4] + 1e-3).tolist()  # the float64 thresholds, as the array path's
_LIMIT_HI = (JOINT_UPPER[1:4] - 1e-3).tolist()


def _clearance_flags(xp, g, h, dipper_z, q, lo, hi):
    """(ground, cabin, joint_limit) of :func:`clearance_violations`, elementwise against ``xp``.

    Args: g, h: gripper centre and hanger (3,), machine frame, m; dipper_z: the dipper pivot's
    height, m; q: (6,) joint positions (boom, dipper, telescope are read); lo, hi: (3,) their
    thresholds (the limits with their tolerance). Lists of floats with ``xp`` runtime.float_xp,
    arrays with numpy / jax.numpy; read entry by entry, combined with ``|`` and ``&`` (no short
    circuit), so both give the same booleans for the same doubles.
    """
    ground = (g[2] < GROUND_CLEARANCE_GRIPPER_M) | (xp.minimum(h[2], dipper_z) < GROUND_CLEARANCE_ARM_M)
    cabin = _in_cabin(xp, g) | _in_cabin(xp, h)
    limit = ((q[1] <= lo[0]) | (q[2] <= lo[1]) | (q[3] <= lo[2])
             | (q[1] >= hi[0]) | (q[2] >= hi[1]) | (q[3] >= hi[2]))
    return ground, cabin, limit


def _in_cabin(xp, p):
    """Point p (3,) strictly inside the cabin cylinder: horizontal distance from the turn axis
    below CABIN_RADIUS_M and height below CABIN_TOP_M (``x * x``: NumPy's ``x ** 2``, exact square
    rounded once)."""
    return (xp.sqrt(p[0] * p[0] + p[1] * p[1]) < CABIN_RADIUS_M) & (p[2] < CABIN_TOP_M)
