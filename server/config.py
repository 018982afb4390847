"""Server settings from the environment (prefix ``SLINGER_``), full-stack-fastapi-template style.

Example: ``SLINGER_DATABASE_URL=postgresql+psycopg://slinger@db/slinger slinger server``.
Settings are read when :func:`get_settings` is first called, never at import time.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

from pydantic import BaseModel, Field, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from runtime.release_check import DEFAULT_RADIUS_M, parse_radius


class KeepOutZone(BaseModel):
    """A circle on the ground (machine frame) that no target may lie in."""

    name: str
    center_m: list[float] = Field(min_length=2, max_length=2)
    radius_m: float = Field(gt=0)


class Settings(BaseSettings):
    """Everything the server needs to run.

    Attributes:
        data_dir: where the SQLite database and telemetry files live (``<data_dir>/telemetry``).
        database_url: SQLAlchemy URL; default SQLite at ``<data_dir>/slinger.db``.
        host / port: HTTP bind address of the API and console.
        viser_host / viser_port: bind address of the viser 3D view (viser moves to the next free
            port if this one is busy; the console asks the server for the real one).
        viser_public_host: the host name console pages load the 3D view from (a second DNS name
            of the server's host, e.g. ``view.site.example``; letters, digits, dots and hyphens,
            or a bracketed IPv6 address). Another site than the console page's, so the browser
            draws the view in its own renderer process and the view's WebGL never holds up the
            page's E-STOP (tests/benchmarks/bench_console_estop.py). None: a page opened under a
            loopback name loads it under the other one (localhost <-> 127.0.0.1), any other page
            under its own host name (same process as the page).
        viser_enabled: start the 3D view (tests of the API alone switch it off).
        zenoh_mode: ``peer`` or ``client``.
        zenoh_listen / zenoh_connect: Zenoh endpoints, e.g. ``tcp/127.0.0.1:7447``.
        zenoh_multicast_scouting: discover peers by multicast (off by default: explicit endpoints).
        zenoh_tls_dir: a site directory of ``slinger certs``: the server's Zenoh session uses
            mutual TLS with its certificate (CN "server") and the site's access control for the
            machines of the site (``tls/`` endpoints); None: plain TCP.
        query_timeout_s: how long a Zenoh query to a runtime may take, s.
        auto_migrate: run ``alembic upgrade head`` when the app starts (skipped, with the reason
            logged and shown by /api/health, while the database's storage has a fault).
        database_busy_timeout_s: how long a request waits for SQLite's write lock before it
            answers 503 "database locked", s.
        storage_min_free_bytes: less free space than this beside a SQLite database is reported
            as ``disk_full`` (server.site.storage).
        session_ttl_s: how long a log-in stays valid, s.
        cookie_secure: always mark the session cookie Secure (it is anyway when the request came
            over HTTPS: scheme https or ``X-Forwarded-Proto: https``).
        max_body_bytes: largest request body, bytes (413 above); policy uploads have
            ``max_policy_upload_bytes``, rosbag2 uploads for a diagnosis ``max_bag_upload_bytes``.
        login_failures_per_user_address / login_failures_per_address / login_failures_per_user:
            failed log-ins allowed per window before 429, per (user name, client address), per
            address and per user name from all addresses (``limits`` notation; the per-user lock
            spares addresses the user logged in from: server.accounts.login_guard).
        trusted_proxies: addresses or networks (e.g. ``["10.0.0.5", "10.1.0.0/16"]``) of reverse
            proxies whose ``X-Forwarded-For``/``X-Forwarded-Proto`` name the client; the header
            of anyone else is ignored. Empty (default): no proxy is trusted, loopback included.
        login_workers / login_max_pending: threads checking passwords (default a quarter of the
            cores, at least 1: argon2 takes a core each), and checks queued or running at most
            (more: 429 at once).
        keep_out_zones: ground circles no target may lie in, e.g.
            ``SLINGER_KEEP_OUT_ZONES='[{"name": "truck", "center_m": [7, 3], "radius_m": 1.5}]'``.
        keep_out_scatter_sigmas / keep_out_margin_m: the preview's scatter ellipse at this many
            sigma (or, without an ellipse, its nominal impact plus the margin, m) must stay out of
            every keep-out zone (server.throws.targets.scatter_refusal; the gate's ``keep_out_scatter``).
        clearance_radius_m: the swing must stay within this horizontal distance of the turn
            axis (the machine's clearance zone), m.
        release_check_radius_m: the release check's radius, m, or None ("off"): given to the
            runtimes that ``slinger up`` starts (``--release-check-radius``) and to every preview
            (sim_twin.preview.preview.PreviewRequest), so that a preview holds a release as the machine
            would (runtime.release_check; env ``SLINGER_RELEASE_CHECK_RADIUS_M``, default 3.0).
        preview_rollouts: Monte Carlo rollouts of a full preview (1 sigma impact ellipse).
        preview_processes: processes a worker runs the Monte Carlo's full rollouts in (a pool
            started with the worker and kept; 0 or 1: in the worker's own thread). Default 2: on
            2 cores the 200-rollout ellipse takes about 40 % of its one-process time
            (tests/benchmarks/bench_preview.py).
        preview_profile: the site's reality profile with its uncertainty block (parameter ranges,
            start-state model; sim_twin.twin.uncertainty) that previews sample; default
            sim_twin/profiles/nominal_uncertain.json. A policy version adapted to a diagnosed site
            (``slinger adapt``) carries its own fitted profile, which then takes precedence.
        eval_distances_m / eval_throws: the small twin evaluation of an uploaded policy version
            (throws per distance); empty distances: the policy's trained range in 3 steps.
        require_validation: a policy version is promoted only after it passed its validation
            (server.policies.validation; a rollback is not checked).
        validation_observations / validation_distances / validation_throws_per_distance: the
            validation's observation sweep, and its twin throws over the declared target range
            (distances spanning it, random start poses each).
        validation_memory_mb / validation_time_s: limits of one validation's child process
            (exceeded: the version fails validation with that reason).
        site_dir: the site directory of ``slinger certs`` (command keys in
            ``machines/<id>/command.key``); default ``<data_dir>/site``.
        require_preview: a throw needs a fresh OK preview of the same request (server.throws.gate);
            only tests of unrelated parts switch it off.
        preview_max_age_s / preview_target_tolerance_m / preview_max_active_joint_delta /
            preview_max_passive_joint_delta: the gate's bounds (server.throws.gate.GateLimits).
        reconcile_period_s / result_grace_s / runtime_gone_s: bounds of the reconciliation of
            open throws (server.fleet.reconcile), s.
        preview_timeout_s: how long the API awaits a worker's preview before answering 503 (the
            bar for a preview is 3 s; this limit only keeps a request from waiting forever).
        job_queue_url: the job queue of the workers (server.jobs.queue): ``sqlite:///FILE``,
            ``postgresql://...`` or ``redis://...``; empty: SQLite ``<data_dir>/jobs.db``;
            ``immediate``: run jobs inside the submitting process (tests only).
    """

    model_config = SettingsConfigDict(env_prefix="SLINGER_", env_file=None, extra="ignore")

    data_dir: Path = Path("var")
    database_url: str = ""
    host: str = "127.0.0.1"
    port: int = 8000
    viser_host: str = "127.0.0.1"
    viser_port: int = 8080
    viser_public_host: str | None = Field(None, pattern=r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]{1,253})$")
    viser_enabled: bool = True
    zenoh_mode: str = "peer"
    zenoh_listen: list[str] = Field(default_factory=list)
    zenoh_connect: list[str] = Field(default_factory=list)
    zenoh_multicast_scouting: bool = False
    zenoh_tls_dir: Path | None = None
    query_timeout_s: float = 5.0
    auto_migrate: bool = False
    database_busy_timeout_s: float = Field(10.0, gt=0)
    storage_min_free_bytes: int = Field(8 << 20, ge=0)
    session_ttl_s: float = 12 * 3600.0
    cookie_secure: bool = False
    max_body_bytes: int = Field(1 << 20, ge=1024)
    max_policy_upload_bytes: int = Field(64 << 20, ge=1024)
    max_bag_upload_bytes: int = Field(512 << 20, ge=1024)
    login_failures_per_user_address: str = "5/5minutes"
    login_failures_per_address: str = "20/5minutes"
    login_failures_per_user: str = "100/5minutes"
    trusted_proxies: list[str] = Field(default_factory=list)
    login_workers: int = Field(default_factory=lambda: max(1, (os.cpu_count() or 2) // 4), ge=1, le=16)
    login_max_pending: int = Field(8, ge=1, le=256)
    keep_out_zones: list[KeepOutZone] = Field(default_factory=list)
    clearance_radius_m: float = 12.0
    release_check_radius_m: float | None = DEFAULT_RADIUS_M
    preview_rollouts: int = 200
    preview_processes: int = Field(default=2, ge=0, le=64)
    preview_profile: Path | None = None
    eval_distances_m: list[float] = Field(default_factory=list)
    eval_throws: int = 4
    require_validation: bool = True
    validation_observations: int = Field(4096, ge=1)
    validation_distances: int = Field(5, ge=0)
    validation_throws_per_distance: int = Field(20, ge=0)
    validation_memory_mb: int = Field(1024, ge=64)
    validation_time_s: float = Field(600.0, gt=0)
    site_dir: Path | None = None
    require_preview: bool = True
    preview_max_age_s: float = Field(60.0, gt=0)
    preview_target_tolerance_m: float = Field(0.05, ge=0)
    preview_max_active_joint_delta: float = Field(0.05, gt=0)
    preview_max_passive_joint_delta: float = Field(0.3, gt=0)
    keep_out_scatter_sigmas: float = Field(3.0, gt=0)
    keep_out_margin_m: float = Field(0.6, ge=0)
    reconcile_period_s: float = Field(2.0, gt=0)
    result_grace_s: float = Field(15.0, gt=0)
    runtime_gone_s: float = Field(30.0, gt=0)
    job_queue_url: str = ""
    drift_webhook_url: str = ""
    """POST every drift alert (server.analysis.drift) to this URL as JSON; empty: none."""
    preview_timeout_s: float = 15.0

    @field_validator("release_check_radius_m", mode="before")
    @classmethod
    def _radius(cls, value):
        return parse_radius(value)

    @model_validator(mode="after")
    def _default_database(self) -> Settings:
        if not self.database_url:
            self.database_url = f"sqlite:///{(self.data_dir / 'slinger.db').as_posix()}"
        return self

    @property
    def resolved_site_dir(self) -> Path:
        """The site directory (``site_dir``, default ``<data_dir>/site``)."""
        return self.site_dir if self.site_dir is not None else self.data_dir / "site"

    @property
    def telemetry_dir(self) -> Path:
        """Directory of the per-throw MCAP files."""
        return self.data_dir / "telemetry"


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings, read from the environment on first call."""
    return Settings()
