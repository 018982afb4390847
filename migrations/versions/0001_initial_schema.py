"""initial schema: machines, policy_versions, throws

Revision ID: 0001
Revises:
Create Date: 2026-11-21

Timestamps are ``DateTime(timezone=True)`` (timestamptz on PostgreSQL; on SQLite the app's
UTCDateTime type stores UTC and re-attaches the zone). Constraint names follow
server.db.models.NAMING_CONVENTION so batch migrations on SQLite can address them.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TS = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "machines",
        sa.Column("id", sa.String(length=64), nullable=False),
        sa.Column("simulated", sa.Boolean(), nullable=False),
        sa.Column("first_seen_at", TS, nullable=False),
        sa.Column("last_seen_at", TS, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_machines")),
    )
    op.create_table(
        "policy_versions",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("name", sa.String(length=128), nullable=False),
        sa.Column("mode", sa.String(length=2), nullable=False),
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.Column("manifest", sa.JSON(), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_policy_versions")),
        sa.UniqueConstraint("sha256", name=op.f("uq_policy_versions_sha256")),
    )
    op.create_table(
        "throws",
        sa.Column("id", sa.String(length=36), nullable=False),
        sa.Column("machine_id", sa.String(length=64), nullable=False),
        sa.Column("mode", sa.String(length=2), nullable=False),
        sa.Column("target_x_m", sa.Float(), nullable=False),
        sa.Column("target_y_m", sa.Float(), nullable=False),
        sa.Column("target_z_m", sa.Float(), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("failure_reason", sa.Text(), nullable=True),
        sa.Column("impact_x_m", sa.Float(), nullable=True),
        sa.Column("impact_y_m", sa.Float(), nullable=True),
        sa.Column("impact_z_m", sa.Float(), nullable=True),
        sa.Column("downrange_error_m", sa.Float(), nullable=True),
        sa.Column("crossrange_error_m", sa.Float(), nullable=True),
        sa.Column("policy_version", sa.String(length=128), nullable=True),
        sa.Column("requested_at", TS, nullable=False),
        sa.Column("started_at", TS, nullable=True),
        sa.Column("released_at", TS, nullable=True),
        sa.Column("completed_at", TS, nullable=True),
        sa.Column("duration_s", sa.Float(), nullable=True),
        sa.Column("telemetry_path", sa.String(length=512), nullable=True),
        sa.ForeignKeyConstraint(
            ["machine_id"], ["machines.id"], name=op.f("fk_throws_machine_id_machines")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_throws")),
    )
    with op.batch_alter_table("throws", schema=None) as batch_op:
        batch_op.create_index("ix_throws_machine_requested", ["machine_id", "requested_at"], unique=False)
        batch_op.create_index("ix_throws_requested_at", ["requested_at"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("throws", schema=None) as batch_op:
        batch_op.drop_index("ix_throws_requested_at")
        batch_op.drop_index("ix_throws_machine_requested")
    op.drop_table("throws")
    op.drop_table("policy_versions")
    op.drop_table("machines")
