"""alarms kept on the server (server.console.alarms)

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-25

``alarms``: one row per raised alarm (ISA-18.2 states: raised, acknowledged by whom and when,
cleared, shelved until a time), kept as the alarm history once it is cleared and acknowledged.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

PRIORITIES = ("high", "medium", "low")
TS = sa.DateTime(timezone=True)
CAUSES = ("host_behind_real_time", "runtime_not_answering", "link_lost", "machine_fault", "drift")


def upgrade() -> None:
    op.create_table(
        "alarms",
        sa.Column("id", sa.String(length=36), nullable=False),
        sa.Column("key", sa.String(length=128), nullable=False),
        sa.Column("machine_id", sa.String(length=64), nullable=True),
        sa.Column("priority", sa.Enum(*PRIORITIES, name="priority", native_enum=False, create_constraint=True,
                                      length=16), nullable=False),
        sa.Column("cause", sa.Enum(*CAUSES, name="cause", native_enum=False, create_constraint=True, length=32),
                  nullable=False),
        sa.Column("title", sa.String(length=200), nullable=False),
        sa.Column("text", sa.Text(), nullable=False),
        sa.Column("todo", sa.Text(), nullable=False),
        sa.Column("subject", sa.String(length=64), nullable=True),
        sa.Column("raised_at", TS, nullable=False),
        sa.Column("cleared_at", TS, nullable=True),
        sa.Column("acked_at", TS, nullable=True),
        sa.Column("acked_by", sa.String(length=64), nullable=True),
        sa.Column("shelved_until", TS, nullable=True),
        sa.Column("shelved_by", sa.String(length=64), nullable=True),
        sa.Column("active", sa.Boolean(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_alarms")),
    )
    op.create_index("ix_alarms_raised_at", "alarms", ["raised_at"])
    op.create_index("ix_alarms_key", "alarms", ["key"])


def downgrade() -> None:
    op.drop_index("ix_alarms_key", table_name="alarms")
    op.drop_index("ix_alarms_raised_at", table_name="alarms")
    op.drop_table("alarms")
