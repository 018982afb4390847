"""operator console: users, auth sessions, audit log, policy files and deployments, throw previews

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-28

Adds ``users`` (argon2 password hashes, role), ``auth_sessions`` (SHA-256 of the bearer/cookie
token, expiry), ``audit_log`` (who did what), ``policy_deployments`` (promotions and rollbacks per
machine and mode); columns for uploaded policy versions (file, notes, twin evaluation) and for
throws (the preview they were given, who asked).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TS = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "users",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("username", sa.String(length=64), nullable=False),
        sa.Column("password_hash", sa.String(length=255), nullable=False),
        sa.Column("role", sa.String(length=16), nullable=False),
        sa.Column("active", sa.Boolean(), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_users")),
        sa.UniqueConstraint("username", name=op.f("uq_users_username")),
    )
    op.create_table(
        "auth_sessions",
        sa.Column("token_sha256", sa.String(length=64), nullable=False),
        sa.Column("user_id", sa.Integer(), nullable=False),
        sa.Column("created_at", TS, nullable=False),
        sa.Column("expires_at", TS, nullable=False),
        sa.ForeignKeyConstraint(["user_id"], ["users.id"], name=op.f("fk_auth_sessions_user_id_users"),
                                ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("token_sha256", name=op.f("pk_auth_sessions")),
    )
    op.create_table(
        "audit_log",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("at", TS, nullable=False),
        sa.Column("username", sa.String(length=64), nullable=False),
        sa.Column("action", sa.String(length=32), nullable=False),
        sa.Column("subject", sa.String(length=128), nullable=True),
        sa.Column("detail", sa.JSON(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_audit_log")),
    )
    with op.batch_alter_table("audit_log", schema=None) as batch_op:
        batch_op.create_index("ix_audit_log_at", ["at"], unique=False)
    with op.batch_alter_table("policy_versions", schema=None) as batch_op:
        batch_op.add_column(sa.Column("onnx_path", sa.String(length=512), nullable=True))
        batch_op.add_column(sa.Column("notes", sa.Text(), nullable=True))
        batch_op.add_column(sa.Column("uploaded_by", sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column("evaluation_status", sa.String(length=16), nullable=True))
        batch_op.add_column(sa.Column("metrics", sa.JSON(), nullable=True))
    op.create_table(
        "policy_deployments",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("machine_id", sa.String(length=64), nullable=False),
        sa.Column("mode", sa.String(length=2), nullable=False),
        sa.Column("policy_version_id", sa.Integer(), nullable=False),
        sa.Column("previous_sha256", sa.String(length=64), nullable=True),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("reason", sa.Text(), nullable=True),
        sa.Column("requested_by", sa.String(length=64), nullable=True),
        sa.Column("requested_at", TS, nullable=False),
        sa.Column("confirmed_at", TS, nullable=True),
        sa.ForeignKeyConstraint(["machine_id"], ["machines.id"],
                                name=op.f("fk_policy_deployments_machine_id_machines")),
        sa.ForeignKeyConstraint(["policy_version_id"], ["policy_versions.id"],
                                name=op.f("fk_policy_deployments_policy_version_id_policy_versions")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_policy_deployments")),
    )
    with op.batch_alter_table("policy_deployments", schema=None) as batch_op:
        batch_op.create_index("ix_policy_deployments_machine_mode", ["machine_id", "mode", "requested_at"], unique=False)
    with op.batch_alter_table("throws", schema=None) as batch_op:
        batch_op.add_column(sa.Column("preview", sa.JSON(), nullable=True))
        batch_op.add_column(sa.Column("requested_by", sa.String(length=64), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("throws", schema=None) as batch_op:
        batch_op.drop_column("requested_by")
        batch_op.drop_column("preview")
    with op.batch_alter_table("policy_deployments", schema=None) as batch_op:
        batch_op.drop_index("ix_policy_deployments_machine_mode")
    op.drop_table("policy_deployments")
    with op.batch_alter_table("policy_versions", schema=None) as batch_op:
        for col in ("metrics", "evaluation_status", "uploaded_by", "notes", "onnx_path"):
            batch_op.drop_column(col)
    with op.batch_alter_table("audit_log", schema=None) as batch_op:
        batch_op.drop_index("ix_audit_log_at")
    op.drop_table("audit_log")
    op.drop_table("auth_sessions")
    op.drop_table("users")
