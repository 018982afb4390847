"""Throw history queries: filters, sorting and pagination in SQL; CSV export. Accuracy
statistics (per mode, policy version and target distance) are in :mod:`server.analysis.accuracy`.

A policy version is identified by its ONNX file's SHA-256 (``throws.policy_sha256``; names are
not unique). Target distance is the horizontal distance of the target from the turn axis;
filters compare squared distances.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import Select, func, select

from server.db.models import Throw

_DIST2 = Throw.target_x_m * Throw.target_x_m + Throw.target_y_m * Throw.target_y_m
SORTS = {
    "requested_at": Throw.requested_at, "machine_id": Throw.machine_id, "mode": Throw.mode,
    "policy_version": Throw.policy_version, "policy_sha256": Throw.policy_sha256, "status": Throw.status, "target_distance": _DIST2,
    "downrange_error": Throw.downrange_error_m, "crossrange_error": Throw.crossrange_error_m,
    "duration": Throw.duration_s,
}


@dataclass
class ThrowFilter:
    """History filters; None means "any". Distances in m, times UTC-aware."""

    machine_id: str | None = None
    policy_version: str | None = None
    mode: str | None = None
    status: str | None = None
    min_distance_m: float | None = None
    max_distance_m: float | None = None
    since: datetime | None = None
    until: datetime | None = None
    policy_sha256: str | None = None

    def apply(self, stmt: Select) -> Select:
        for col, value in ((Throw.machine_id, self.machine_id), (Throw.policy_version, self.policy_version),
                           (Throw.mode, self.mode), (Throw.status, self.status),
                           (Throw.policy_sha256, self.policy_sha256)):
            if value:
                stmt = stmt.where(col == value)
        if self.min_distance_m is not None:
            stmt = stmt.where(_DIST2 >= self.min_distance_m ** 2)
        if self.max_distance_m is not None:
            stmt = stmt.where(_DIST2 <= self.max_distance_m ** 2)
        if self.since is not None:
            stmt = stmt.where(Throw.requested_at >= self.since)
        if self.until is not None:
            stmt = stmt.where(Throw.requested_at <= self.until)
        return stmt


def page(db, flt: ThrowFilter, sort: str = "requested_at", order: str = "desc", limit: int = 50,
         offset: int = 0) -> tuple[list[Throw], int]:
    """(rows of one page, total matching rows)."""
    col = SORTS[sort]
    key = col.desc() if order == "desc" else col.asc()
    total = db.scalar(flt.apply(select(func.count()).select_from(Throw)))
    rows = list(db.scalars(flt.apply(select(Throw)).order_by(key, Throw.id).limit(limit).offset(offset)))
    return rows, int(total or 0)


CSV_COLUMNS = ["id", "machine_id", "mode", "policy_version", "policy_sha256", "status", "failure_reason", "requested_at",
               "target_x_m", "target_y_m", "target_z_m", "target_distance_m", "impact_x_m", "impact_y_m",
               "impact_z_m", "downrange_error_m", "crossrange_error_m", "duration_s", "requested_by",
               "predicted_downrange_error_m", "predicted_crossrange_error_m"]


def to_csv(rows: list[Throw]) -> str:
    """The rows as CSV (header: CSV_COLUMNS)."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(CSV_COLUMNS)
    for t in rows:
        p = t.preview or {}
        w.writerow([t.id, t.machine_id, t.mode, t.policy_version or "", t.policy_sha256 or "", t.status, t.failure_reason or "",
                    t.requested_at.isoformat(), t.target_x_m, t.target_y_m, t.target_z_m,
                    round(math.hypot(t.target_x_m, t.target_y_m), 4),
                    *(("" if v is None else v) for v in (t.impact_x_m, t.impact_y_m, t.impact_z_m,
                                                          t.downrange_error_m, t.crossrange_error_m, t.duration_s)),
                    t.requested_by or "", p.get("downrange_error_m", ""), p.get("crossrange_error_m", "")])
    return buf.getvalue()
