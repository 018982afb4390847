"""jobs: worker leases (heartbeats) and attempts, so that jobs of dead workers are re-run

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-21

``jobs`` gains the claim of the worker running a job (``worker_id``: a random id per worker
process, ``worker_host``, ``worker_pid``), its last ``heartbeat_at`` and ``lease_expires_at``
(written by the running worker every few seconds), and ``attempts`` (how often a worker started
it). A worker on any host that sees an expired lease (or, on the same host, a dead pid) re-queues
the job, up to a limit of attempts, then fails it with the reason (server.jobs.leases).
Numbered 0007: it follows 0006 (accuracy aggregates), written at the same time on another branch.
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

TS = sa.DateTime(timezone=True)


def upgrade() -> None:
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("attempts", sa.Integer(), nullable=False, server_default="0"))
        batch_op.add_column(sa.Column("worker_id", sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column("worker_host", sa.String(length=128), nullable=True))
        batch_op.add_column(sa.Column("worker_pid", sa.Integer(), nullable=True))
        batch_op.add_column(sa.Column("heartbeat_at", TS, nullable=True))
        batch_op.add_column(sa.Column("lease_expires_at", TS, nullable=True))
        batch_op.create_index("ix_jobs_status_lease", ["status", "lease_expires_at"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_index("ix_jobs_status_lease")
        for column in ("lease_expires_at", "heartbeat_at", "worker_pid", "worker_host", "worker_id", "attempts"):
            batch_op.drop_column(column)
