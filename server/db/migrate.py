"""Run Alembic migrations programmatically (``slinger db upgrade``, app startup, tests).

The Alembic config is ``server/alembic.ini`` (shipped as package data); its script location is
set here: ``server/migrations`` inside an installed slinger-server wheel (packaging/: the
migrations are package data), else the repository's ``migrations/`` folder (the repo, an
editable install), from any working directory.
"""

from __future__ import annotations

import logging
from pathlib import Path

from alembic import command
from alembic.config import Config

log = logging.getLogger(__name__)

SERVER_DIR = Path(__file__).resolve().parent.parent
ALEMBIC_INI = SERVER_DIR / "alembic.ini"
MIGRATIONS_DIR = next((d for d in (SERVER_DIR / "migrations", SERVER_DIR.parent / "migrations")
                       if (d / "env.py").is_file()), SERVER_DIR.parent / "migrations")


def alembic_config(database_url: str) -> Config:
    """An Alembic config for ``database_url``.

    Raises:
        FileNotFoundError: if the migrations folder is missing (an install of the all-in-one
            root package without -e; install slinger-server, or ``pip install -e .``).
    """
    if not (MIGRATIONS_DIR / "env.py").is_file():
        raise FileNotFoundError(f"Alembic migrations not found at {MIGRATIONS_DIR}")
    cfg = Config(str(ALEMBIC_INI))
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    # '%' is interpolation syntax in ini files; escape it in passwords etc.
    cfg.set_main_option("sqlalchemy.url", database_url.replace("%", "%%"))
    cfg.attributes["configure_logging"] = False
    return cfg


def upgrade(database_url: str, revision: str = "head") -> None:
    """``alembic upgrade <revision>`` on ``database_url``; creates a SQLite file's folder."""
    _ensure_sqlite_dir(database_url)
    log.info("alembic upgrade %s on %s", revision, _redact(database_url))
    command.upgrade(alembic_config(database_url), revision)


def downgrade(database_url: str, revision: str = "base") -> None:
    """``alembic downgrade <revision>`` on ``database_url``."""
    command.downgrade(alembic_config(database_url), revision)


def _ensure_sqlite_dir(database_url: str) -> None:
    prefix = "sqlite:///"
    if database_url.startswith(prefix) and ":memory:" not in database_url:
        Path(database_url[len(prefix):]).parent.mkdir(parents=True, exist_ok=True)


def _redact(url: str) -> str:
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)
