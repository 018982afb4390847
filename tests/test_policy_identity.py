"""Throws keyed by policy identity: a throw records the SHA-256 of the policy that made it (from
the runtime's ack, or the policy it reports), accuracy and comparisons group by it even when two
versions share a name; modes and statuses are enums in the database (CHECK) and the API."""

from __future__ import annotations

import pytest
from sqlalchemy import text
from sqlalchemy.exc import IntegrityError, StatementError

from server.db.models import Machine, PolicyVersion, Throw
from tests.conftest import wait_for, wait_online

SHA_A, SHA_B = "a" * 64, "b" * 64


def _throws(db, sha: str, name: str, down: float, n: int = 4, start: int = 0) -> None:
    for i in range(n):
        db.add(Throw(id=f"{sha[0]}{start + i}", machine_id="m1", mode="2d", target_x_m=8.0, target_y_m=0.0,
                     target_z_m=0.0, status="landed", downrange_error_m=down + 0.01 * i, crossrange_error_m=0.0,
                     policy_version=name, policy_sha256=sha))


def test_accuracy_and_compare_group_by_sha_not_name(client):
    with client.app.state.sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
        db.add_all([PolicyVersion(name="same", mode="2d", sha256=SHA_A, manifest={}),
                    PolicyVersion(name="same", mode="2d", sha256=SHA_B, manifest={})])
        _throws(db, SHA_A, "same", 0.10)
        _throws(db, SHA_B, "same", -0.30, start=10)
    groups = client.get("/api/throws/accuracy").json()
    assert sorted((g["policy_sha256"], g["n"]) for g in groups) == [(SHA_A, 4), (SHA_B, 4)]
    by = {g["policy_sha256"]: g for g in groups}
    assert by[SHA_A]["bias_m"] == pytest.approx(0.115) and by[SHA_B]["bias_m"] == pytest.approx(-0.285)
    assert len(client.get("/api/throws", params={"policy_sha256": SHA_B}).json()) == 4
    assert client.get("/api/throws", params={"policy_sha256": "xyz"}).status_code == 422
    ids = {p["sha256"]: p["id"] for p in client.get("/api/policies").json()}
    cmp = client.get("/api/policies/compare", params={"ids": [ids[SHA_A], ids[SHA_B]]}).json()
    assert [c["logged"][0]["n"] for c in cmp] == [4, 4] and cmp[0]["logged"][0]["bias_m"] != cmp[1]["logged"][0]["bias_m"]


def test_a_throw_records_the_policy_sha(client, fake_runtime_factory):
    rt = fake_runtime_factory()  # reports fake-2d with sha "ab"*32, acks without a SHA
    wait_online(client)
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": [8.0, -0.292, 0.0]})
    assert r.status_code == 202, r.text
    assert r.json()["policy_sha256"] == rt.policies[0].sha256
    t = wait_for(lambda: (x := client.get(f"/api/throws/{r.json()['id']}").json())["status"] == "landed" and x, 10)
    assert t["policy_sha256"] == "ab" * 32 and t["mode"] == "2d"


def test_modes_and_statuses_are_database_enums(client):
    sessions = client.app.state.sessions
    with sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
    with pytest.raises(StatementError, match="status"), sessions.begin() as db:
        db.add(Throw(id="x", machine_id="m1", mode="2d", target_x_m=8, target_y_m=0, target_z_m=0, status="flying"))
    with pytest.raises(IntegrityError), sessions.begin() as db:  # the CHECK holds for raw SQL too
        db.execute(text("INSERT INTO throws (id, machine_id, mode, target_x_m, target_y_m, target_z_m, status, "
                        "requested_at) VALUES ('y', 'm1', '4d', 8, 0, 0, 'landed', '2026-01-01 00:00:00')"))
    assert client.get("/api/throws", params={"status": "flying"}).status_code == 422
    spec = client.get("/openapi.json").json()["components"]["schemas"]["ThrowOut"]["properties"]
    assert "lost" in spec["status"]["enum"] and spec["mode"]["enum"] == ["2d", "3d"]
