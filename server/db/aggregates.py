"""Incremental accuracy aggregates (table ``throw_accuracy``, model
:class:`server.db.models.ThrowAccuracy`), kept in the same transaction as the throws they sum.

A throw **contributes** iff its status is ``landed`` and both errors are set. Its key is
(machine, mode, policy SHA-256 or ``''``, policy name or ``''``, target-distance bin, UTC day of
``requested_at``); its sums are 1, down, cross, down², cross², down·cross, sqrt(down² + cross²)
(errors in m, machine frame as in ``throws``).

How they stay exact: a ``before_flush`` listener on every ORM :class:`~sqlalchemy.orm.Session`
compares, for each new, changed or deleted :class:`~server.db.models.Throw`, its contribution
before (the loaded values; the relevant columns have ``active_history``) and after the change;
an ``after_flush`` listener upserts the differences into ``throw_accuracy`` on the flush's own
connection, so the aggregates commit or roll back with the row. A re-delivered result that stores the same values
changes nothing. Writes that bypass the ORM unit of work are not seen; the server makes only
these, and none changes a contribution: ``ResultStore.mark_lost`` (a conditional UPDATE of a
NON-final throw to ``lost``: only a landed, i.e. final, throw contributes) and
``ThrowService._delete`` (a throw whose hand-shake failed, never landed),
``ResultStore.apply_status`` (a conditional UPDATE that never changes a final row's status). Bulk loads with Core
statements (the benchmark's fill) must call :func:`rebuild` afterwards.

Supported databases: SQLite and PostgreSQL (``INSERT ... ON CONFLICT DO UPDATE``).
"""

from __future__ import annotations

import math
from collections import defaultdict
from datetime import UTC, date, datetime

from sqlalchemy import delete, event, inspect, select
from sqlalchemy.orm import Session
from sqlalchemy.orm.base import NO_VALUE

from server.db.models import Throw, ThrowAccuracy
from server.db.types import utcnow
from server.db.upsert import dialect_insert

DISTANCE_BIN_M = 0.5
"""Width of the target-distance bins, m (the accuracy view's bins)."""
KEY_COLUMNS = ("machine_id", "mode", "policy_sha256", "policy_version", "distance_bin", "day")
SUM_COLUMNS = ("n", "sum_down_m", "sum_cross_m", "sum_down2_m2", "sum_cross2_m2", "sum_down_cross_m2", "sum_abs_m")
_FIELDS = ("machine_id", "mode", "policy_sha256", "policy_version", "target_x_m", "target_y_m", "requested_at",
           "status", "downrange_error_m", "crossrange_error_m")


def distance_bin(x_m: float, y_m: float, bin_m: float = DISTANCE_BIN_M) -> int:
    """Bin index of a target at (x, y) (machine frame, m): floor(sqrt(x² + y²) / bin_m + 0.5),
    i.e. the nearest multiple of ``bin_m``, halves up. The SQL row scan (server.analysis.accuracy)
    evaluates the same IEEE operations in the same order, so both agree to the bit."""
    return math.floor(math.sqrt(x_m * x_m + y_m * y_m) / bin_m + 0.5)


def contribution(v: dict) -> tuple[tuple, tuple] | None:
    """(key, sums) of a throw given its column values ``v`` (names of _FIELDS), or None when it
    does not contribute (not landed, or an error missing). Key order: KEY_COLUMNS; sums order:
    SUM_COLUMNS."""
    down, cross = v["downrange_error_m"], v["crossrange_error_m"]
    if v["status"] != "landed" or down is None or cross is None:
        return None
    at: datetime = v["requested_at"]
    day: date = (at.astimezone(UTC) if at.tzinfo else at).date()
    key = (v["machine_id"], v["mode"], v["policy_sha256"] or "", v["policy_version"] or "",
           distance_bin(v["target_x_m"], v["target_y_m"]), day)
    return key, (1, down, cross, down * down, cross * cross, down * cross, math.sqrt(down * down + cross * cross))


