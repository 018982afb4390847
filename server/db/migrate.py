"""Run Alembic migrations programmatically (``slinger db upgrade``, app startup, tests).

The Alembic config is ``server/alembic.ini`` (shipped as package data); its script location is
set here: the ``migrations`` package (the repository's ``migrations/`` folder, installed as a
package by every install: ``pip install .``, the slinger-server wheel, an editable install),
found through importlib.resources from any working directory.
"""

from __future__ import annotations

import logging
from importlib import resources
from pathlib import Path

from alembic import command
from alembic.config import Config

log = logging.getLogger(__name__)

SERVER_DIR = Path(__file__).resolve().parent.parent
ALEMBIC_INI = SERVER_DIR / "alembic.ini"


def migrations_dir() -> Path:
    """The folder of the ``migrations`` package (env.py, versions/).

    Raises:
        FileNotFoundError: the package is not installed or has no env.py (a broken install).
    """
    try:
        folder = Path(str(resources.files("migrations")))
    except ModuleNotFoundError as e:
        raise FileNotFoundError(f"Alembic migrations not found: the 'migrations' package is not installed ({e})") from e
    if not (folder / "env.py").is_file():
        raise FileNotFoundError(f"Alembic migrations not found at {folder}")
    return folder


def alembic_config(database_url: str) -> Config:
    """An Alembic config for ``database_url``.

    Raises:
        FileNotFoundError: the migrations package is missing (:func:`migrations_dir`).
    """
    folder = migrations_dir()
    cfg = Config(str(ALEMBIC_INI))
    cfg.set_main_option("script_location", str(folder))
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
