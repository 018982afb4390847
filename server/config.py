"""Server settings from the environment (prefix ``SLINGER_``), full-stack-fastapi-template style.

Example: ``SLINGER_DATABASE_URL=postgresql+psycopg://slinger@db/slinger slinger server``.
Settings are read when :func:`get_settings` is first called, never at import time.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import BaseModel, Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


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
        viser_enabled: start the 3D view (tests of the API alone switch it off).
        zenoh_mode: ``peer`` or ``client``.
        zenoh_listen / zenoh_connect: Zenoh endpoints, e.g. ``tcp/127.0.0.1:7447``.
        zenoh_multicast_scouting: discover peers by multicast (off by default: explicit endpoints).
        query_timeout_s: how long a Zenoh query to a runtime may take, s.
        auto_migrate: run ``alembic upgrade head`` when the app starts.
        session_ttl_s: how long a log-in stays valid, s.
        cookie_secure: mark the session cookie Secure (serve over HTTPS).
        keep_out_zones: ground circles no target may lie in, e.g.
            ``SLINGER_KEEP_OUT_ZONES='[{"name": "truck", "center_m": [7, 3], "radius_m": 1.5}]'``.
        clearance_radius_m: the swing must stay within this horizontal distance of the turn
            axis (the machine's clearance zone), m.
        preview_rollouts: Monte Carlo rollouts of a full preview (1 sigma impact ellipse).
        eval_distances_m / eval_throws: the small twin evaluation of an uploaded policy version
            (throws per distance); empty distances: the policy's trained range in 3 steps.
    """

    model_config = SettingsConfigDict(env_prefix="SLINGER_", env_file=None, extra="ignore")

    data_dir: Path = Path("var")
    database_url: str = ""
    host: str = "127.0.0.1"
    port: int = 8000
    viser_host: str = "127.0.0.1"
    viser_port: int = 8080
    viser_enabled: bool = True
    zenoh_mode: str = "peer"
    zenoh_listen: list[str] = Field(default_factory=list)
    zenoh_connect: list[str] = Field(default_factory=list)
    zenoh_multicast_scouting: bool = False
    query_timeout_s: float = 5.0
    auto_migrate: bool = False
    session_ttl_s: float = 12 * 3600.0
    cookie_secure: bool = False
    keep_out_zones: list[KeepOutZone] = Field(default_factory=list)
    clearance_radius_m: float = 12.0
    preview_rollouts: int = 200
    eval_distances_m: list[float] = Field(default_factory=list)
    eval_throws: int = 4

    @model_validator(mode="after")
    def _default_database(self) -> "Settings":
        if not self.database_url:
            self.database_url = f"sqlite:///{(self.data_dir / 'slinger.db').as_posix()}"
        return self

    @property
    def telemetry_dir(self) -> Path:
        """Directory of the per-throw MCAP files."""
        return self.data_dir / "telemetry"


@lru_cache
def get_settings() -> Settings:
    """The process-wide settings, read from the environment on first call."""
    return Settings()
