"""Throw history queries: filters, sorting and pagination in SQL; accuracy statistics per mode,
policy version and target distance (the paper's figure, live from the database), aggregated in
SQL so that 100 000 stored throws answer in well under 100 ms; CSV export.

A policy version is identified by its ONNX file's SHA-256 (``throws.policy_sha256``; names are
not unique); throws stored before the SHA was recorded fall back to their version name.
Target distance is the horizontal distance of the target from the turn axis; filters compare
squared distances, bins use SQL ``sqrt`` (server.db.session provides it on SQLite builds without it).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from datetime import datetime

import numpy as np
from sqlalchemy import Float, Select, cast, func, literal, select

from server.db.models import Throw

_DIST2 = Throw.target_x_m * Throw.target_x_m + Throw.target_y_m * Throw.target_y_m
SORTS = {
    "requested_at": Throw.requested_at, "machine_id": Throw.machine_id, "mode": Throw.mode,
    "policy_version": Throw.policy_version, "policy_sha256": Throw.policy_sha256, "status": Throw.status, "target_distance": _DIST2,
    "downrange_error": Throw.downrange_error_m, "crossrange_error": Throw.crossrange_error_m,
    "duration": Throw.duration_s,
}
DISTANCE_BIN_M = 0.5
ERRORS_PER_GROUP = 200
"""The scatter of a group carries at most this many of its newest throws' errors."""
SCATTER_SAMPLE = 5000
"""The scatter is drawn from the newest this many landed throws matching the filters (an index
scan), so that the statistics over all throws stay one aggregate query."""


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


def error_ellipse(down: np.ndarray, cross: np.ndarray, n: int = 48) -> dict | None:
    """1 sigma ellipse of the (downrange, crossrange) errors: semi-axes, angle, outline."""
    if len(down) < 3:
        return None
    pts = np.column_stack([down, cross])
    return ellipse_of(pts.mean(axis=0), np.cov(pts.T), n)


def ellipse_of(mean: np.ndarray, cov: np.ndarray, n: int = 48) -> dict:
    """1 sigma ellipse of a 2D Gaussian (``mean`` (2,), ``cov`` (2, 2), m and m²): semi-axes,
    angle of the major axis from downrange (rad), outline (n + 1, 2)."""
    vals, vecs = np.linalg.eigh(cov)
    vals = np.clip(vals, 0, None)
    ang = np.linspace(0, 2 * math.pi, n + 1)
    outline = mean + np.outer(math.sqrt(vals[1]) * np.cos(ang), vecs[:, 1]) + np.outer(math.sqrt(vals[0]) * np.sin(ang), vecs[:, 0])
    return {"semi_major_m": math.sqrt(vals[1]), "semi_minor_m": math.sqrt(vals[0]),
            "angle_rad": math.atan2(vecs[1, 1], vecs[0, 1]), "outline_m": np.round(outline, 4).tolist()}


def accuracy(db, flt: ThrowFilter, bin_m: float = DISTANCE_BIN_M, errors_per_group: int = ERRORS_PER_GROUP) -> list[dict]:
    """Landed throws matching ``flt`` grouped by mode, policy identity (SHA-256) and target
    distance (bins of ``bin_m``), aggregated in SQL: n, mean impact distance, bias, sigma
    downrange/crossrange (population), mean crossrange, mean |error|, 1 sigma ellipse (sample
    covariance), and the errors of up to ``errors_per_group`` of the group's newest throws among
    the newest SCATTER_SAMPLE matching ones (scatter)."""
    dr, cr = Throw.downrange_error_m, Throw.crossrange_error_m
    ident = func.coalesce(Throw.policy_sha256, literal("name:") + func.coalesce(Throw.policy_version, "?"))
    dist_bin = func.round(func.sqrt(cast(_DIST2, Float)) / bin_m)
    landed = (Throw.status == "landed", dr.is_not(None), cr.is_not(None))
    keys = (Throw.mode.label("mode"), ident.label("ident"), dist_bin.label("bin"))
    stats = db.execute(flt.apply(select(
        *keys, func.max(Throw.policy_version), func.max(Throw.policy_sha256), func.count(), func.avg(dr), func.avg(cr),
        func.avg(dr * dr), func.avg(cr * cr), func.avg(dr * cr), func.avg(func.sqrt(dr * dr + cr * cr)),
    ).where(*landed)).group_by(*keys)).all()
    recent = flt.apply(select(*keys, dr, cr).where(*landed)).order_by(Throw.requested_at.desc()).limit(SCATTER_SAMPLE)
    scatter: dict[tuple, list] = {}
    for mode, ident_, b, d, c in db.execute(recent):
        pts = scatter.setdefault((mode, ident_, float(b)), [])
        if len(pts) < errors_per_group:
            pts.append([round(d, 4), round(c, 4)])
    out = []
    for mode, ident_, b, version, sha, n, mdr, mcr, mdr2, mcr2, mdrcr, mabs in stats:
        d = round(float(b) * bin_m, 3)
        var_d, var_c = max(mdr2 - mdr * mdr, 0.0), max(mcr2 - mcr * mcr, 0.0)
        cov = np.array([[var_d, mdrcr - mdr * mcr], [mdrcr - mdr * mcr, var_c]]) * (n / (n - 1) if n > 1 else 1.0)
        out.append({
            "mode": mode, "policy_version": version or "?", "policy_sha256": sha, "target_distance_m": d, "n": int(n),
            "mean_impact_distance_m": float(d + mdr), "bias_m": float(mdr),
            "sigma_downrange_m": math.sqrt(var_d), "mean_crossrange_m": float(mcr),
            "sigma_crossrange_m": math.sqrt(var_c), "mean_abs_error_m": float(mabs),
            "ellipse": ellipse_of(np.array([mdr, mcr]), cov) if n >= 3 else None,
            "errors_m": scatter.get((mode, ident_, float(b)), []),
        })
    return sorted(out, key=lambda g: (g["mode"], g["policy_version"], g["policy_sha256"] or "", g["target_distance_m"]))
