"""Throw geometry shared by runtime, twin and server: impact errors and which targets a mode serves.

Definitions (docs/architecture.md): downrange is the horizontal distance along the line from the
cabin-turn axis towards the target; crossrange is the signed horizontal offset perpendicular to
it, left positive (z x downrange).
"""

from __future__ import annotations

import math

import numpy as np

from runtime.machine import BOOM_OFFSET_M

MIN_TARGET_DISTANCE_M = 5.0
"""Closest target a throw may aim at: nearer targets risk hitting the cabin (paper Sec. III-B:
"the horizontal distance from the target to the cabin turn center is constrained to have a
minimum value"). Chosen: 5 m, about two thirds of the 7.4 m static reach."""

MAX_TARGET_HEIGHT_M = 0.5
"""Targets are on the ground: |z| must not exceed this (m)."""

PLANE_TOLERANCE_M = 0.25
"""2D mode: largest lateral offset (m) of a target from the arm's vertical plane."""

ARM_PLANE_OFFSET_M = BOOM_OFFSET_M[1]
"""Lateral offset (m, cabin frame y) of the arm's vertical plane from the turn axis."""


def impact_errors(target_m, impact_m) -> tuple[float, float]:
    """Downrange and crossrange error of an impact.

    Args:
        target_m: (3,) target, machine frame, m.
        impact_m: (3,) impact point, machine frame, m.

    Returns:
        (downrange_error_m, crossrange_error_m): positive downrange = long (overshoot),
        positive crossrange = left of the line from the turn axis to the target.

    Raises:
        ValueError: if the target lies on the turn axis (no downrange direction).
    """
    t = np.asarray(target_m, dtype=float)[:2]
    e = np.asarray(impact_m, dtype=float)[:2] - t
    dist = float(np.hypot(*t))
    if dist < 1e-6:
        raise ValueError("target on the turn axis has no downrange direction")
    u = t / dist
    return float(e @ u), float(e @ np.array([-u[1], u[0]]))


def to_cabin_frame(xy, cabin_turn_rad: float) -> np.ndarray:
    """Rotate horizontal machine-frame coordinates (..., 2) into the cabin frame."""
    c, s = math.cos(cabin_turn_rad), math.sin(cabin_turn_rad)
    xy = np.asarray(xy, dtype=float)
    return np.stack([c * xy[..., 0] + s * xy[..., 1], -s * xy[..., 0] + c * xy[..., 1]], axis=-1)


def target_refusal(
    mode: str,
    target_m,
    cabin_turn_rad: float,
    target_range_m: tuple[float, float] = (MIN_TARGET_DISTANCE_M, 10.7),
) -> str | None:
    """Why ``mode`` cannot serve ``target_m`` from the current cabin angle, or None if it can.

    Args:
        mode: "2d" or "3d".
        target_m: (3,) target, machine frame, m.
        cabin_turn_rad: current cabin_turn angle, rad (2D throws hold it).
        target_range_m: (min, max) horizontal distance from the turn axis the policy was trained
            for (policy manifest ``target_range_m``), m.

    Returns:
        A sentence for the operator, or None.
    """
    if mode not in ("2d", "3d"):
        return f"unknown mode {mode!r}; use '2d' or '3d'"
    t = np.asarray(target_m, dtype=float)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        return "target must be three finite numbers [x, y, z] in metres"
    if abs(t[2]) > MAX_TARGET_HEIGHT_M:
        return f"target must be on the ground (|z| <= {MAX_TARGET_HEIGHT_M} m), got z = {t[2]:.2f} m"
    dist = float(np.hypot(t[0], t[1]))
    lo, hi = target_range_m
    if dist < lo:
        return f"target too close: {dist:.2f} m from the turn axis, minimum {lo:.2f} m"
    if dist > hi:
        return f"target beyond the policy's trained range: {dist:.2f} m, maximum {hi:.2f} m"
    if mode == "2d":
        x_c, y_c = to_cabin_frame(t[:2], cabin_turn_rad)
        lateral = y_c - ARM_PLANE_OFFSET_M
        if x_c <= 0 or abs(lateral) > PLANE_TOLERANCE_M:
            return (
                f"target off the 2D throwing plane by {lateral:+.2f} m (tolerance "
                f"{PLANE_TOLERANCE_M} m); turn the cabin towards it or use 3D mode"
            )
    return None
