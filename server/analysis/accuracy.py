"""Accuracy statistics of the landed throws per mode, policy identity and target distance (the
paper's figure, live from the database).

Where the numbers come from (:func:`accuracy`):

* **From the incremental aggregates** (``throw_accuracy``, kept by server.db.aggregates in the
  transaction that stores a result) for the filters they are keyed by: machine, mode, policy
  SHA-256, policy name, status (only ``landed`` throws count: ``landed`` or none is served, any
  other status answers no groups) and the time range to whole UTC days. A ``since``/``until``
  that falls inside a day is served by the aggregates for the whole days in between plus a
  row scan of the partial days at the edges (bounded by the ``requested_at`` index).
* **From a row scan** (one SQL aggregate over every matching landed throw) for what the
  aggregates cannot serve: a target-distance filter (``min_distance_m`` / ``max_distance_m``:
  a bin holds targets up to 0.25 m either side of its centre) or a bin width other than
  DISTANCE_BIN_M.

Both paths produce the same sums (count, sums of errors, squares, products, |error|) per group
and one function turns them into the answer, so they agree up to float rounding of the sums
(tests/test_accuracy_aggregates.py compares them). The scatter (``errors_m``) is always a bounded
query: the newest SCATTER_SAMPLE matching landed throws, by index.

A policy version is identified by its ONNX file's SHA-256 (names are not unique); throws stored
without a SHA fall back to their version name (``name:<version>``). Bins: server.db.aggregates.distance_bin,
in SQL ``floor(sqrt(x*x + y*y) / bin + 0.5)`` (server.db.session provides ``sqrt``/``floor`` on
SQLite builds without them).
"""

from __future__ import annotations

import math
from datetime import UTC, datetime, time, timedelta

import numpy as np
from sqlalchemy import Float, String, and_, case, cast, func, literal, or_, select, type_coerce

from server.db.aggregates import DISTANCE_BIN_M
from server.db.models import Throw, ThrowAccuracy
from server.throws.history import _DIST2, ThrowFilter

ERRORS_PER_GROUP = 200
"""The scatter of a group carries at most this many of its newest throws' errors."""
SCATTER_SAMPLE = 1000
"""The scatter is drawn from the newest this many landed throws matching the filters (an index
scan; 5000 before the aggregates, lowered because fetching and grouping those rows had become
most of the request's time: 1000 halves the CPU per request of 2000 over 100 000 throws and
lets PostgreSQL read them backwards by index instead of sorting a machine's whole history)."""

_DOWN, _CROSS = Throw.downrange_error_m, Throw.crossrange_error_m
_LANDED = (Throw.status == "landed", _DOWN.is_not(None), _CROSS.is_not(None))
_ROW_IDENT = func.coalesce(func.nullif(Throw.policy_sha256, ""),
                           literal("name:") + func.coalesce(func.nullif(Throw.policy_version, ""), "?"))
_A = ThrowAccuracy
_AGG_IDENT = case((_A.policy_sha256 != "", _A.policy_sha256),
                  else_=literal("name:") + case((_A.policy_version != "", _A.policy_version), else_="?"))


def _row_bin(bin_m: float):
    return func.floor(func.sqrt(cast(_DIST2, Float)) / bin_m + 0.5)


def _row_sums(db, flt: ThrowFilter, bin_m: float, *where) -> list[tuple]:
    """Row scan: per (mode, ident, bin) the max name, max SHA and SUM_COLUMNS' sums."""
    keys = (Throw.mode, _ROW_IDENT, _row_bin(bin_m))
    stmt = flt.apply(select(
        *keys, func.max(func.nullif(Throw.policy_version, "")), func.max(func.nullif(Throw.policy_sha256, "")),
        func.count(), func.sum(_DOWN), func.sum(_CROSS), func.sum(_DOWN * _DOWN), func.sum(_CROSS * _CROSS),
        func.sum(_DOWN * _CROSS), func.sum(func.sqrt(_DOWN * _DOWN + _CROSS * _CROSS)),
    ).where(*_LANDED, *where)).group_by(*keys)
    return db.execute(stmt).all()


