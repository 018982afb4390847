"""The scalar fast path of runtime.machine.forward_kinematics (one NumPy state: the executor's
every tick, every preview rollout) against the general array path (batches, jax), and the
machine's key geometry it must keep."""

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

