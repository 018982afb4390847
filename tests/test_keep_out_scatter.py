"""Keep-out zones against a preview's predicted scatter (server.throws.targets.scatter_refusal and the
gate's ``keep_out_scatter`` condition): a target outside every zone is not enough when the
payload may land inside one."""

from __future__ import annotations

import math
from datetime import UTC, datetime

import pytest

from server.config import KeepOutZone
from server.throws.targets import _distance_to_ellipse, scatter_refusal
from server.throws.gate import GateLimits, preview_refusal

TARGET = [8.5, -0.3, 0.0]


def _preview(ellipse: dict | None = None, impact=(8.5, -0.3)) -> dict:
    """An OK preview summary as server.throws.previews stores it (ellipse: 1 sigma, machine frame)."""
    return {"status": "ok", "machine_id": "m1", "mode": "2d", "target_m": TARGET, "created_at": datetime.now(UTC).isoformat(),
            "policy_sha256": "abc", "start_q": [0.0] * 6, "impact_m": [*impact, 0.0],
            "mc": {"ellipse": ellipse} if ellipse else None}


def _ellipse(major: float, minor: float, angle_rad: float = 0.0) -> dict:
    return {"center_m": [8.5, -0.3], "semi_major_m": major, "semi_minor_m": minor, "angle_rad": angle_rad}


def test_distance_to_an_ellipse():
    assert _distance_to_ellipse((3.0, 0.0), (0.0, 0.0), 1.0, 1.0, 0.0) == pytest.approx(2.0, abs=1e-6)
    assert _distance_to_ellipse((0.0, 3.0), (0.0, 0.0), 2.0, 1.0, 0.0) == pytest.approx(2.0, abs=1e-4)
    assert _distance_to_ellipse((0.0, 3.0), (0.0, 0.0), 2.0, 1.0, math.pi / 2) == pytest.approx(1.0, abs=1e-4)  # turned
    assert _distance_to_ellipse((0.5, 0.2), (0.0, 0.0), 2.0, 1.0, 0.3) == 0.0  # inside


def test_the_three_sigma_ellipse_must_stay_out_of_every_zone():
    zone = [KeepOutZone(name="truck", center_m=[8.5, 1.2], radius_m=1.0)]
    # 3 sigma across: 0.3 m, the ellipse's edge at y = 0, 1.2 m from the zone's centre
    assert scatter_refusal(_preview(_ellipse(0.2, 0.1)), zone, 3.0, 0.6) is None
    wide = [KeepOutZone(name="truck", center_m=[8.5, 1.2], radius_m=1.3)]
    reason = scatter_refusal(_preview(_ellipse(0.2, 0.1)), wide, 3.0, 0.6)
    assert reason is not None and "3 sigma scatter ellipse reaches 0.10 m into keep-out zone 'truck'" in reason
    # the same ellipse turned by 90 degrees reaches 0.9 m across: into a zone it missed unturned
    small = [KeepOutZone(name="pit", center_m=[8.5, 1.2], radius_m=0.5)]
    assert scatter_refusal(_preview(_ellipse(0.4, 0.1)), small, 3.0, 0.6) is None
    assert "'pit'" in scatter_refusal(_preview(_ellipse(0.4, 0.1, math.pi / 2)), small, 3.0, 0.6)


def test_without_an_ellipse_the_nominal_impact_keeps_a_margin():
    near = [KeepOutZone(name="truck", center_m=[8.5, 0.6], radius_m=0.5)]  # rim 0.4 m from the impact
    reason = scatter_refusal(_preview(None), near, 3.0, 0.6)
    assert reason is not None and "0.40 m from keep-out zone 'truck' (at least 0.60 m" in reason
    far = [KeepOutZone(name="truck", center_m=[8.5, 1.0], radius_m=0.5)]  # 0.8 m
    assert scatter_refusal(_preview(None), far, 3.0, 0.6) is None
    assert scatter_refusal(_preview(None), [], 3.0, 0.6) is None


def test_the_gate_names_the_condition_and_checks_it_before_staleness():
    zones = [KeepOutZone(name="truck", center_m=[8.5, 1.2], radius_m=1.3)]
    p = _preview(_ellipse(0.2, 0.1))
    now = datetime.now(UTC)
    assert preview_refusal(p, "p1", "m1", "2d", TARGET, [0.0] * 6, "abc", now, GateLimits()) is None
    refusal = preview_refusal(p, "p1", "m1", "2d", TARGET, [0.0] * 6, "abc", now, GateLimits(), zones)
    assert refusal is not None and refusal.condition == "keep_out_scatter" and refusal.error.__name__ == "Refused"
    # the edge at 3 sigma is 1.2 m from the centre, at 2 sigma 1.3 m: a zone of radius 1.25 m
    # is reached by the one and not by the other
    zone = [KeepOutZone(name="truck", center_m=[8.5, 1.2], radius_m=1.25)]
    assert preview_refusal(p, "p1", "m1", "2d", TARGET, [0.0] * 6, "abc", now, GateLimits(), zone) is not None
    assert preview_refusal(p, "p1", "m1", "2d", TARGET, [0.0] * 6, "abc", now, GateLimits(scatter_sigmas=2.0), zone) is None
    stale = {**p, "created_at": "2000-01-01T00:00:00+00:00"}
    assert preview_refusal(stale, "p1", "m1", "2d", TARGET, [0.0] * 6, "abc", now, GateLimits(), zones).condition == "keep_out_scatter"
