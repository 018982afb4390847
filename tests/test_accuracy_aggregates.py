"""Incremental accuracy aggregates (server.db.aggregates, server.analysis.accuracy) on SQLite and
PostgreSQL: results stored through the real ingest path (signed ThrowResult queries over Zenoh
to the server's fleet link) keep ``throw_accuracy`` in step, and the accuracy answered from the
aggregates equals the row scan's for every filter the aggregates serve: a result re-delivered
twice counts once, a throw marked lost does not count until its late result lands, failed throws
never count. The migration's backfill and :func:`server.db.aggregates.rebuild` give the same
sums as the live maintenance. PostgreSQL cases use a throwaway database (fixture ``pg_url``).
"""

from __future__ import annotations

import math
import time
import uuid
from datetime import datetime, timedelta, timezone

import pytest
from sqlalchemy import insert, select

import server.analysis.accuracy as acc
from runtime.protocol.messages import PolicyInfo, ThrowResult
from server.db.aggregates import distance_bin, rebuild
from server.db.migrate import upgrade
from server.db.models import Machine, Throw, ThrowAccuracy
from server.db.session import make_engine, make_sessionmaker
from server.throws.history import ThrowFilter
from tests.conftest import ADMIN, FakeRuntime, add_user, login

T0 = datetime(2026, 5, 1, 20, 0, tzinfo=timezone.utc)
SHA_A, SHA_B = "a" * 64, "b" * 64


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def db_url(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'agg.db'}"
    return request.getfixturevalue("pg_url")


@pytest.fixture
def app_client(db_url, tmp_path, zenoh_endpoint):
    """The app on ``db_url`` (migrated at start), logged in as admin."""
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.config import Settings

    settings = Settings(data_dir=tmp_path / "var", database_url=db_url, zenoh_listen=[zenoh_endpoint],
                        viser_enabled=False, query_timeout_s=2.0, auto_migrate=True, require_preview=False,
                        job_queue_url="immediate", runtime_gone_s=3600.0, result_grace_s=3600.0)
    with TestClient(create_app(settings)) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        login(c, *ADMIN)
        c.site_dir = settings.resolved_site_dir
        yield c


def _plan(k: int) -> dict:
    """The k-th synthetic throw: machine, mode, policy, target (some exactly on a bin edge), time."""
    d = [7.0, 7.25, 7.6, 8.0, 8.75, 9.3][k % 6]  # 7.25 and 8.75 lie exactly half-way between bins
    y = 0.0 if k % 4 else -0.31
    x = math.sqrt(d * d - y * y)
    sha, name = [(SHA_A, "pA"), (SHA_B, "pB"), (None, "pOld")][k % 3]
    return dict(id=str(uuid.uuid4()), machine_id=f"m{k % 2 + 1}", mode="2d" if k % 5 else "3d", target_x_m=x,
                target_y_m=y, target_z_m=0.0, status="released", policy_version=name, policy_sha256=sha,
                requested_at=T0 + timedelta(hours=7 * k))


def _result(rt: FakeRuntime, row: dict, k: int, status: str = "landed") -> ThrowResult:
    landed = status == "landed"
    impact = [row["target_x_m"] + 0.05 * math.sin(k), row["target_y_m"] + 0.03 * math.cos(3 * k), 0.0]
    return rt.signed(ThrowResult(
        machine_id=row["machine_id"], stamp_s=time.monotonic(), throw_id=row["id"], mode=row["mode"], status=status,
        target_m=[row["target_x_m"], row["target_y_m"], 0.0], impact_m=impact if landed else None,
        failure_reason=None if landed else "machine link lost", policy_version=row["policy_version"],
        policy_sha256=row["policy_sha256"], duration_s=2.0))


