"""SQLAlchemy 2 typed models. API schemas live in :mod:`server.api.schemas`; never mix them.

Tables: ``machines``, ``policy_versions``, ``throws``, ``throw_accuracy`` (incremental accuracy
aggregates, maintained by :mod:`server.db.aggregates`), ``users``, ``auth_sessions``,
``audit_log``, ``policy_deployments``, ``jobs``. Modes and statuses are database enums
(:func:`db_enum`: a VARCHAR with a CHECK constraint on SQLite and PostgreSQL alike, so that a new
value is one constraint swap in a migration) and ``Literal`` types in the API (OpenAPI enums). Positions are machine-frame metres,
timestamps UTC-aware (:class:`server.db.types.UTCDateTime`). Constraint names follow
:data:`NAMING_CONVENTION` so Alembic batch migrations on SQLite can address them.
"""

from __future__ import annotations

import secrets
import uuid
from datetime import date, datetime
from typing import Literal, get_args

from sqlalchemy import JSON, BigInteger, Boolean, Date, Enum, Float, ForeignKey, Index, Integer, MetaData, String, Text
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from server.db.types import UTCDateTime, utcnow

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

THROW_STATUSES = ("requested", "preparing", "swinging", "released", "landed", "failed", "aborted", "lost")
"""Row status: ``requested`` until the runtime reports a phase, then the ThrowStatus phase;
``lost`` when the server's reconciliation (server.fleet.reconcile) finds that the throw's result can
never arrive (its runtime restarted without it, or stayed away past the bound), with the reason
in ``failure_reason``. A late result from the runtime still replaces ``lost``."""
FINAL_STATUSES = ("landed", "failed", "aborted", "lost")
MODES = ("2d", "3d")
EVALUATION_STATUSES = ("pending", "running", "done", "failed")


def db_enum(values, name: str, length: int = 16) -> Enum:
    """A database enum of ``values``: VARCHAR(``length``) + CHECK ``ck_<table>_<name>``.

    Not a native PostgreSQL ENUM type: SQLite has none, and a CHECK constraint gains a value by
    being dropped and re-created in one migration on both databases. Writing a value outside
    ``values`` raises ``LookupError`` in Python (``StatementError`` from a session) before SQL runs.
    """
    return Enum(*values, name=name, native_enum=False, create_constraint=True, length=length,
                validate_strings=True)


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class Machine(Base):
    """A machine the server has seen (its runtime's liveliness token or its state)."""

    __tablename__ = "machines"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    simulated: Mapped[bool] = mapped_column(Boolean, default=False)
    first_seen_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    last_seen_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class PolicyVersion(Base):
    """A policy version (ONNX + manifest) identified by the ONNX file's SHA-256."""

    __tablename__ = "policy_versions"

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(128))
    mode: Mapped[str] = mapped_column(db_enum(MODES, "mode", 2))
    sha256: Mapped[str] = mapped_column(String(64), unique=True)
    manifest: Mapped[dict] = mapped_column(JSON, default=dict)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    onnx_path: Mapped[str | None] = mapped_column(String(512), nullable=True)
    """The ONNX file relative to the data dir (None: the server has no copy)."""
    notes: Mapped[str | None] = mapped_column(Text, nullable=True)
    uploaded_by: Mapped[str | None] = mapped_column(String(64), nullable=True)
    evaluation_status: Mapped[str | None] = mapped_column(db_enum(EVALUATION_STATUSES, "evaluation_status"),
                                                          nullable=True)
    """None (not evaluated), ``pending``, ``running``, ``done`` or ``failed``."""
    metrics: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    """The twin evaluation report (sim_twin.evaluation.evaluate format)."""


