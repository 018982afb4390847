"""Which targets the server serves: the mode's geometry (runtime.throw_geometry.target_refusal)
plus the site's keep-out zones (settings.keep_out_zones), and whether a preview's predicted
scatter stays out of those zones (:func:`scatter_refusal`)."""

from __future__ import annotations

import math

import numpy as np

from runtime.throw_geometry import target_refusal


def keep_out_refusal(target_m, zones) -> str | None:
    """The reason ``target_m`` is refused by a keep-out zone (ground circle), or None."""
    for z in zones:
        d = math.hypot(target_m[0] - z.center_m[0], target_m[1] - z.center_m[1])
        if d <= z.radius_m:
            return (f"target inside keep-out zone {z.name!r} ({d:.2f} m from its centre, "
                    f"radius {z.radius_m:.2f} m)")
    return None


def serve_refusal(mode: str, target_m, cabin_turn_rad: float, target_range_m=None, zones=()) -> str | None:
    """Why the target cannot be served (too close, beyond the trained range, off the 2D plane,
    off the ground, inside a keep-out zone), or None."""
    extra = {"target_range_m": target_range_m} if target_range_m else {}
    return target_refusal(mode, target_m, cabin_turn_rad, **extra) or keep_out_refusal(target_m, zones)


def _distance_to_ellipse(point, center, semi_major: float, semi_minor: float, angle_rad: float) -> float:
    """Distance (m) from ``point`` (x, y) to the filled ellipse (0 inside): the boundary sampled
    every 0.5 degrees (under 0.01 % of the semi-major axis too far, from the chord)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    dx, dy = point[0] - center[0], point[1] - center[1]
    u, v = c * dx + s * dy, -s * dx + c * dy  # in the ellipse's axes
    a, b = max(semi_major, 1e-9), max(semi_minor, 1e-9)
    if (u / a) ** 2 + (v / b) ** 2 <= 1.0:
        return 0.0
    t = np.linspace(0.0, 2.0 * math.pi, 721)
    return float(np.min(np.hypot(a * np.cos(t) - u, b * np.sin(t) - v)))


def scatter_refusal(preview: dict, zones, sigmas: float, margin_m: float) -> str | None:
    """Why a throw as ``preview`` predicts it could land in a keep-out zone, or None.

    A target outside every zone is not enough: the payload lands around it. With a Monte Carlo
    ellipse (``preview["mc"]["ellipse"]``: centre, 1 sigma semi-axes, angle; sim_twin.preview.preview)
    the ``sigmas``-sigma ellipse must not touch a zone; without one the nominal impact
    (``preview["impact_m"]``) must lie at least ``margin_m`` outside every zone.

    Args:
        preview: an OK preview's summary (server.throws.previews), machine frame, m.
        zones: server.config.KeepOutZone circles on the ground.
        sigmas: the ellipse's scale, e.g. 3 (98.9 % of a 2-D Gaussian's impacts inside).
        margin_m: clearance of the nominal impact from a zone when there is no ellipse, m.
    """
    mc = preview.get("mc") or {}
    ellipse = mc.get("ellipse")
    impact = preview.get("impact_m")
    for z in zones:
        if ellipse:
            d = _distance_to_ellipse(z.center_m, ellipse["center_m"], sigmas * ellipse["semi_major_m"],
                                     sigmas * ellipse["semi_minor_m"], ellipse["angle_rad"])
            if d <= z.radius_m:
                return (f"the preview's {sigmas:g} sigma scatter ellipse reaches {z.radius_m - d:.2f} m into "
                        f"keep-out zone {z.name!r}: pick a target further from the zone")
        elif impact is not None:
            d = math.hypot(impact[0] - z.center_m[0], impact[1] - z.center_m[1]) - z.radius_m
            if d < margin_m:
                return (f"the predicted impact is {max(d, 0.0):.2f} m from keep-out zone {z.name!r} "
                        f"(at least {margin_m:.2f} m without a scatter ellipse): pick a target further "
                        f"from the zone, or preview with rollouts for its ellipse")
    return None
