"""API schemas of previews (the summary of sim_twin.preview.preview.preview_throw)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from server.api.schemas import Vec3


class PreviewCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    machine_id: Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")]
    mode: Literal["2d", "3d"]
    target: Vec3
    rollouts: int | None = Field(default=None, ge=0, le=2000)
    """Monte Carlo rollouts (default: settings.preview_rollouts); 0 or 1: nominal only."""
    extends: str | None = Field(default=None, max_length=64)
    """The id of a preview of the same machine, mode and target that this one completes (the
    console's nominal-only preview before its ellipse): it then starts from that preview's
    machine state and reuses its nominal rollout, while the throw gate would still accept that
    preview (server.throws.previews.PreviewService.submit); otherwise from the current state."""


class PreviewOut(BaseModel):
    """A preview. ``status`` "failed" means the twin's swing failed (``reason``); then the
    prediction fields are None. Positions machine frame, m; speeds rad/s (telescope m/s).
    ``created_at``: when the machine state it starts from was read (a preview made with
    ``extends``: that preview's); the throw gate judges its age from it."""

    id: str
    machine_id: str
    mode: str
    target_m: list[float]
    policy_version: str
    policy_sha256: str | None = None
    created_at: str
    status: Literal["ok", "failed"]
    reason: str | None = None
    start_q: list[float] | None = None
    impact_m: list[float] | None = None
    downrange_error_m: float | None = None
    crossrange_error_m: float | None = None
    release_pos_m: list[float] | None = None
    release_vel_mps: list[float] | None = None
    release_command_pos_m: list[float] | None = None
    release_after_s: float | None = None
    flight_s: float | None = None
    duration_s: float | None = None
    peak_joint_speeds: dict[str, float] | None = None
    clearance: dict | None = None
    gripper_path_m: list[list[float]] | None = None
    payload_path_m: list[list[float]] | None = None
    mc: dict | None = None
    timing_s: dict[str, float] | None = None