class Throw(Base):
    """One throw at one target and what came of it.

    Columns of note: ``target_*_m`` / ``impact_*_m`` machine frame, m; errors as defined by
    :func:`runtime.throw_geometry.impact_errors`; ``telemetry_path`` relative to the data dir.
    The columns a landed throw's accuracy contribution depends on keep their previous value on
    change (``active_history``), so that :mod:`server.db.aggregates` can move the contribution.
    """

    __tablename__ = "throws"
    __table_args__ = (
        Index("ix_throws_machine_requested", "machine_id", "requested_at"),
        Index("ix_throws_requested_at", "requested_at"),
        Index("ix_throws_policy_sha256", "policy_sha256", "requested_at"),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=lambda: str(uuid.uuid4()))
    machine_id: Mapped[str] = mapped_column(ForeignKey("machines.id"), active_history=True)
    mode: Mapped[str] = mapped_column(db_enum(MODES, "mode", 2), active_history=True)
    target_x_m: Mapped[float] = mapped_column(Float, active_history=True)
    target_y_m: Mapped[float] = mapped_column(Float, active_history=True)
    target_z_m: Mapped[float] = mapped_column(Float)
    status: Mapped[str] = mapped_column(db_enum(THROW_STATUSES, "status"), default="requested", active_history=True)
    failure_reason: Mapped[str | None] = mapped_column(Text, nullable=True)
    impact_x_m: Mapped[float | None] = mapped_column(Float, nullable=True)
    impact_y_m: Mapped[float | None] = mapped_column(Float, nullable=True)
    impact_z_m: Mapped[float | None] = mapped_column(Float, nullable=True)
    downrange_error_m: Mapped[float | None] = mapped_column(Float, nullable=True, active_history=True)
    crossrange_error_m: Mapped[float | None] = mapped_column(Float, nullable=True, active_history=True)
    policy_version: Mapped[str | None] = mapped_column(String(128), nullable=True, active_history=True)
    """The policy version's name, for people; names are not unique, ``policy_sha256`` is."""
    policy_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True, active_history=True)
    """SHA-256 of the ONNX file that made the throw: the policy identity comparisons and accuracy group by."""
    requested_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow, active_history=True)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    released_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    completed_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    duration_s: Mapped[float | None] = mapped_column(Float, nullable=True)
    telemetry_path: Mapped[str | None] = mapped_column(String(512), nullable=True)
    preview: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    """The twin preview the throw was sent with (sim_twin.preview.preview summary), if any."""
    requested_by: Mapped[str | None] = mapped_column(String(64), nullable=True)
    runtime_epoch: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    """The claim epoch of the runtime the throw was sent to (RuntimeInfo.epoch): a runtime with
    another epoch restarted since and cannot be running it."""

    @property
    def target_m(self) -> list[float]:
        return [self.target_x_m, self.target_y_m, self.target_z_m]

    @property
    def impact_m(self) -> list[float] | None:
        if self.impact_x_m is None or self.impact_y_m is None or self.impact_z_m is None:  # written together
            return None
        return [self.impact_x_m, self.impact_y_m, self.impact_z_m]


class ThrowAccuracy(Base):
    """Incremental accuracy aggregates of the landed throws (server.db.aggregates maintains them
    in the transaction that changes a throw; server.analysis.accuracy answers from them).

    One row per (machine, mode, policy SHA-256, policy name, target-distance bin, UTC day of
    ``requested_at``); a missing SHA or name is stored as ``''`` (key columns are NOT NULL).
    ``distance_bin`` = floor(target distance / 0.5 m + 0.5) (server.db.aggregates.distance_bin).
    Sums over the landed throws of the key (errors as in ``throws``, m; products m²):
    ``n``, sums of downrange, crossrange, their squares, their product and of |error| =
    sqrt(down² + cross²). A row whose ``n`` fell to 0 stays (its sums ~0) and is ignored.
    """

    __tablename__ = "throw_accuracy"

    machine_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    mode: Mapped[str] = mapped_column(String(2), primary_key=True)
    policy_sha256: Mapped[str] = mapped_column(String(64), primary_key=True)
    policy_version: Mapped[str] = mapped_column(String(128), primary_key=True)
    distance_bin: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    day: Mapped[date] = mapped_column(Date, primary_key=True)
    n: Mapped[int] = mapped_column(BigInteger)
    sum_down_m: Mapped[float] = mapped_column(Float)
    sum_cross_m: Mapped[float] = mapped_column(Float)
    sum_down2_m2: Mapped[float] = mapped_column(Float)
    sum_cross2_m2: Mapped[float] = mapped_column(Float)
    sum_down_cross_m2: Mapped[float] = mapped_column(Float)
    sum_abs_m: Mapped[float] = mapped_column(Float)


