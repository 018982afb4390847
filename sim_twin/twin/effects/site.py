"""Site effects: steady wind on the payload in flight, and its first-order landing shift for the
training environment's analytic flight."""

from __future__ import annotations

import numpy as np

from sim_twin.twin.effects.base import Effect, Param
from sim_twin.twin.effects.payload import AIR_DENSITY_KG_M3
from sim_twin.twin.model import PAYLOAD_MASS_KG, PAYLOAD_RADIUS_M
from sim_twin.twin.physics import GRAVITY_MPS2

WIND_DRAG_COEFFICIENT = 0.5  # basketball, subcritical Re (wind-tunnel literature; PayloadDrag's source)
WIND_K_PER_M = AIR_DENSITY_KG_M3 * WIND_DRAG_COEFFICIENT * np.pi * PAYLOAD_RADIUS_M**2 / (2 * PAYLOAD_MASS_KG)
"""k = rho Cd A / (2 m) of the model payload, 1/m (the drag acceleration per squared air speed)."""
_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(8)  # Gauss-Legendre on [-1, 1]


class Wind(Effect):
    """Steady horizontal wind w = (wind_x_mps, wind_y_mps, 0) in the machine frame. It adds the
    wind's share of the quadratic drag (Cd 0.5 on pi r^2):

        a = -k (|v - w| (v - w) - |v| v),   k = rho Cd A / (2 m)

    i.e. the drag relative to moving air minus the still-air drag, so that zero wind is the
    nominal twin and still-air drag stays the business of ``payload_drag``."""

    name = "wind"
    summary = "steady horizontal wind acting on the payload in flight"
    stage = "flight"
    params = (
        Param("wind_x_mps", "m/s", 0.0, -15.0, 15.0, "wind along the machine frame's x axis", "CHOSEN: up to a fresh breeze (Beaufort 5-6)"),
        Param("wind_y_mps", "m/s", 0.0, -15.0, 15.0, "wind along the machine frame's y axis (left positive)", "CHOSEN: as wind_x_mps"),
    )

    def flight_accel(self, pos_m, vel_mps):
        return wind_accel(np, vel_mps, np.array([self.wind_x_mps, self.wind_y_mps, 0.0]))


def wind_accel(xp, vel_mps, wind_mps):
    """The wind's share of the payload's drag (:class:`Wind`), m/s^2: (..., 3) for velocities
    ``vel_mps`` (..., 3) m/s in a wind ``wind_mps`` (3,) m/s (machine frame, horizontal).
    Array module ``xp`` (numpy, jax.numpy)."""
    rel = vel_mps - wind_mps
    speed = xp.sqrt(xp.sum(rel * rel, axis=-1, keepdims=True))
    still = xp.sqrt(xp.sum(vel_mps * vel_mps, axis=-1, keepdims=True))
    return -WIND_K_PER_M * (speed * rel - still * vel_mps)


def wind_landing_shift(xp, p0, v0, t_flight, wind_xy):
    """How far (2,) m, machine frame, a steady wind ``wind_xy`` (2,) m/s moves the landing point
    of a payload freed at ``p0`` (3,) m with ``v0`` (3,) m/s whose drag-free flight to the ground
    takes ``t_flight`` s: the wind's share of the drag (:func:`wind_accel`) to first order along
    the drag-free path, for the training environment, which flies the payload analytically.

    The displacement at the drag-free landing time T is dp = int_0^T (T - t) a(t) dt (8-point
    Gauss-Legendre along v(t) = v0 + g t); the landing comes dt = -dp_z / v_z(T) later, so the
    point moves by dp_xy + v_xy dt (v_z(T) taken as at most -0.5 m/s, a landing that grazes the
    ground). Second-order terms are of the relative size k |v| T (about 0.1 for the model payload's
    throws); tests/test_wind_training.py holds it to the twin's RK4 flight under :class:`Wind`.
    Array module ``xp`` (numpy, jax.numpy)."""
    g = xp.asarray([0.0, 0.0, -GRAVITY_MPS2])
    tau = 0.5 * (xp.asarray(_GL_NODES) + 1.0)  # (8,) in (0, 1)
    t = t_flight * tau
    v = v0[None, :] + t[:, None] * g[None, :]
    wind = xp.concatenate([wind_xy, xp.zeros(1)])
    a = wind_accel(xp, v, wind)
    dp = xp.sum((0.5 * xp.asarray(_GL_WEIGHTS) * t_flight * (t_flight - t))[:, None] * a, axis=0)
    v_end = v0 + g * t_flight
    dt = -dp[2] / xp.minimum(v_end[2], -0.5)
    return dp[:2] + v_end[:2] * dt
