"""Aim correction of a policy version adapted to a site (``slinger adapt``, sim_twin.adaptation.adapt).

A per-distance offset table in the version's manifest says where to aim so that the MEAN impact
on that site hits the target: the runtime builds the policy's observation with the corrected
target ``target + down(d) * u + cross(d) * u_perp`` (u the unit vector from the turn axis towards
the target, u_perp = z x u, left positive; d the target's horizontal distance from the turn axis;
offsets linearly interpolated in d, held constant beyond the table's ends). Impact errors, target
checks and the operator's view keep the requested target.

Manifest block (``aim_correction``)::

    {"format": "slinger-aim/1", "distances_m": [7.5, 8.0, ...],
     "downrange_offset_m": [-0.31, ...], "crossrange_offset_m": [0.0, ...], ...provenance}

The same block is sealed into the ONNX file's metadata (key :data:`ONNX_METADATA_KEY`, canonical
JSON), so the file's SHA-256 binds it: a manifest whose table was edited afterwards is refused.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

AIM_FORMAT = "slinger-aim/1"
ONNX_METADATA_KEY = "slinger_aim_correction"
MAX_OFFSET_M = 3.0
"""Largest offset accepted (m): larger ones mean the policy does not fit the site at all."""


def canonical_json(block: dict) -> str:
    """The sealed form of a block: sorted keys, no spaces."""
    return json.dumps(block, sort_keys=True, separators=(",", ":"))


@dataclass(frozen=True)
class AimCorrection:
    """A checked offset table.

    Attributes:
        distances_m: (K,) strictly increasing target distances from the turn axis, m.
        downrange_m / crossrange_m: (K,) offsets added to the target at those distances, m.
        block: the manifest block it came from.
    """

    distances_m: np.ndarray
    downrange_m: np.ndarray
    crossrange_m: np.ndarray
    block: dict

    @classmethod
    def from_block(cls, block: dict) -> AimCorrection:
        """Parse and check a manifest block.

        Raises:
            ValueError: wrong format tag, missing or unequal-length lists, non-finite values,
                distances not strictly increasing or <= 0, offsets beyond MAX_OFFSET_M.
        """
        if not isinstance(block, dict) or block.get("format") != AIM_FORMAT:
            raise ValueError(f"aim_correction must be an object with format {AIM_FORMAT!r}")
        try:
            d, dr, cr = (np.asarray(block[k], dtype=float) for k in ("distances_m", "downrange_offset_m", "crossrange_offset_m"))
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"aim_correction needs numeric lists distances_m, downrange_offset_m, crossrange_offset_m: {e}") from e
        if d.ndim != 1 or len(d) < 1 or dr.shape != d.shape or cr.shape != d.shape:
            raise ValueError("aim_correction lists must be non-empty and of equal length")
        if not (np.all(np.isfinite(d)) and np.all(np.isfinite(dr)) and np.all(np.isfinite(cr))):
            raise ValueError("aim_correction values must be finite")
        if np.any(d <= 0) or np.any(np.diff(d) <= 0):
            raise ValueError("aim_correction distances_m must be positive and strictly increasing")
        worst = float(max(np.abs(dr).max(), np.abs(cr).max()))
        if worst > MAX_OFFSET_M:
            raise ValueError(f"aim_correction offset of {worst:.2f} m exceeds {MAX_OFFSET_M} m")
        return cls(d, dr, cr, block)

    def offsets_at(self, distance_m: float) -> tuple[float, float]:
        """(downrange, crossrange) offset at ``distance_m`` (interpolated, held at the ends), m."""
        return (float(np.interp(distance_m, self.distances_m, self.downrange_m)),
                float(np.interp(distance_m, self.distances_m, self.crossrange_m)))

    def aim(self, target_m) -> np.ndarray:
        """The corrected target (3,) for a requested target (3,), machine frame, m. A target
        on the turn axis is returned unchanged (it has no direction)."""
        t = np.asarray(target_m, dtype=float).copy()
        dist = math.hypot(t[0], t[1])
        if dist < 1e-6:
            return t
        u = t[:2] / dist
        down, cross = self.offsets_at(dist)
        t[:2] += down * u + cross * np.array([-u[1], u[0]])
        return t