ROLES = ("viewer", "operator", "admin")
"""Roles in increasing order of rights: viewer reads, operator previews and throws, admin manages
policy versions, machines and users."""


def new_session_key() -> str:
    """A random 256-bit key, hex (64 characters): :attr:`User.session_key`."""
    return secrets.token_hex(32)


class User(Base):
    """An account. ``password_hash`` is an argon2id hash (server.accounts.auth).

    ``session_key`` is random per account and copied into each of its sessions
    (:attr:`AuthSession.user_key`); a session counts only while the two agree, so a session
    never passes to a later account that reuses a deleted account's ``id`` (SQLite reuses the
    largest rowid) and rotating the key ends every session of the account.
    """

    __tablename__ = "users"

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    username: Mapped[str] = mapped_column(String(64), unique=True)
    password_hash: Mapped[str] = mapped_column(String(255))
    role: Mapped[str] = mapped_column(String(16))
    active: Mapped[bool] = mapped_column(Boolean, default=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    session_key: Mapped[str] = mapped_column(String(64), default=new_session_key)


class AuthSession(Base):
    """A log-in: the SHA-256 of its random token (never the token itself), its expiry, and the
    ``session_key`` of the account it was made for (``user_key``, see :class:`User`)."""

    __tablename__ = "auth_sessions"

    token_sha256: Mapped[str] = mapped_column(String(64), primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"))
    user_key: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(UTCDateTime)


class AuditEntry(Base):
    """Who did what: throws, aborts, promotions, rollbacks, uploads, user changes, log-ins."""

    __tablename__ = "audit_log"
    __table_args__ = (Index("ix_audit_log_at", "at"),)

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    username: Mapped[str] = mapped_column(String(64))
    action: Mapped[str] = mapped_column(String(32))
    subject: Mapped[str | None] = mapped_column(String(128), nullable=True)
    detail: Mapped[dict] = mapped_column(JSON, default=dict)


DEPLOYMENT_STATUSES = ("offered", "active", "failed", "superseded")


class PolicyDeployment(Base):
    """One promotion (or rollback) of a policy version to one machine and mode.

    ``previous_sha256`` is what the machine ran for that mode before (rollback goes there);
    ``status``: offered -> active (the runtime confirmed) | failed (its reason).
    """

    __tablename__ = "policy_deployments"
    __table_args__ = (Index("ix_policy_deployments_machine_mode", "machine_id", "mode", "requested_at"),)

    id: Mapped[int] = mapped_column(primary_key=True, autoincrement=True)
    machine_id: Mapped[str] = mapped_column(ForeignKey("machines.id"))
    mode: Mapped[str] = mapped_column(db_enum(MODES, "mode", 2))
    policy_version_id: Mapped[int] = mapped_column(ForeignKey("policy_versions.id"))
    previous_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True)
    status: Mapped[str] = mapped_column(db_enum(DEPLOYMENT_STATUSES, "status"), default="offered")
    reason: Mapped[str | None] = mapped_column(Text, nullable=True)
    requested_by: Mapped[str | None] = mapped_column(String(64), nullable=True)
    requested_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    confirmed_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)


JobKind = Literal["preview", "evaluation", "diagnosis", "adaptation", "probe", "catalog"]
JobStatus = Literal["queued", "running", "done", "failed", "cancelled"]
JOB_KINDS: tuple[str, ...] = get_args(JobKind)
JOB_STATUSES: tuple[str, ...] = get_args(JobStatus)
FINAL_JOB_STATUSES = ("done", "failed", "cancelled")


