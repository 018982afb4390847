"""Inserts that concurrent writers of the same key cannot fail, on the two databases Slinger
supports (SQLite and PostgreSQL both have ``INSERT ... ON CONFLICT``)."""

from __future__ import annotations

from typing import Any

from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session


def dialect_insert(dialect: str, model: type) -> postgresql.Insert | sqlite.Insert:
    """The ``INSERT`` of ``model`` in ``dialect``'s own form (the one with ``on_conflict_do_*``).

    Raises:
        NotImplementedError: ``dialect`` is neither ``"sqlite"`` nor ``"postgresql"``.
    """
    if dialect == "postgresql":
        return postgresql.insert(model)
    if dialect == "sqlite":
        return sqlite.insert(model)
    raise NotImplementedError(f"{dialect}: Slinger's database is SQLite or PostgreSQL")


def insert_if_absent(db: Session, model: type, key: list[str], **values: Any) -> bool:
    """``INSERT ... ON CONFLICT (key) DO NOTHING`` of one ``model`` row inside ``db``'s transaction:
    the get-or-add that two writers racing for the same key cannot fail (a SELECT then an add
    lets both see no row; the second commit then fails on the unique constraint). The database
    serialises the two inserts: the second waits for the first's transaction and inserts nothing.
    Column defaults apply as for an ORM add. Returns True when this call inserted the row
    (read from ``RETURNING``: SQLite 3.35 or later, PostgreSQL 9.5 or later).

    Raises:
        NotImplementedError: the database is neither SQLite nor PostgreSQL.
    """
    table = model.__table__  # type: ignore[attr-defined]
    stmt = (dialect_insert(db.get_bind().dialect.name, model).values(**values).on_conflict_do_nothing(index_elements=key)
            .returning(*table.primary_key.columns))  # psycopg reports no row count for it: a row back = inserted
    return db.execute(stmt).first() is not None
