"""throw_accuracy: incremental accuracy aggregates of the landed throws, backfilled

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-21

One row per (machine, mode, policy SHA-256, policy name, target-distance bin, UTC day) with the
count and sums of the landed throws' errors (server.db.models.ThrowAccuracy; kept up to date by
server.db.aggregates in the transaction that changes a throw). The backfill sums the existing
landed throws in Python, with the key and sums as server.db.aggregates defines them at the time
of writing (copied, not imported, so this revision means the same thing forever; a test checks
that the backfill equals the live aggregates). Downgrade drops the table (derived data only).
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from datetime import UTC

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

BIN_M = 0.5
KEYS = ("machine_id", "mode", "policy_sha256", "policy_version", "distance_bin", "day")
SUMS = ("n", "sum_down_m", "sum_cross_m", "sum_down2_m2", "sum_cross2_m2", "sum_down_cross_m2", "sum_abs_m")


def upgrade() -> None:
    table = op.create_table(
        "throw_accuracy",
        sa.Column("machine_id", sa.String(length=64), nullable=False),
        sa.Column("mode", sa.String(length=2), nullable=False),
        sa.Column("policy_sha256", sa.String(length=64), nullable=False),
        sa.Column("policy_version", sa.String(length=128), nullable=False),
        sa.Column("distance_bin", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("day", sa.Date(), nullable=False),
        sa.Column("n", sa.BigInteger(), nullable=False),
        *(sa.Column(c, sa.Float(), nullable=False) for c in SUMS[1:]),
        sa.PrimaryKeyConstraint(*KEYS, name=op.f("pk_throw_accuracy")),
    )
    _backfill(table)


def _backfill(table: sa.Table) -> None:
    throws = sa.table("throws", *(sa.column(c) for c in (
        "machine_id", "mode", "policy_sha256", "policy_version", "target_x_m", "target_y_m", "status",
        "downrange_error_m", "crossrange_error_m")), sa.column("requested_at", sa.DateTime(timezone=True)))
    sums: dict[tuple, list] = defaultdict(lambda: [0] + [0.0] * (len(SUMS) - 1))
    rows = op.get_bind().execute(sa.select(
        throws.c.machine_id, throws.c.mode, throws.c.policy_sha256, throws.c.policy_version, throws.c.target_x_m,
        throws.c.target_y_m, throws.c.requested_at, throws.c.downrange_error_m, throws.c.crossrange_error_m,
    ).where(throws.c.status == "landed", throws.c.downrange_error_m.is_not(None),
            throws.c.crossrange_error_m.is_not(None)))
    for machine, mode, sha, version, x, y, at, down, cross in rows:
        day = (at.astimezone(UTC) if at.tzinfo else at).date()  # SQLite: naive UTC
        key = (machine, mode, sha or "", version or "", math.floor(math.sqrt(x * x + y * y) / BIN_M + 0.5), day)
        acc = sums[key]
        for i, s in enumerate((1, down, cross, down * down, cross * cross, down * cross,
                               math.sqrt(down * down + cross * cross))):
            acc[i] += s
    if sums:
        op.bulk_insert(table, [dict(zip(KEYS, k)) | dict(zip(SUMS, s)) for k, s in sums.items()])


def downgrade() -> None:
    op.drop_table("throw_accuracy")
