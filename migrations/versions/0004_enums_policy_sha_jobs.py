"""modes and statuses as database enums, throws keyed by policy SHA-256, the jobs table

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-21

* CHECK constraints (server.db.models.db_enum) on ``throws.mode``/``status``,
  ``policy_versions.mode``/``evaluation_status``, ``policy_deployments.mode``/``status``.
  Values are copied from server.db.models at the time of writing, NOT imported, so that this
  revision means the same thing forever; a later revision that adds a value drops and re-creates
  the constraint.
* ``throws.policy_sha256`` (the ONNX file's SHA-256; names are not unique), filled for existing
  throws from ``policy_versions`` where the version name maps to exactly one file, with an index
  for accuracy and comparisons grouped by it.
* ``jobs``: heavy work run by worker processes (server.jobs).
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TS = sa.DateTime(timezone=True)
MODES = ("2d", "3d")
THROW_STATUSES = ("requested", "preparing", "swinging", "released", "landed", "failed", "aborted", "lost")
EVALUATION_STATUSES = ("pending", "running", "done", "failed")
DEPLOYMENT_STATUSES = ("offered", "active", "failed", "superseded")
JOB_KINDS = ("preview", "evaluation", "diagnosis", "adaptation", "probe")
JOB_STATUSES = ("queued", "running", "done", "failed", "cancelled")

CHECKS = {  # table -> [(constraint suffix = enum name, column, values)]
    "throws": [("mode", "mode", MODES), ("status", "status", THROW_STATUSES)],
    "policy_versions": [("mode", "mode", MODES), ("evaluation_status", "evaluation_status", EVALUATION_STATUSES)],
    "policy_deployments": [("mode", "mode", MODES), ("status", "status", DEPLOYMENT_STATUSES)],
}


def _in(column: str, values) -> str:
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


def _enum(values, name: str, length: int = 16) -> sa.Enum:
    return sa.Enum(*values, name=name, native_enum=False, create_constraint=True, length=length)


def upgrade() -> None:
    for table, checks in CHECKS.items():
        with op.batch_alter_table(table, schema=None) as batch_op:
            for name, column, values in checks:
                batch_op.create_check_constraint(name, _in(column, values))
    with op.batch_alter_table("throws", schema=None) as batch_op:
        batch_op.add_column(sa.Column("policy_sha256", sa.String(length=64), nullable=True))
        batch_op.create_index("ix_throws_policy_sha256", ["policy_sha256", "requested_at"], unique=False)
    op.execute(
        "UPDATE throws SET policy_sha256 = (SELECT MIN(p.sha256) FROM policy_versions p "
        "WHERE p.name = throws.policy_version AND p.mode = throws.mode) "
        "WHERE policy_version IS NOT NULL AND (SELECT COUNT(*) FROM policy_versions p "
        "WHERE p.name = throws.policy_version AND p.mode = throws.mode) = 1")
    op.create_table(
        "jobs",
        sa.Column("id", sa.String(length=36), nullable=False),
        sa.Column("kind", _enum(JOB_KINDS, "kind"), nullable=False),
        sa.Column("status", _enum(JOB_STATUSES, "status"), nullable=False),
        sa.Column("subject", sa.String(length=128), nullable=True),
        sa.Column("params", sa.JSON(), nullable=False),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("message", sa.Text(), nullable=True),
        sa.Column("result", sa.JSON(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("cancel_requested", sa.Boolean(), nullable=False),
        sa.Column("worker", sa.String(length=128), nullable=True),
        sa.Column("requested_by", sa.String(length=64), nullable=True),
        sa.Column("created_at", TS, nullable=False),
        sa.Column("started_at", TS, nullable=True),
        sa.Column("finished_at", TS, nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_jobs")),
    )
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.create_index("ix_jobs_kind_created", ["kind", "created_at"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_index("ix_jobs_kind_created")
    op.drop_table("jobs")
    with op.batch_alter_table("throws", schema=None) as batch_op:
        batch_op.drop_index("ix_throws_policy_sha256")
        batch_op.drop_column("policy_sha256")
    for table, checks in CHECKS.items():
        with op.batch_alter_table(table, schema=None) as batch_op:
            for name, _column, _values in checks:
                batch_op.drop_constraint(name, type_="check")