def _values(obj: Throw, before: bool) -> dict:
    """The throw's relevant column values now, or as loaded (``before``)."""
    state = inspect(obj)
    out = {}
    for name in _FIELDS:
        if before and name in state.committed_state:
            value = state.committed_state[name]
            if value is NO_VALUE:  # never loaded: cannot happen with active_history
                raise RuntimeError(f"throw {obj.id}: previous {name} unknown; aggregates cannot be kept")
        else:
            value = state.dict[name] if name in state.dict else getattr(obj, name)
        out[name] = value
    return out


def deltas_of(session: Session) -> dict[tuple, list]:
    """Per aggregate key, the change of the sums that flushing ``session`` makes."""
    out: dict[tuple, list] = defaultdict(lambda: [0] + [0.0] * (len(SUM_COLUMNS) - 1))
    changed = [(o, False, True) for o in session.new] + [(o, True, True) for o in session.dirty] + [
        (o, True, False) for o in session.deleted]
    for obj, had, has in changed:
        if not isinstance(obj, Throw):
            continue
        if has and had and not session.is_modified(obj):
            continue
        if not had and obj.requested_at is None:  # the column default, applied now to know the day
            obj.requested_at = utcnow()
        old = contribution(_values(obj, True)) if had else None
        new = contribution(_values(obj, False)) if has else None
        if old == new:
            continue
        for c, sign in ((old, -1), (new, 1)):
            if c is not None:
                acc = out[c[0]]
                for i, s in enumerate(c[1]):
                    acc[i] += sign * s
    return {k: v for k, v in out.items() if v[0] != 0 or any(v[1:])}


def upsert(connection, deltas: dict[tuple, list]) -> None:
    """Add ``deltas`` (key -> sums, as :func:`deltas_of`) to ``throw_accuracy`` on ``connection``.

    Raises:
        NotImplementedError: a database other than SQLite or PostgreSQL.
    """
    if not deltas:
        return
    stmt = dialect_insert(connection.dialect.name, ThrowAccuracy)
    table = ThrowAccuracy.__table__
    stmt = stmt.on_conflict_do_update(index_elements=list(KEY_COLUMNS),
                                      set_={c: table.c[c] + stmt.excluded[c] for c in SUM_COLUMNS})
    rows = [dict(zip(KEY_COLUMNS, k)) | dict(zip(SUM_COLUMNS, s)) for k, s in sorted(deltas.items())]
    connection.execute(stmt, rows)


_PENDING = "accuracy_deltas"


@event.listens_for(Session, "before_flush")
def _measure(session: Session, _flush_context, _instances) -> None:
    session.info[_PENDING] = deltas_of(session)


@event.listens_for(Session, "after_flush")
def _apply(session: Session, _flush_context) -> None:
    # after the rows' own statements: the aggregate rows (shared by concurrent writers) are
    # locked only from here to the commit, and always in key order (no deadlock)
    upsert(session.connection(), session.info.pop(_PENDING, {}))


def rebuild(session: Session, batch: int = 20_000) -> int:
    """Recompute ``throw_accuracy`` from the landed throws inside ``session``'s transaction (after
    bulk loads that bypassed the ORM); returns the number of throws summed."""
    session.execute(delete(ThrowAccuracy))
    cols = [getattr(Throw, f) for f in _FIELDS]
    sums: dict[tuple, list] = defaultdict(lambda: [0] + [0.0] * (len(SUM_COLUMNS) - 1))
    count = 0
    rows = session.execute(select(*cols).where(Throw.status == "landed").execution_options(yield_per=batch))
    for row in rows:
        c = contribution(dict(zip(_FIELDS, row)))
        if c is not None:
            count += 1
            acc = sums[c[0]]
            for i, s in enumerate(c[1]):
                acc[i] += s
    upsert(session.connection(), sums)
    return count