def _close(a, b, path="") -> None:
    """``a`` == ``b``, floats to 1e-9 relative (sums added in another order), outlines to 1e-3 m."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        tol = 1e-3 if "outline_m" in path else 1e-9
        assert b == pytest.approx(a, rel=tol, abs=max(tol * 1e-3, 1e-12)), path
    else:
        assert a == b, path


def _both_ways(db, flt: ThrowFilter) -> tuple[list, list]:
    """(answer as served: aggregates where they can, row scan of the same filter)."""
    served = acc.accuracy(db, flt)
    orig = acc._served_by_aggregates
    acc._served_by_aggregates = lambda *_: False
    try:
        scanned = acc.accuracy(db, flt)
    finally:
        acc._served_by_aggregates = orig
    return served, scanned


FILTERS = [
    ThrowFilter(), ThrowFilter(machine_id="m1"), ThrowFilter(mode="3d"), ThrowFilter(machine_id="m2", mode="2d"),
    ThrowFilter(policy_sha256=SHA_A), ThrowFilter(policy_version="pOld"), ThrowFilter(status="landed"),
    ThrowFilter(since=T0 + timedelta(hours=30)),  # inside a day: aggregates + one partial day
    ThrowFilter(until=T0 + timedelta(days=6, hours=5)),
    ThrowFilter(since=T0 + timedelta(hours=4), until=T0 + timedelta(days=5, minutes=17), machine_id="m1"),
    ThrowFilter(since=datetime(2026, 5, 3, tzinfo=timezone.utc), until=datetime(2026, 5, 6, tzinfo=timezone.utc)),
    ThrowFilter(since=T0 + timedelta(hours=30), until=T0 + timedelta(hours=45)),  # no whole day: row scan
]


def _table(db) -> dict:
    cols = [c for c in ThrowAccuracy.__table__.c]
    return {tuple(r[:6]): tuple(r[6:]) for r in db.execute(select(*cols).where(ThrowAccuracy.n != 0))}


def _assert_tables_equal(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k][0] == b[k][0] and list(a[k][1:]) == pytest.approx(list(b[k][1:]), rel=1e-9, abs=1e-12), k


def test_aggregates_follow_the_ingest_path_and_equal_the_row_scan(app_client, zenoh_endpoint):
    app = app_client.app
    sessions, store = app.state.sessions, app.state.store
    plan = [_plan(k) for k in range(36)]
    with sessions.begin() as db:  # the throws the server issued (as ThrowService records them)
        db.add_all([Machine(id="m1", simulated=True), Machine(id="m2", simulated=True)])
        db.flush()
        db.execute(insert(Throw), plan)
    rts = {m: FakeRuntime(zenoh_endpoint, m, site_dir=app_client.site_dir) for m in ("m1", "m2")}
    try:
        lost_then_late, lost_for_good, failed = plan[4]["id"], plan[5]["id"], {plan[7]["id"], plan[8]["id"]}
        assert store.mark_lost(lost_then_late, "runtime of m1 restarted") and store.mark_lost(lost_for_good, "gone")
        for k, row in enumerate(plan):
            if row["id"] == lost_for_good:
                continue
            result = _result(rts[row["machine_id"]], row, k, "failed" if row["id"] in failed else "landed")
            ack = rts[row["machine_id"]].send_result(result)
            assert ack is not None and ack.stored, (k, ack)
            if k == 3:  # the outbox re-delivers: twice more, same values
                for _ in range(2):
                    assert rts[row["machine_id"]].send_result(result).stored
        assert not store.mark_lost(plan[3]["id"], "too late")  # a landed throw stays landed
    finally:
        for rt in rts.values():
            rt.close()
    with sessions() as db:
        status = {i: s for i, s in db.execute(select(Throw.id, Throw.status))}
        assert status[lost_then_late] == "landed" and status[lost_for_good] == "lost"
        assert {status[i] for i in failed} == {"failed"}
        n_landed = sum(s == "landed" for s in status.values())
        assert n_landed == 33
        assert sum(db.scalars(select(ThrowAccuracy.n))) == n_landed
        # bins as distance_bin says (targets exactly half-way go up) on both paths
        bins = {distance_bin(r["target_x_m"], r["target_y_m"]) * 0.5 for r in plan if status[r["id"]] == "landed"}
        assert {7.5, 9.0} <= bins and {g["target_distance_m"] for g in acc.accuracy(db, ThrowFilter())} == bins
        for flt in FILTERS:
            served, scanned = _both_ways(db, flt)
            assert served, flt
            _close(scanned, served)
        assert sum(g["n"] for g in acc.accuracy(db, ThrowFilter())) == n_landed
        assert acc.accuracy(db, ThrowFilter(status="failed")) == []
        live = _table(db)
    # the API answers the same as the module, schema unchanged
    r = app_client.get("/api/throws/accuracy", params={"machine_id": "m1"})
    assert r.status_code == 200
    with sessions() as db:
        _close(acc.accuracy(db, ThrowFilter(machine_id="m1")), r.json())
        assert set(r.json()[0]) == {"mode", "policy_version", "policy_sha256", "target_distance_m", "n",
                                    "mean_impact_distance_m", "bias_m", "sigma_downrange_m", "mean_crossrange_m",
                                    "sigma_crossrange_m", "mean_abs_error_m", "ellipse", "errors_m"}
    with sessions.begin() as db:
        assert rebuild(db) == n_landed
    with sessions() as db:
        _assert_tables_equal(live, _table(db))


def test_whole_days_are_served_by_the_aggregates(app_client, monkeypatch):
    """Without distance filters and with day-aligned times no landed row is scanned for the
    statistics; a time inside a day scans only that partial day."""
    sessions = app_client.app.state.sessions
    with sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
        for k in range(6):
            row = _plan(2 * k)
            db.add(Throw(**{**row, "status": "landed", "downrange_error_m": 0.01 * k, "crossrange_error_m": -0.02}))
    scans = []
    real = acc._row_sums
    monkeypatch.setattr(acc, "_row_sums", lambda db, flt, b, *where: scans.append(where) or real(db, flt, b, *where))
    with sessions() as db:
        assert sum(g["n"] for g in acc.accuracy(db, ThrowFilter())) == 6 and scans == []
        acc.accuracy(db, ThrowFilter(machine_id="m1", mode="2d", since=datetime(2026, 5, 2, tzinfo=timezone.utc)))
        assert scans == []
        acc.accuracy(db, ThrowFilter(since=T0 + timedelta(hours=1)))
        assert len(scans) == 1 and len(scans[0]) == 1  # the partial first day only
        acc.accuracy(db, ThrowFilter(min_distance_m=7.5))
        assert len(scans) == 2 and scans[1] == ()  # distance filter: full row scan


@pytest.mark.parametrize("kind", ["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def test_migration_backfills_the_aggregates(kind, tmp_path, request):
    """Throws stored before revision 0006 are summed by its backfill exactly as live maintenance
    and :func:`rebuild` sum them; downgrade to 0005 drops the table."""
    from server.db.migrate import downgrade

    url = f"sqlite:///{tmp_path / 'old.db'}" if kind == "sqlite" else request.getfixturevalue("pg_url")
    upgrade(url, "0005")
    engine = make_engine(url)
    try:
        rows = []
        for k in range(40):
            row = _plan(k)
            landed = k % 7 != 6
            rows.append({**row, "status": "landed" if landed else "failed",
                         "downrange_error_m": 0.04 * math.sin(k) if landed else None,
                         "crossrange_error_m": 0.02 * math.cos(k) if landed else None})
        with engine.begin() as conn:
            conn.execute(insert(Machine.__table__), [dict(id="m1", simulated=True, first_seen_at=T0, last_seen_at=T0),
                                                     dict(id="m2", simulated=True, first_seen_at=T0, last_seen_at=T0)])
            conn.execute(insert(Throw.__table__), rows)
        upgrade(url)
        sessions = make_sessionmaker(engine)
        with sessions() as db:
            backfilled = _table(db)
            assert sum(v[0] for v in backfilled.values()) == sum(r["status"] == "landed" for r in rows)
            for flt in FILTERS:
                served, scanned = _both_ways(db, flt)
                _close(scanned, served)
        with sessions.begin() as db:
            rebuild(db)
        with sessions() as db:
            _assert_tables_equal(backfilled, _table(db))
    finally:
        engine.dispose()
    downgrade(url, "0005")
    engine = make_engine(url)
    try:
        from sqlalchemy import inspect

        assert "throw_accuracy" not in inspect(engine).get_table_names()
    finally:
        engine.dispose()


def test_distance_bins_round_halves_up():
    assert distance_bin(7.25, 0.0) == 15 and distance_bin(7.24, 0.0) == 14 and distance_bin(0.0, 8.0) == 16
    assert distance_bin(3.0, 4.0) == 10 and distance_bin(3.0, 4.0, bin_m=1.0) == 5


def test_concurrent_redeliveries_count_once(app_client, zenoh_endpoint):
    """Every result delivered by 4 threads at once (the outbox re-sending while the first
    delivery is still being stored) and late statuses meanwhile: each landed throw counts once,
    the aggregates equal a rebuild from the rows, no landed row goes back to an open status."""
    import threading

    from runtime.protocol.messages import ThrowStatus, encode

    sessions = app_client.app.state.sessions
    plan = [{**_plan(k), "machine_id": "m1"} for k in range(40)]
    with sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
        db.flush()
        db.execute(insert(Throw), plan)
    rt = FakeRuntime(zenoh_endpoint, "m1", site_dir=app_client.site_dir)
    results = [_result(rt, row, k) for k, row in enumerate(plan)]
    acks: list = []

    def deliver(offset: int) -> None:
        for r in results[offset:] + results[:offset]:
            acks.append(rt.send_result(r))
            rt._status_pub.put(encode(ThrowStatus(machine_id="m1", stamp_s=time.monotonic(), throw_id=r.throw_id,
                                                  phase="swinging")))

    try:
        threads = [threading.Thread(target=deliver, args=(10 * i,)) for i in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        time.sleep(0.5)  # the last statuses reach the database
    finally:
        rt.close()
    assert len(acks) == 160 and all(a is not None and a.stored for a in acks)
    with sessions() as db:
        assert set(db.scalars(select(Throw.status))) == {"landed"}
        assert sum(db.scalars(select(ThrowAccuracy.n))) == 40
        live = _table(db)
    with sessions.begin() as db:
        rebuild(db)
    with sessions() as db:
        _assert_tables_equal(live, _table(db))
