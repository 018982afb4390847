"""The scalar fast paths of runtime.machine.forward_kinematics and clearance_violations (one NumPy
state: the executor's every tick, every preview rollout) against the general array paths
(batches, jax), and the machine's key geometry they must keep."""

from __future__ import annotations

import numpy as np
import pytest

from runtime import machine as m


def _points(p):
    return [np.asarray(getattr(p, k)) for k in ("boom_pivot", "dipper_pivot", "hanger", "gripper_centre", "gripper_centre_vel")]


def test_scalar_path_equals_the_array_path():
    rng = np.random.default_rng(3)
    for _ in range(300):
        q, qd = rng.uniform(-3, 3, 6), rng.uniform(-2, 2, 6)
        fast = m.forward_kinematics(np, q, qd)
        for a, b in zip(_points(fast), _points(m._forward_kinematics_array(np, q, qd))):
            assert a.shape == (3,) and a.dtype == np.float64
            np.testing.assert_allclose(a, b, atol=1e-12)


def test_scalar_path_geometry():
    """Zero pose: the boom pivot at its offset above the chassis, the gripper centre straight
    below the hanger; a cabin turn by 90 deg turns every point about z; the gripper's velocity
    under a pure cabin turn is omega x r."""
    q = np.zeros(6)
    p = m.forward_kinematics(np, q, np.zeros(6))
    h = m.CHASSIS_HEIGHT_M + m.CABIN_OFFSET_M[2]
    assert p.boom_pivot == pytest.approx([m.BOOM_OFFSET_M[0], m.BOOM_OFFSET_M[1], h + m.BOOM_OFFSET_M[2]])
    assert p.gripper_centre == pytest.approx(p.hanger - [0, 0, m.GRIPPER_CENTRE_DROP_M])
    turned = m.forward_kinematics(np, np.r_[np.pi / 2, q[1:]], np.r_[1.0, np.zeros(5)])
    x, y, z = p.gripper_centre
    assert turned.gripper_centre == pytest.approx([-y, x, z])
    assert turned.gripper_centre_vel == pytest.approx(np.cross([0, 0, 1.0], turned.gripper_centre))



def test_clearance_scalar_path_gives_the_array_path_flags():
    """Every flag equal, over states spread across the joint limits, the ground and the cabin
    cylinder (and states right at the limits' 1 mrad tolerance)."""
    rng = np.random.default_rng(4)
    lo, hi = m.JOINT_LOWER.copy(), m.JOINT_UPPER.copy()
    lo[~np.isfinite(lo)], hi[~np.isfinite(hi)] = -3.2, 3.2
    states = [rng.uniform(lo - 0.1, hi + 0.1) for _ in range(3000)]
    for j in (1, 2, 3):
        for edge in (lo[j] + 1e-3, hi[j] - 1e-3):
            q = rng.uniform(lo, hi)
            q[j] = edge
            states.append(q)
    seen = set()
    for q in states:
        pts = m.forward_kinematics(np, q, np.zeros(6))
        fast = m.clearance_violations(np, q, pts)
        slow = tuple(bool(f) for f in m._clearance_violations_array(np, q, pts))
        assert fast == slow and all(type(f) is bool for f in fast)
        seen.add(slow)
    assert len(seen) >= 4  # the states reach several combinations of flags


_Q_CLEAR = np.array([0.0, -0.5, 1.5, 0.5, -1.0, 0.0])  # every active joint well inside its range
_FAR = (6.0, 0.0, 3.0)  # a point clear of ground and cabin


def _chain(gripper=_FAR, hanger=_FAR, dipper_z=4.0):
    """ChainPoints with the points clearance_violations reads set directly (float64, (3,))."""
    return m.ChainPoints(np.zeros(3), np.array([0.0, 0.0, dipper_z]), np.array(hanger, dtype=float),
                         np.array(gripper, dtype=float), np.zeros(3))


def _below(x):
    return float(np.nextafter(x, -np.inf))


def _above(x):
    return float(np.nextafter(x, np.inf))


