"""throws: the runtime epoch a throw was sent to (reconciliation; status ``lost``)

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-21

``throws.status`` is a free string column; this revision adds no constraint, the new final
status ``lost`` (server.db.models.THROW_STATUSES) needs none. The reason of a lost throw goes to
the existing ``failure_reason`` column. ``runtime_epoch`` is the claim epoch (ms since the Unix
epoch at the runtime's start) of the runtime that accepted the throw.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("throws", schema=None) as batch_op:
        batch_op.add_column(sa.Column("runtime_epoch", sa.BigInteger(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("throws", schema=None) as batch_op:
        batch_op.drop_column("runtime_epoch")
