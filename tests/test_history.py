"""Throw history API: filters, sorting, server-side pagination, CSV export, accuracy statistics,
per-throw trajectory (from the MCAP telemetry) and replay."""

from __future__ import annotations

import csv
import io
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from server.db.models import Machine, Throw
from tests.conftest import wait_for, wait_online

T0 = datetime(2026, 5, 1, 12, 0, tzinfo=timezone.utc)


@pytest.fixture
def rows(client):
    """40 throws: machines m1/m2, modes, two policy versions, distances 7.5..9.5, some failed."""
    rng = np.random.default_rng(1)
    with client.app.state.sessions.begin() as db:
        db.add_all([Machine(id="m1", simulated=True), Machine(id="m2", simulated=True)])
        for i in range(40):
            d = 7.5 + 0.5 * (i % 5)
            landed = i % 10 != 9
            down, cross = (float(rng.normal(0.1, 0.2)), float(rng.normal(0, 0.1))) if landed else (None, None)
            db.add(Throw(id=f"t{i:02d}", machine_id="m1" if i % 2 else "m2", mode="2d" if i < 30 else "3d",
                         target_x_m=d, target_y_m=0.0, target_z_m=0.0, status="landed" if landed else "failed",
                         downrange_error_m=down, crossrange_error_m=cross,
                         impact_x_m=d + down if landed else None, impact_y_m=cross if landed else None,
                         impact_z_m=0.0 if landed else None, policy_version="pA" if i < 20 else "pB",
                         requested_at=T0 + timedelta(minutes=i), duration_s=2.0 + 0.01 * i,
                         preview={"downrange_error_m": 0.05, "crossrange_error_m": 0.0} if i == 3 else None))
    return 40


def ids(r):
    return [t["id"] for t in r.json()]


def test_filters_sort_and_pagination(client, rows):
    r = client.get("/api/throws", params={"limit": 10})
    assert r.headers["X-Total-Count"] == "40" and ids(r)[0] == "t39" and len(ids(r)) == 10
    r2 = client.get("/api/throws", params={"limit": 10, "offset": 10})
    assert ids(r2)[0] == "t29" and not set(ids(r)) & set(ids(r2))
    r = client.get("/api/throws", params={"machine_id": "m1", "mode": "2d", "policy_version": "pA"})
    assert r.headers["X-Total-Count"] == "10" and all(int(i[1:]) % 2 == 1 and int(i[1:]) < 20 for i in ids(r))
    r = client.get("/api/throws", params={"status": "failed"})
    assert sorted(ids(r)) == ["t09", "t19", "t29", "t39"]
    r = client.get("/api/throws", params={"min_distance_m": 8.9, "max_distance_m": 9.1})
    assert r.headers["X-Total-Count"] == "8" and all(t["target_distance_m"] == pytest.approx(9.0) for t in r.json())
    r = client.get("/api/throws", params={"since": (T0 + timedelta(minutes=5)).isoformat(),
                                          "until": (T0 + timedelta(minutes=7)).isoformat()})
    assert sorted(ids(r)) == ["t05", "t06", "t07"]
    r = client.get("/api/throws", params={"sort": "target_distance", "order": "asc", "limit": 8})
    assert all(t["target_distance_m"] == pytest.approx(7.5) for t in r.json())
    r = client.get("/api/throws", params={"sort": "downrange_error", "order": "desc", "status": "landed"})
    errs = [t["downrange_error_m"] for t in r.json()]
    assert errs == sorted(errs, reverse=True)


@pytest.mark.parametrize("params", [{"sort": "bogus"}, {"order": "up"}, {"limit": 0}, {"offset": -1},
                                    {"mode": "4d"}, {"since": "yesterday"}, {"min_distance_m": -1}])
def test_bad_history_queries_are_422(client, rows, params):
    assert client.get("/api/throws", params=params).status_code == 422


def test_csv_export_of_filtered_rows(client, rows):
    r = client.get("/api/throws/export.csv", params={"mode": "3d"})
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    table = list(csv.DictReader(io.StringIO(r.text)))
    assert len(table) == 10 and {t["mode"] for t in table} == {"3d"}
    full = {t["id"]: t for t in csv.DictReader(io.StringIO(client.get("/api/throws/export.csv").text))}
    assert full["t03"]["predicted_downrange_error_m"] == "0.05"
    assert float(full["t04"]["target_distance_m"]) == pytest.approx(9.5)


def test_accuracy_per_mode_policy_and_distance(client, rows):
    groups = client.get("/api/throws/accuracy", params={"mode": "2d"}).json()
    assert {(g["policy_version"], g["target_distance_m"]) for g in groups} == {
        (p, d) for p in ("pA", "pB") for d in (7.5, 8.0, 8.5, 9.0, 9.5)}
    g = next(g for g in groups if g["policy_version"] == "pA" and g["target_distance_m"] == 7.5)
    errs = np.array(g["errors_m"])
    assert g["n"] == len(errs) == 4
    assert g["bias_m"] == pytest.approx(errs[:, 0].mean(), abs=1e-3) and g["sigma_downrange_m"] == pytest.approx(errs[:, 0].std(), abs=1e-3)
    assert g["mean_impact_distance_m"] == pytest.approx(7.5 + errs[:, 0].mean(), abs=1e-3)
    assert g["ellipse"]["semi_major_m"] >= g["ellipse"]["semi_minor_m"]


def test_trajectory_replay_and_mcap(client, fake_runtime_factory):
    fake_runtime_factory()
    wait_online(client)
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": [8.0, -0.292, 0.0]})
    tid = r.json()["id"]
    wait_for(lambda: client.get(f"/api/throws/{tid}").json()["status"] == "landed", 10)
    tr = client.get(f"/api/throws/{tid}/trajectory").json()
    assert len(tr["gripper_path_m"]) == 10 and len(tr["payload_path_m"]) == 10 and len(tr["t_s"]) == 10
    assert tr["impact_m"] == pytest.approx([8.3, -0.1, 0.0]) and tr["events"][0]["phase"] == "swinging"
    assert client.get(f"/api/throws/{tid}/telemetry").content[:5] == b"\x89MCAP"
    assert client.post(f"/api/throws/{tid}/replay").status_code == 409  # 3D view off in API tests
    assert client.get("/api/throws/nope/trajectory").status_code == 404
    assert client.post("/api/throws/nope/replay").status_code == 404


def test_fleet_view_of_machines(client, rows):
    ms = {m["id"]: m for m in client.get("/api/machines").json()}
    m1 = ms["m1"]
    assert m1["online"] is False and m1["last_throw_status"] == "failed" and m1["current_mode"] == "3d"
    assert m1["recent_throws"] == 16 and m1["recent_mean_abs_error_m"] > 0
