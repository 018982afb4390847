"""Server settings from the environment (prefix ``SLINGER_``), full-stack-fastapi-template style.

Example: ``SLINGER_DATABASE_URL=postgresql+psycopg://slinger@db/slinger slinger server``.
Settings are read when :func:`get_settings` is first called, never at import time.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


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
