"""Which targets the server serves: the mode's geometry (runtime.throw_geometry.target_refusal)
plus the site's keep-out zones (settings.keep_out_zones)."""

from __future__ import annotations

import math

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