def _aggregate_sums(db, flt: ThrowFilter, first_day, last_day) -> list[tuple]:
    """The same tuples as :func:`_row_sums`, from ``throw_accuracy`` (days inclusive, None = open)."""
    keys = (_A.mode, _AGG_IDENT, _A.distance_bin)
    stmt = select(*keys, func.max(func.nullif(_A.policy_version, "")), func.max(func.nullif(_A.policy_sha256, "")),
                  *(func.sum(c) for c in (_A.n, _A.sum_down_m, _A.sum_cross_m, _A.sum_down2_m2, _A.sum_cross2_m2,
                                          _A.sum_down_cross_m2, _A.sum_abs_m)))
    for col, value in ((_A.machine_id, flt.machine_id), (_A.policy_version, flt.policy_version),
                       (_A.mode, flt.mode), (_A.policy_sha256, flt.policy_sha256)):
        if value:
            stmt = stmt.where(col == value)
    if first_day is not None:
        stmt = stmt.where(_A.day >= first_day)
    if last_day is not None:
        stmt = stmt.where(_A.day <= last_day)
    return db.execute(stmt.group_by(*keys).having(func.sum(_A.n) > 0)).all()


def _whole_days(since: datetime | None, until: datetime | None):
    """Split [since, until] (UTC-aware or None) into whole UTC days for the aggregates and the
    partial edges for a row scan: (first_day, last_day, edge clauses); first_day > last_day means
    no whole day (then the edges are None: scan everything)."""
    first = last = None
    edges = []
    if since is not None:
        s = since.astimezone(UTC)
        first = s.date() if s.timetz() == time(0, tzinfo=UTC) else s.date() + timedelta(days=1)
    if until is not None:
        last = until.astimezone(UTC).date() - timedelta(days=1)
    if first is not None and last is not None and first > last:
        return first, last, None
    if since is not None and first is not None and first != since.astimezone(UTC).date():  # first is set with since
        edges.append(Throw.requested_at < datetime.combine(first, time(0), UTC))
    if until is not None and last is not None:  # last is set with until
        edges.append(Throw.requested_at >= datetime.combine(last + timedelta(days=1), time(0), UTC))
    return first, last, edges


def _served_by_aggregates(flt: ThrowFilter, bin_m: float) -> bool:
    return bin_m == DISTANCE_BIN_M and flt.min_distance_m is None and flt.max_distance_m is None


def group_sums(db, flt: ThrowFilter, bin_m: float = DISTANCE_BIN_M) -> dict[tuple, list]:
    """Per (mode, ident, bin) the list [max name, max SHA, n, sum down, sum cross, sum down²,
    sum cross², sum down·cross, sum |error|] of the landed throws matching ``flt`` (errors m,
    products m²), from the aggregates where they serve ``flt``, else by row scan."""
    if flt.status not in (None, "landed"):
        return {}
    if not _served_by_aggregates(flt, bin_m):
        parts = [_row_sums(db, flt, bin_m)]
    else:
        first, last, edges = _whole_days(flt.since, flt.until)
        if edges is None:
            parts = [_row_sums(db, flt, bin_m)]
        else:
            parts = [_aggregate_sums(db, flt, first, last)]
            if edges:
                parts.append(_row_sums(db, flt, bin_m, or_(*edges) if len(edges) > 1 else and_(*edges)))
    out: dict[tuple, list] = {}
    for part in parts:
        for mode, ident, b, version, sha, *sums in part:
            key = (mode, ident, int(b))
            if key not in out:
                out[key] = [version, sha, *sums]
                continue
            acc = out[key]
            acc[0] = max((v for v in (acc[0], version) if v), default=None)
            acc[1] = max((v for v in (acc[1], sha) if v), default=None)
            for i, s in enumerate(sums):
                acc[2 + i] += s
    return out


