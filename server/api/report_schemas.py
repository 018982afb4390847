"""Response bodies of the analysis routes: diagnosis and adaptation runs, the effects library, a
throw's recorded trajectory, accuracy groups and policy comparisons.

The documented fields are the ones these routes always write (server.analysis.diagnosis.run_view,
server.analysis.adaptation.adaptation_view, server.analysis.accuracy.accuracy, ...); the models allow more, so a
field a newer report adds reaches the console before it is documented here.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

RunStatus = Literal["queued", "running", "done", "failed"]


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow")


class DiagnosisRunOut(_Open):
    """A diagnosis run (a ``diagnosis`` job; a cancelled one reads as failed with error
    "cancelled"); ``report`` (sim_twin.diagnosis report.json) once it is done and read alone."""

    id: str
    job_id: str
    machine_id: str | None
    throws: int | None = Field(description="throws diagnosed (asked for, until it is done)")
    status: RunStatus
    error: str | None
    progress: float | None = Field(description="0..1")
    message: str | None
    started_at: str = Field(description="ISO 8601 UTC")
    finished_at: str | None
    requested_by: str | None
    verdict: dict[str, Any] | None = Field(description="sim_twin.diagnosis.verdict.verdict_of, once done")
    source: Literal["stored throws", "rosbag2 upload"]
    report: dict[str, Any] | None = None


class AdaptationRunOut(_Open):
    """An adaptation run (an ``adaptation`` job); ``progress``: its log lines so far; the new
    policy version once it is done."""

    id: str
    job_id: str
    diagnosis_id: str | None
    machine_id: str | None
    mode: str | None
    base_version: str | None
    status: RunStatus
    error: str | None
    progress: list[str]
    policy_version_id: int | None
    policy_version: str | None
    started_at: str = Field(description="ISO 8601 UTC")
    finished_at: str | None
    requested_by: str | None


class EffectParamOut(_Open):
    """One parameter of an effect (sim_twin.twin.effects.base.Param.to_dict): name, unit, prior range, source."""

    name: str


class EffectOut(_Open):
    """One effect of the library (sim_twin.twin.effects.base.Effect.describe)."""

    name: str
    summary: str
    stage: str
    params: list[EffectParamOut]


class TrajectoryEvent(BaseModel):
    t_s: float
    phase: str


class TrajectoryOut(BaseModel):
    """A throw's recorded trajectory (at most 300 points, from its MCAP telemetry): times (s),
    joint angles ``q`` (N, 6, rad or m), velocities ``qd`` (N, 6) and references ``qd_ref`` (N, 4),
    valve commands ``valve_u`` (N, 4, -1..1), gripper-centre and payload paths (machine frame, m),
    phase events; target, impact and the preview the throw was sent with."""

    throw_id: str
    t_s: list[float]
    q: list[list[float]]
    qd: list[list[float]]
    qd_ref: list[list[float]]
    valve_u: list[list[float]]
    payload_t_s: list[float]
    gripper_path_m: list[list[float]]
    payload_path_m: list[list[float]]
    events: list[TrajectoryEvent]
    target_m: list[float]
    impact_m: list[float] | None
    preview: dict[str, Any] | None


class EllipseOut(BaseModel):
    """1 sigma error ellipse (server.analysis.accuracy.ellipse_of): semi-axes (m), major axis angle from
    downrange (rad), outline ((n + 1, 2), m)."""

    semi_major_m: float
    semi_minor_m: float
    angle_rad: float
    outline_m: list[list[float]]


class AccuracyGroupOut(BaseModel):
    """Landed throws of one mode, policy version and target-distance bin (server.analysis.accuracy.accuracy):
    mean, bias and spread of the impact errors (m), the ellipse (None below 3 throws) and up to
    200 errors ([downrange, crossrange], m) for the scatter plot."""

    mode: str
    policy_version: str
    policy_sha256: str | None
    target_distance_m: float
    n: int
    mean_impact_distance_m: float
    bias_m: float
    sigma_downrange_m: float
    mean_crossrange_m: float
    sigma_crossrange_m: float
    mean_abs_error_m: float
    ellipse: EllipseOut | None
    errors_m: list[list[float]]


class PolicyComparisonOut(BaseModel):
    """One policy version in a comparison: its twin evaluation per target distance
    (``twin``: the ``targets`` of its metrics) and its logged throws' accuracy groups."""

    id: int
    name: str
    mode: str
    sha256: str
    evaluation_status: str | None
    twin: list[dict[str, Any]]
    logged: list[AccuracyGroupOut]


class RollbackTargetOut(BaseModel):
    """The version a rollback would go back to."""

    id: int
    name: str


class DriftAlertOut(_Open):
    """A machine's accuracy-drift alert (server.analysis.drift.DriftWatch; the ``drift`` event on /api/live)."""

    machine_id: str
    raised_at: str = Field(description="ISO 8601 UTC")
    status: Literal["open", "acknowledged"]
    text: str = Field(description="the alert in words (shift in m, axis, baseline)")
    test: dict[str, Any] = Field(description="the sequential test: two-sided self-starting CUSUM (Page 1954, Hawkins 1987), its k, h, axis, statistic, shift_m")
    diagnosis: dict[str, Any] | None = Field(description="the diagnosis it started: id, status, throws")
    adaptation: dict[str, Any] | None
