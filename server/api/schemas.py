"""API schemas (pydantic), separate from the SQLAlchemy models in :mod:`server.db.models`.

Positions are machine-frame metres ``[x, y, z]``; timestamps are UTC-aware ISO 8601.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from server.db.models import Throw


def _finite(v: list[float]) -> list[float]:
    if not all(math.isfinite(x) for x in v):
        raise ValueError("target must be finite")
    return v


Vec3 = Annotated[list[float], Field(min_length=3, max_length=3), AfterValidator(_finite)]


class Health(BaseModel):
    status: Literal["ok"] = "ok"
    zenoh: bool
    database: bool


class MachineOut(BaseModel):
    """A machine as the console sees it.

    Attributes:
        online: its runtime holds its liveliness token.
        simulated: the machine is the SIMULATED machine (sim_twin plant), not hardware.
        policies: active policy version name per mode (``{"2d": "throw2d-..."}``).
        busy: the runtime is executing a throw (None if unknown).
        cabin_turn_rad: latest cabin angle, rad (None before the first state).
    """

    id: str
    online: bool
    simulated: bool
    policies: dict[str, str] = Field(default_factory=dict)
    busy: bool | None = None
    cabin_turn_rad: float | None = None
    last_throw_at: datetime | None = None
    last_throw_status: str | None = None
    current_mode: str | None = None
    """Mode of the machine's latest throw."""
    recent_throws: int = 0
    recent_mean_abs_error_m: float | None = None
    """Mean |impact - target| over the last landed throws (at most 20)."""


class ThrowCreate(BaseModel):
    """POST /api/throws body."""

    model_config = ConfigDict(extra="forbid")

    machine_id: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")]
    mode: Literal["2d", "3d"]
    target: Vec3
    preview_id: str | None = Field(default=None, max_length=64)
    """The preview this throw was shown (its prediction is stored with the throw)."""
    confirm_clearance: bool = False
    """3D throws only: the operator confirmed that the swept clearance zone is clear."""


class ThrowCreated(BaseModel):
    id: str
    status: str
    policy_version: str | None = None


class ThrowOut(BaseModel):
    """One throw: request, outcome, errors (see runtime.throw_geometry.impact_errors)."""

    id: str
    machine_id: str
    mode: str
    status: str
    failure_reason: str | None
    target: list[float]
    impact: list[float] | None
    downrange_error_m: float | None
    crossrange_error_m: float | None
    policy_version: str | None
    requested_at: datetime
    started_at: datetime | None
    released_at: datetime | None
    completed_at: datetime | None
    duration_s: float | None
    telemetry_url: str | None
    target_distance_m: float | None = None
    requested_by: str | None = None
    preview: dict | None = None
    """The twin preview the throw was sent with (predicted impact, errors, ellipse), if any."""

    @classmethod
    def of(cls, row: Throw) -> "ThrowOut":
        return cls(
            id=row.id, machine_id=row.machine_id, mode=row.mode, status=row.status,
            failure_reason=row.failure_reason, target=row.target_m, impact=row.impact_m,
            downrange_error_m=row.downrange_error_m, crossrange_error_m=row.crossrange_error_m,
            policy_version=row.policy_version, requested_at=row.requested_at,
            started_at=row.started_at, released_at=row.released_at,
            completed_at=row.completed_at, duration_s=row.duration_s,
            telemetry_url=f"/api/throws/{row.id}/telemetry" if row.telemetry_path else None,
            target_distance_m=math.hypot(row.target_x_m, row.target_y_m),
            requested_by=row.requested_by, preview=row.preview,
        )


class SceneState(BaseModel):
    """The console's 3D view: where it is served and what the operator picked in it."""

    viser_port: int | None
    machine_id: str | None
    mode: Literal["2d", "3d"]
    target: list[float] | None
    preview: list[str] = Field(default_factory=list)
    """Scene names of the preview drawn in the 3D view (paths, release, impact, ellipse, ...)."""


class SceneUpdate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    machine_id: str | None = None
    mode: Literal["2d", "3d"] | None = None
    target: Vec3 | None = None


class Problem(BaseModel):
    detail: str