def _scatter(db, flt: ThrowFilter, bin_m: float, errors_per_group: int) -> dict[tuple, list]:
    """Per (mode, ident, bin) up to ``errors_per_group`` [down, cross] errors (m) of its newest
    throws among the newest SCATTER_SAMPLE landed throws matching ``flt``."""
    if flt.status not in (None, "landed"):
        return {}
    mode = type_coerce(Throw.mode, String)  # plain strings: no per-row enum processing
    recent = flt.apply(select(mode, _ROW_IDENT, _row_bin(bin_m), _DOWN, _CROSS).where(*_LANDED)).order_by(
        Throw.requested_at.desc()).limit(SCATTER_SAMPLE)
    out: dict[tuple, list] = {}
    for m, ident, b, d, c in db.execute(recent):
        pts = out.setdefault((m, ident, int(b)), [])
        if len(pts) < errors_per_group:
            pts.append([round(d, 4), round(c, 4)])
    return out


def accuracy(db, flt: ThrowFilter, bin_m: float = DISTANCE_BIN_M, errors_per_group: int = ERRORS_PER_GROUP) -> list[dict]:
    """Landed throws matching ``flt`` grouped by mode, policy identity (SHA-256) and target
    distance (bins of ``bin_m``, m): n, mean impact distance, bias, sigma downrange/crossrange
    (population), mean crossrange, mean |error|, 1 sigma ellipse (sample covariance; None below
    3 throws), and the errors of up to ``errors_per_group`` of the group's newest throws among
    the newest SCATTER_SAMPLE matching ones (``errors_m``, scatter). Sorted by mode, name, SHA,
    distance. See the module docstring for which filters the aggregates serve."""
    scatter = _scatter(db, flt, bin_m, errors_per_group)
    out = []
    for (mode, ident, b), (version, sha, n, sd, sc, sdd, scc, sdc, sabs) in group_sums(db, flt, bin_m).items():
        n = int(n)
        d = round(b * bin_m, 3)
        mdr, mcr = sd / n, sc / n
        var_d, var_c = max(sdd / n - mdr * mdr, 0.0), max(scc / n - mcr * mcr, 0.0)
        cov_dc = sdc / n - mdr * mcr
        cov = np.array([[var_d, cov_dc], [cov_dc, var_c]]) * (n / (n - 1) if n > 1 else 1.0)
        out.append({
            "mode": mode, "policy_version": version or "?", "policy_sha256": sha or None, "target_distance_m": d,
            "n": n, "mean_impact_distance_m": float(d + mdr), "bias_m": float(mdr),
            "sigma_downrange_m": math.sqrt(var_d), "mean_crossrange_m": float(mcr),
            "sigma_crossrange_m": math.sqrt(var_c), "mean_abs_error_m": float(sabs / n),
            "ellipse": ellipse_of(np.array([mdr, mcr]), cov) if n >= 3 else None,
            "errors_m": scatter.get((mode, ident, b), []),
        })
    return sorted(out, key=lambda g: (g["mode"], g["policy_version"], g["policy_sha256"] or "", g["target_distance_m"]))


def ellipse_of(mean: np.ndarray, cov: np.ndarray, n: int = 48) -> dict:
    """1 sigma ellipse of a 2D Gaussian (``mean`` (2,), ``cov`` (2, 2), m and m²): semi-axes,
    angle of the major axis from downrange (rad), outline (n + 1, 2)."""
    vals, vecs = np.linalg.eigh(cov)
    vals = np.clip(vals, 0, None)
    ang = np.linspace(0, 2 * math.pi, n + 1)
    outline = mean + np.outer(math.sqrt(vals[1]) * np.cos(ang), vecs[:, 1]) + np.outer(math.sqrt(vals[0]) * np.sin(ang), vecs[:, 0])
    return {"semi_major_m": math.sqrt(vals[1]), "semi_minor_m": math.sqrt(vals[0]),
            "angle_rad": math.atan2(vecs[1, 1], vecs[0, 1]), "outline_m": np.round(outline, 4).tolist()}
