"""jobs: the kind ``catalog`` (the effects library described by a worker)

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-21

GET /api/diagnosis/effects submits a job of kind ``catalog`` (server.jobs.tasks.RUNNERS), which
0004's CHECK constraint ``ck_jobs_kind`` did not allow: every call answered 500. This revision
re-creates the constraint with the value added (values copied, not imported, as in 0004).
Downgrade deletes ``catalog`` jobs first (they are a cache of the library, nothing is lost).
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JOB_KINDS_0004 = ("preview", "evaluation", "diagnosis", "adaptation", "probe")
JOB_KINDS = (*JOB_KINDS_0004, "catalog")


def _recreate(values) -> None:
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_constraint("kind", type_="check")
        batch_op.create_check_constraint("kind", f"kind IN ({', '.join(repr(v) for v in values)})")


def upgrade() -> None:
    _recreate(JOB_KINDS)


def downgrade() -> None:
    op.execute("DELETE FROM jobs WHERE kind = 'catalog'")
    _recreate(JOB_KINDS_0004)
