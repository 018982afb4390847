"""Drag-free flight of the payload, shared by the runtime (runtime.release_check) and the twin
(sim_twin.twin.physics re-exports these names for the simulated machine, MJX environment and preview).

Machine frame (runtime.machine: origin on the cabin-turn axis at ground level, z up); metres,
seconds. Works on any array module ``xp`` (numpy, jax.numpy).
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

GRAVITY_MPS2 = 9.81
PAYLOAD_RADIUS_M = 0.12
"""Size 7 basketball, 0.24 m diameter (machine-spec.md): the payload's centre is this high when
it touches the ground."""


def ballistic_impact_time(xp: ModuleType, p0, v0, ground_z):
    """Time (s) until a drag-free projectile from p0 (3,) with v0 (3,) reaches height ground_z.

    Solves z0 + vz t - g t^2 / 2 = ground_z for the later root; if p0 is already below
    ground_z it returns 0.
    """
    dz = p0[2] - ground_z
    disc = v0[2] ** 2 + 2.0 * GRAVITY_MPS2 * xp.maximum(dz, 0.0)
    return (v0[2] + xp.sqrt(disc)) / GRAVITY_MPS2


def ballistic_position(xp: ModuleType, p0, v0, t):
    """Drag-free projectile position (3,) at time t after leaving p0 with v0."""
    g = xp.asarray([0.0, 0.0, -GRAVITY_MPS2], dtype=p0.dtype)
    return p0 + v0 * t + 0.5 * g * t * t


def ground_impact(p0: np.ndarray, v0: np.ndarray) -> tuple[np.ndarray, float]:
    """Where and when (numpy) a payload freed at p0 (3,) with v0 (3,) touches the ground in
    drag-free flight: the ground point under its centre (3,), z = 0, m, and the flight time, s
    (its centre PAYLOAD_RADIUS_M high at the touch)."""
    t = float(ballistic_impact_time(np, p0, v0, PAYLOAD_RADIUS_M))
    hit = ballistic_position(np, p0, v0, t)
    hit[2] = 0.0
    return hit, t