class Job(Base):
    """One unit of heavy (MuJoCo) work run by a worker process (server.jobs).

    The queue itself lives in the job library's storage (Huey: SQLite file, PostgreSQL tables or
    Redis); this row is what people and the console see: status, progress, result.
    ``progress`` is a fraction in [0, 1]; ``result`` the job's JSON answer; ``worker`` the
    ``host:pid`` that ran it; ``cancel_requested`` is polled by the running job.
    The running worker's claim (``worker_id``, ``worker_host``, ``worker_pid``) and lease
    (``heartbeat_at``, ``lease_expires_at``, renewed by its heartbeat) let any worker re-queue
    the job when its worker died (server.jobs.leases); ``attempts`` counts starts.
    """

    __tablename__ = "jobs"
    __table_args__ = (Index("ix_jobs_kind_created", "kind", "created_at"),
                      Index("ix_jobs_status_lease", "status", "lease_expires_at"))

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=lambda: str(uuid.uuid4()))
    kind: Mapped[str] = mapped_column(db_enum(JOB_KINDS, "kind"))
    status: Mapped[str] = mapped_column(db_enum(JOB_STATUSES, "status"), default="queued")
    subject: Mapped[str | None] = mapped_column(String(128), nullable=True)
    """What the job is about: a machine id, a policy version id."""
    params: Mapped[dict] = mapped_column(JSON, default=dict)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    message: Mapped[str | None] = mapped_column(Text, nullable=True)
    result: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    worker: Mapped[str | None] = mapped_column(String(128), nullable=True)
    requested_by: Mapped[str | None] = mapped_column(String(64), nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    worker_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    worker_host: Mapped[str | None] = mapped_column(String(128), nullable=True)
    worker_pid: Mapped[int | None] = mapped_column(Integer, nullable=True)
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    lease_expires_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)


ALARM_PRIORITIES = ("high", "medium", "low")
ALARM_CAUSES = ("host_behind_real_time", "runtime_not_answering", "link_lost", "machine_fault", "drift")


class Alarm(Base):
    """One alarm (server.console.alarms, after ISA-18.2 / IEC 62682): raised by a condition, cleared
    when the condition is gone, acknowledged by an operator (who, when), possibly shelved until
    a time. It leaves the active list once it is both cleared and acknowledged; the row stays as
    the alarm history. ``key`` names the condition (one active alarm per key)."""

    __tablename__ = "alarms"
    __table_args__ = (Index("ix_alarms_raised_at", "raised_at"), Index("ix_alarms_key", "key"))

    id: Mapped[str] = mapped_column(String(36), primary_key=True, default=lambda: str(uuid.uuid4()))
    key: Mapped[str] = mapped_column(String(128))
    machine_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    priority: Mapped[str] = mapped_column(db_enum(ALARM_PRIORITIES, "priority"))
    cause: Mapped[str] = mapped_column(db_enum(ALARM_CAUSES, "cause", length=32))
    title: Mapped[str] = mapped_column(String(200))
    text: Mapped[str] = mapped_column(Text)
    todo: Mapped[str] = mapped_column(Text)
    subject: Mapped[str | None] = mapped_column(String(64), nullable=True)
    """What the alarm is about besides the machine: a throw id, a drift alert's raised_at."""
    raised_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    cleared_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    acked_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    acked_by: Mapped[str | None] = mapped_column(String(64), nullable=True)
    shelved_until: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    shelved_by: Mapped[str | None] = mapped_column(String(64), nullable=True)
    active: Mapped[bool] = mapped_column(Boolean, default=True)
    """False once cleared and acknowledged: history only."""
    revision: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    """1 when raised, one more with every change of the row (cleared, acknowledged, shelved,
    unshelved): a console orders the records of one alarm it hears by it (web/js/strip.js), so an
    answer that lands after the live event of a later change does not draw over it."""
