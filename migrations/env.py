"""Alembic environment of the Slinger server.

URL: the config's ``sqlalchemy.url`` when the caller set one (server.db.migrate), else
``server.config.get_settings().database_url`` (env ``SLINGER_DATABASE_URL``).

SQLite pitfall handled: SQLite cannot ALTER most things, so migrations run in batch mode
(``render_as_batch=True``: copy-and-move tables) and every constraint is named by the models'
naming convention, without which batch mode cannot drop or alter unnamed constraints.
Logging is configured from the ini only when Alembic runs from its own CLI, so that calling
migrations from the server does not disable the application's loggers.
"""

from __future__ import annotations

from logging.config import fileConfig

from alembic import context
from sqlalchemy import engine_from_config, pool

from server.db.models import Base

config = context.config

if config.config_file_name is not None and config.attributes.get("configure_logging", True):
    fileConfig(config.config_file_name, disable_existing_loggers=False)

target_metadata = Base.metadata


def _url() -> str:
    url = config.get_main_option("sqlalchemy.url")
    if url:
        return url
    from server.config import get_settings

    return get_settings().database_url


def run_migrations_offline() -> None:
    """Emit SQL to stdout (``alembic upgrade head --sql``)."""
    url = _url()
    context.configure(
        url=url,
        target_metadata=target_metadata,
        literal_binds=True,
        dialect_opts={"paramstyle": "named"},
        render_as_batch=url.startswith("sqlite"),
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    """Run against a live connection (one given in ``config.attributes['connection']`` or a new one)."""
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    section = config.get_section(config.config_ini_section, {})
    section["sqlalchemy.url"] = _url()
    engine = engine_from_config(section, prefix="sqlalchemy.", poolclass=pool.NullPool)
    with engine.connect() as conn:
        _run(conn)
    engine.dispose()


def _ours(name, type_, _parent_names) -> bool:
    """Tables of the job queue (Huey's PostgresStorage, prefix ``huey_``) are not ours: keep them
    out of comparisons (``alembic check``)."""
    return not (type_ == "table" and name and name.startswith("huey_"))


def _run(connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        include_name=_ours,
        render_as_batch=connection.dialect.name == "sqlite",
        compare_type=True,
    )
    with context.begin_transaction():
        context.run_migrations()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
