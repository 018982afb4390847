"""API schemas (pydantic), separate from the SQLAlchemy models in :mod:`server.db.models`.

Positions are machine-frame metres ``[x, y, z]``; timestamps are UTC-aware ISO 8601.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime
from typing import Annotated, Literal

from pydantic import AfterValidator, AwareDatetime, BaseModel, ConfigDict, Field

from server.db.models import MODES, THROW_STATUSES, Throw

COORD_LIMIT_M = 1000.0
"""Bound of any position coordinate the API accepts, m (the machines reach ~12 m)."""
DISTANCE_LIMIT_M = 10_000.0
"""Bound of any distance filter the API accepts, m."""

MAX_DB_ID = 2**31 - 1
"""Largest row id the API accepts (PostgreSQL ``integer``; a larger one is 422, not a 500 from
the database driver)."""
DbId = Annotated[int, Field(ge=1, le=MAX_DB_ID)]


def _utc(value: datetime) -> datetime:
    try:
        return value.astimezone(UTC)
    except OverflowError as e:  # 0001-01-01T00:00+14:00 has no UTC equivalent
        raise ValueError("time out of range") from e


UtcTime = Annotated[AwareDatetime, AfterValidator(_utc)]
"""An ISO 8601 time WITH its zone (a naive time is 422), as UTC."""

Coord = Annotated[float, Field(ge=-COORD_LIMIT_M, le=COORD_LIMIT_M, allow_inf_nan=False)]
"""A finite machine-frame coordinate, m, within +-COORD_LIMIT_M (else 422)."""
Vec3 = Annotated[list[Coord], Field(min_length=3, max_length=3)]


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
        estop_latched / estop_reason: the runtime's E-STOP is latched (valves neutral, throws
            refused until an operator resets it) and why.
        ready / not_ready_reason: the runtime would accept a throw now, else why not
            ("E-STOP latched", "machine offline", the machine's fault, ...); None if unknown.
        phase / throw_id: the running throw's phase and id (None when idle or unknown).
        clock_offset_s: the runtime host's wall clock minus the server's, s (None: not
            reported); ``clock_warning`` says so in words when it is more than
            CLOCK_WARN_S off (signed commands are compensated; the host's time sync is broken).
        lease_holder: the server id (server.fleet.command_signer) whose commands the runtime
            obeys now (one writer per machine: runtime.service's lease; "" an unnamed server),
            None while nobody holds the lease or unknown; ``lease_held_here`` True when it is
            this server, False when another one (this server's commands are refused until its
            lease expires or an operator takes it over: POST .../lease/takeover), None when
            nobody holds it or unknown.
        undeliverable_results: throw results the runtime's outbox set aside after servers
            refused them repeatedly (runtime.outbox; kept on the runtime's disk), None if unknown.
    """

    id: str
    online: bool
    simulated: bool
    policies: dict[str, str] = Field(default_factory=dict)
    busy: bool | None = None
    cabin_turn_rad: float | None = None
    estop_latched: bool | None = None
    estop_reason: str | None = None
    ready: bool | None = None
    not_ready_reason: str | None = None
    phase: str | None = None
    throw_id: str | None = None
    clock_offset_s: float | None = None
    clock_warning: str | None = None
    lease_holder: str | None = None
    lease_held_here: bool | None = None
    undeliverable_results: int | None = None
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


ThrowStatusName = Literal[THROW_STATUSES]  # type: ignore[valid-type]
"""A throw's status (server.db.models.THROW_STATUSES), an enum in OpenAPI."""
ModeName = Literal[MODES]  # type: ignore[valid-type]


class ThrowCreated(BaseModel):
    id: str
    status: ThrowStatusName
    policy_version: str | None = None
    policy_sha256: str | None = None


class ThrowOut(BaseModel):
    """One throw: request, outcome, errors (see runtime.throw_geometry.impact_errors)."""

    id: str
    machine_id: str
    mode: ModeName
    status: ThrowStatusName
    failure_reason: str | None
    target: list[float]
    impact: list[float] | None
    downrange_error_m: float | None
    crossrange_error_m: float | None
    policy_version: str | None
    policy_sha256: str | None = None
    """SHA-256 of the policy's ONNX file: the version's identity (names are not unique)."""
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
    def of(cls, row: Throw) -> ThrowOut:
        return cls(
            id=row.id, machine_id=row.machine_id, mode=row.mode, status=row.status,
            failure_reason=row.failure_reason, target=row.target_m, impact=row.impact_m,
            downrange_error_m=row.downrange_error_m, crossrange_error_m=row.crossrange_error_m,
            policy_version=row.policy_version, policy_sha256=row.policy_sha256, requested_at=row.requested_at,
            started_at=row.started_at, released_at=row.released_at,
            completed_at=row.completed_at, duration_s=row.duration_s,
            telemetry_url=f"/api/throws/{row.id}/telemetry" if row.telemetry_path else None,
            target_distance_m=math.hypot(row.target_x_m, row.target_y_m),
            requested_by=row.requested_by, preview=row.preview,
        )


class Problem(BaseModel):
    """An error answer (server.api.errors): a sentence for the operator and, when the error names
    one, the failed condition (also in the ``X-Refused-Condition`` header)."""

    detail: str
    condition: str | None = None
