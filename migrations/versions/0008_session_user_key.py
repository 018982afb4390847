"""auth sessions bound to the account they were made for (a random per-user key)

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-22

``users`` gains ``session_key`` (random 256 bits, hex; server.db.models.new_session_key) and
``auth_sessions`` gains ``user_key``, the account's key when the session was made. server.accounts.auth
accepts a session only while the two agree, so a session of a deleted account never passes to a
new account that SQLite gives the same ``id``. Existing sessions are kept (each gets its
account's new key); sessions whose account is gone are deleted. On SQLite a trigger deletes an
account's sessions with the account even when foreign keys are off (the sqlite3 command-line
shell's default), where ``ON DELETE CASCADE`` does nothing.
"""

from __future__ import annotations

import secrets
from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TRIGGER = "trg_users_delete_auth_sessions"


def upgrade() -> None:
    bind = op.get_bind()
    with op.batch_alter_table("users", schema=None) as batch_op:
        batch_op.add_column(sa.Column("session_key", sa.String(length=64), nullable=True))
    with op.batch_alter_table("auth_sessions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("user_key", sa.String(length=64), nullable=True))
    users = sa.table("users", sa.column("id", sa.Integer), sa.column("session_key", sa.String))
    sessions = sa.table("auth_sessions", sa.column("user_id", sa.Integer), sa.column("user_key", sa.String))
    for (user_id,) in bind.execute(sa.select(users.c.id)).all():
        key = secrets.token_hex(32)
        bind.execute(users.update().where(users.c.id == user_id).values(session_key=key))
        bind.execute(sessions.update().where(sessions.c.user_id == user_id).values(user_key=key))
    bind.execute(sessions.delete().where(sessions.c.user_key.is_(None)))
    with op.batch_alter_table("users", schema=None) as batch_op:
        batch_op.alter_column("session_key", existing_type=sa.String(length=64), nullable=False)
    with op.batch_alter_table("auth_sessions", schema=None) as batch_op:
        batch_op.alter_column("user_key", existing_type=sa.String(length=64), nullable=False)
    if bind.dialect.name == "sqlite":
        op.execute(f"CREATE TRIGGER {TRIGGER} AFTER DELETE ON users FOR EACH ROW "
                   "BEGIN DELETE FROM auth_sessions WHERE user_id = OLD.id; END")


def downgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        op.execute(f"DROP TRIGGER IF EXISTS {TRIGGER}")
    with op.batch_alter_table("auth_sessions", schema=None) as batch_op:
        batch_op.drop_column("user_key")
    with op.batch_alter_table("users", schema=None) as batch_op:
        batch_op.drop_column("session_key")
