"""Payload effects: where the payload sits in the gripper, and aerodynamic drag in flight.

Also the payload kinematics both the simulated machine and the replay use: the grasp point of a
batch of states (:func:`grasp_point`) and numerical flight integration (:func:`integrate_flight`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from runtime.machine import (
    BOOM_OFFSET_M,
    CABIN_OFFSET_M,
    CHASSIS_HEIGHT_M,
    DIPPER_OFFSET_M,
    GRIPPER_CENTRE_DROP_M,
    HANGER_OFFSET_M,
    TELESCOPE_OFFSET_M,
)
from sim_twin.twin.effects.base import Effect, Param
from sim_twin.twin.model import PAYLOAD_MASS_KG, PAYLOAD_RADIUS_M
from sim_twin.twin.physics import GRAVITY_MPS2

AIR_DENSITY_KG_M3 = 1.225  # ISA sea level
FLIGHT_DT_S = 0.005  # RK4 step; drag varies slowly, error < 1 mm over a 2 s flight


def gripper_frame_point(xp, q, local):
    """Machine-frame position (..., 3) of a point given in the gripper frame (origin on the
    pitch/roll axes; x along the jaws, z up when the gripper hangs plumb), for joint positions
    q (..., 6) in JOINT_NAMES order (rad, m). ``xp`` is ``numpy`` or ``jax.numpy``; ``local`` (3,)
    in m. Same chain as runtime.machine.forward_kinematics (tests/test_payload_effects.py)."""
    c0, s0 = xp.cos(q[..., 0]), xp.sin(q[..., 0])

    def rz(v):
        return xp.stack([c0 * v[..., 0] - s0 * v[..., 1], s0 * v[..., 0] + c0 * v[..., 1], v[..., 2]], axis=-1)

    def ry(a, v):
        c, s = xp.cos(a), xp.sin(a)
        return xp.stack([c * v[..., 0] + s * v[..., 2], v[..., 1], -s * v[..., 0] + c * v[..., 2]], axis=-1)

    def rx(a, v):
        c, s = xp.cos(a), xp.sin(a)
        return xp.stack([v[..., 0], c * v[..., 1] - s * v[..., 2], s * v[..., 1] + c * v[..., 2]], axis=-1)

    z = xp.zeros(q.shape[:-1] + (3,), dtype=q.dtype)
    o = z + xp.asarray([0.0, 0.0, CHASSIS_HEIGHT_M + CABIN_OFFSET_M[2]], dtype=q.dtype)
    o = o + rz(z + xp.asarray(BOOM_OFFSET_M, dtype=q.dtype))
    o = o + rz(ry(q[..., 1], z + xp.asarray(DIPPER_OFFSET_M, dtype=q.dtype)))
    a12 = q[..., 1] + q[..., 2]
    o = o + rz(ry(a12, z + xp.asarray(TELESCOPE_OFFSET_M, dtype=q.dtype)))
    tele = xp.stack([q[..., 3] + HANGER_OFFSET_M[0], z[..., 1], z[..., 2]], axis=-1)
    o = o + rz(ry(a12, tele))
    return o + rz(ry(a12 + q[..., 4], rx(q[..., 5], z + local)))


GRIPPER_CENTRE_LOCAL_M = (0.0, 0.0, -GRIPPER_CENTRE_DROP_M)
"""The gripper centre in the gripper frame, m (runtime.machine's gripper-centre drop below the pitch axis)."""


def grasp_point(q, qd, offset_m=None) -> tuple[np.ndarray, np.ndarray]:
    """Position and velocity (..., 3) of the payload held at ``offset_m`` (3,) from the gripper
    centre, in the gripper frame (None: the centre). Velocity by central differences along qd."""
    q, qd = np.asarray(q, dtype=float), np.asarray(qd, dtype=float)
    local = np.array(GRIPPER_CENTRE_LOCAL_M)
    if offset_m is not None:
        local = local + np.asarray(offset_m, dtype=float)
    h = 1e-6
    p = gripper_frame_point(np, q, local)
    v = (gripper_frame_point(np, q + h * qd, local) - gripper_frame_point(np, q - h * qd, local)) / (2 * h)
    return p, v


def integrate_flight(p0, v0, accel: Callable | None, ground_z: float = PAYLOAD_RADIUS_M, dt_s: float = FLIGHT_DT_S, max_s: float = 10.0):
    """Payload flight under gravity plus ``accel(pos, vel)`` (..., 3), RK4 at ``dt_s``.

    Args:
        p0, v0: (..., 3) release position (m) and velocity (m/s).
        accel: extra acceleration function, or None (gravity only).
        ground_z: height of the payload centre at impact, m.

    Returns:
        (t (S,), pos (S, ..., 3), vel (S, ..., 3), impact_t (...), impact_pos (..., 3)): the
        trajectory from release (rows after a batch member landed repeat its impact state) and
        the impact time and position (z = 0, linear interpolation within the landing step).
    """
    p, v = np.array(p0, dtype=float), np.array(v0, dtype=float)
    g = np.array([0.0, 0.0, -GRAVITY_MPS2])

    def f(pp, vv):
        a = g if accel is None else g + accel(pp, vv)
        return vv, a

    # every step makes new arrays (nothing is changed in place), so the trajectory keeps them as
    # they are; the landing's and the landed members' np.where run only when they change something
    # (with all-False masks they return their else values: the same numbers, fewer NumPy calls)
    ts, ps, vs = [0.0], [p.copy()], [v.copy()]
    landed = p[..., 2] <= ground_z
    t_hit = np.where(landed, 0.0, np.nan)
    hit = np.where(landed[..., None], p, np.nan)
    t = 0.0
    while not landed.all() and t < max_s:
        k1p, k1v = f(p, v)
        k2p, k2v = f(p + 0.5 * dt_s * k1p, v + 0.5 * dt_s * k1v)
        k3p, k3v = f(p + 0.5 * dt_s * k2p, v + 0.5 * dt_s * k2v)
        k4p, k4v = f(p + dt_s * k3p, v + dt_s * k3v)
        pn = p + dt_s / 6 * (k1p + 2 * k2p + 2 * k3p + k4p)
        vn = v + dt_s / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        new = ~landed & (pn[..., 2] <= ground_z)
        if new.any():
            frac = np.where(new, (p[..., 2] - ground_z) / np.maximum(p[..., 2] - pn[..., 2], 1e-12), 0.0)
            t_hit = np.where(new, t + frac * dt_s, t_hit)
            hit = np.where(new[..., None], p + frac[..., None] * (pn - p), hit)
        if landed.any():
            pn = np.where(landed[..., None], p, pn)
            vn = np.where(landed[..., None], 0.0, vn)
        landed = landed | new
        p, v, t = pn, vn, t + dt_s
        ts.append(t)
        ps.append(p)
        vs.append(v)
    hit = np.array(hit)
    hit[..., 2] = 0.0
    return np.array(ts), np.stack(ps), np.stack(vs), t_hit, hit


class PayloadDrag(Effect):
    """Quadratic aerodynamic drag on the payload in flight: a = -rho Cd A |v| v / (2 m), with the
    model payload (size 7 basketball: 0.12 m radius, 0.6 kg). The nominal twin flies drag-free."""

    name = "payload_drag"
    summary = "quadratic aerodynamic drag of the payload in flight"
    stage = "flight"
    params = (Param("drag_coefficient", "-", 0.0, 0.0, 1.5, "drag coefficient Cd on the frontal area pi r^2",
                    "sphere Cd ~0.47 (subcritical Re), basketball 0.5-0.55 (wind-tunnel literature); nominal twin 0"),)

    @property
    def k_per_m(self) -> float:
        """rho Cd A / (2 m), 1/m."""
        area = np.pi * PAYLOAD_RADIUS_M**2
        return AIR_DENSITY_KG_M3 * self.drag_coefficient * area / (2.0 * PAYLOAD_MASS_KG)

    def flight_accel(self, pos_m, vel_mps):
        # np.linalg.norm's own arithmetic for a real array, without its argument handling
        # (called four times per RK4 step of every Monte Carlo flight)
        speed = np.sqrt(np.add.reduce(vel_mps * vel_mps, axis=-1, keepdims=True))
        return -self.k_per_m * speed * vel_mps


class GraspOffset(Effect):
    """The payload sits away from the gripper centre: ``forward_m`` along the gripper's x axis
    (jaw direction) and ``up_m`` along its z axis. It is held there and released from there."""

    name = "grasp_offset"
    summary = "payload position in the gripper relative to the gripper centre"
    stage = "payload"
    params = (
        Param("forward_m", "m", 0.0, -0.4, 0.4, "offset along the gripper x axis", "CHOSEN: gripper jaws ~0.9 m wide (machine-spec.md masses/sizes)"),
        Param("up_m", "m", 0.0, -0.4, 0.4, "offset along the gripper z axis (up positive)", "CHOSEN: gripper body ~1.0 m tall"),
    )

    def grasp_offset(self):
        return np.array([self.forward_m, 0.0, self.up_m])