def _edge_cases():
    """(q, points, expected (ground, cabin, limit)) right at each threshold and one double past it,
    and NaN in each input."""
    g_min, arm_min, r, top = m.GROUND_CLEARANCE_GRIPPER_M, m.GROUND_CLEARANCE_ARM_M, m.CABIN_RADIUS_M, m.CABIN_TOP_M
    none, ground, cabin = (False, False, False), (True, False, False), (False, True, False)
    cases = [
        (_Q_CLEAR, _chain(), none),
        # ground: strictly below the clearance
        (_Q_CLEAR, _chain(gripper=(6.0, 0.0, g_min)), none),
        (_Q_CLEAR, _chain(gripper=(6.0, 0.0, _below(g_min))), ground),
        (_Q_CLEAR, _chain(hanger=(6.0, 0.0, arm_min)), none),
        (_Q_CLEAR, _chain(hanger=(6.0, 0.0, _below(arm_min))), ground),
        (_Q_CLEAR, _chain(dipper_z=arm_min), none),
        (_Q_CLEAR, _chain(dipper_z=_below(arm_min)), ground),
        # cabin: strictly inside the radius and below the top; the gripper or the hanger
        (_Q_CLEAR, _chain(gripper=(r, 0.0, 1.0)), none),
        (_Q_CLEAR, _chain(gripper=(0.0, -r, 1.0)), none),
        (_Q_CLEAR, _chain(gripper=(_below(r), 0.0, 1.0)), cabin),
        (_Q_CLEAR, _chain(gripper=(0.6, -0.8, 1.0)), cabin),
        (_Q_CLEAR, _chain(gripper=(0.0, 0.0, 1.0)), cabin),
        (_Q_CLEAR, _chain(gripper=(1.0, 1.0, top)), none),
        (_Q_CLEAR, _chain(gripper=(1.0, 1.0, _below(top))), cabin),
        (_Q_CLEAR, _chain(hanger=(-1.0, 1.0, 2.0)), cabin),
        (_Q_CLEAR, _chain(hanger=(-1.0, 1.0, top)), none),
        (_Q_CLEAR, _chain(gripper=(1.0, 0.0, 0.2), hanger=(1.0, 0.0, 0.1)), (True, True, False)),
        # NaN: every comparison false, so no flag from the NaN input (NumPy's minimum propagates
        # NaN: a NaN dipper pivot hides a low hanger, as on arrays)
        (_Q_CLEAR, _chain(gripper=(np.nan, 0.0, 1.0)), none),
        (_Q_CLEAR, _chain(gripper=(0.0, 0.0, np.nan)), none),
        (_Q_CLEAR, _chain(hanger=(0.0, np.nan, 0.1)), (True, False, False)),
        (_Q_CLEAR, _chain(hanger=(6.0, 0.0, np.nan), dipper_z=0.1), none),
        (_Q_CLEAR, _chain(hanger=(6.0, 0.0, 0.1), dipper_z=np.nan), none),
    ]
    for j in (1, 2, 3):  # at the limit less its tolerance (the float64 threshold) and one double inside
        for edge, inside in ((m.JOINT_LOWER[j] + 1e-3, _above), (m.JOINT_UPPER[j] - 1e-3, _below)):
            q = _Q_CLEAR.copy()
            q[j] = edge
            cases.append((q, _chain(), (False, False, True)))
            q = q.copy()
            q[j] = inside(edge)
            cases.append((q, _chain(), none))
            q = q.copy()
            q[j] = np.nan
            cases.append((q, _chain(), none))
    for j in range(6):  # a NaN joint through the forward kinematics: NaN points, no flag
        q = _Q_CLEAR.copy()
        q[j] = np.nan
        cases.append((q, m.forward_kinematics(np, q, np.zeros(6)), none))
    return cases


def test_clearance_edge_cases_on_both_paths():
    """At each threshold exactly (ground and cabin strict, joint limits inclusive), one double past
    it, and NaN: the float path's flags, the array path's, and the expected ones agree."""
    for q, pts, want in _edge_cases():
        fast = m.clearance_violations(np, q, pts)
        assert all(type(f) is bool for f in fast)
        assert fast == want, (q, pts, want)
        assert tuple(bool(f) for f in m._clearance_violations_array(np, q, pts)) == want, (q, pts)


def test_clearance_edge_cases_under_jax():
    """The training environment's path (jax.numpy, vmapped, float64 here) flags the edge cases alike."""
    jax = pytest.importorskip("jax")
    jnp = jax.numpy
    cases = _edge_cases()
    with jax.enable_x64(True):
        fields = [jnp.asarray(np.array([getattr(c[1], k) for c in cases])) for k in ("boom_pivot", "dipper_pivot", "hanger", "gripper_centre", "gripper_centre_vel")]
        q = jnp.asarray(np.array([c[0] for c in cases]))
        flags = jax.vmap(lambda q, *p: jnp.stack(m.clearance_violations(jnp, q, m.ChainPoints(*p))))(q, *fields)
        assert [tuple(bool(f) for f in row) for row in np.asarray(flags)] == [c[2] for c in cases]
