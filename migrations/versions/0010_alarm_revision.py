"""alarm revision: one more with every change of an alarm row (server.console.alarms)

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-26

``alarms.revision``: 1 when raised, one more with every change (cleared, acknowledged, shelved,
unshelved); consoles order the records of one alarm by it. Existing rows get 1.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("alarms") as batch:
        batch.add_column(sa.Column("revision", sa.Integer(), nullable=False, server_default="1"))


def downgrade() -> None:
    with op.batch_alter_table("alarms") as batch:
        batch.drop_column("revision")
