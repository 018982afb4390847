"""Clean edges (issue 24 finding 10, server part): unknown machines are 404, error bodies are
sentences naming the field, audit fields carry no control characters, served files never follow
a link out of their folder."""

from __future__ import annotations

import pytest

from server.db.models import AuditEntry, Machine, Throw
from server.jobs.specs import job_dir
from tests.conftest import wait_for
from tests.fixtures import finished_diagnosis_run


@pytest.mark.parametrize("path", ["estop", "abort", "estop/reset", "return-to-ready", "lease/takeover"])
def test_unknown_machine_is_404_known_offline_machine_is_503(client, path):
    r = client.post(f"/api/machines/ghost/{path}")
    assert r.status_code == 404 and r.json()["detail"] == "unknown machine 'ghost'", r.text
    with client.app.state.sessions.begin() as db:
        db.add(Machine(id="m7", simulated=True))
    r = client.post(f"/api/machines/m7/{path}")
    assert r.status_code == 503 and "m7" in r.json()["detail"], r.text
    assert "validation error" not in r.text.lower() and "pydantic" not in r.text.lower()


def test_validation_errors_are_sentences_naming_the_field(client):
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": ["x", 1]})
    assert r.status_code == 422
    body = r.json()
    assert isinstance(body["detail"], str) and body["detail"].startswith("invalid request: target")
    assert any(f.startswith("target") for f in body["fields"])
    assert "'input'" not in r.text and '"loc"' not in r.text  # no pydantic dump, no echo of the input
    r = client.post("/api/throws", content=b'{"machine_id": "m1", "mode": "2d", "target": [NaN, 0, 0]}',
                    headers={"content-type": "application/json"})
    assert r.status_code == 422 and isinstance(r.json()["detail"], str)
    schema = client.get("/openapi.json").json()["components"]["schemas"]["HTTPValidationError"]
    assert schema["properties"]["detail"]["type"] == "string"  # the document says what the body is


def test_audit_fields_have_no_control_characters(client):
    hostile = "stop\x1b[2J\r\nFAKE admin promote ok\x00\u2028"
    client.post("/api/machines/ghost/abort", json={"reason": hostile})

    def audited():
        with client.app.state.sessions() as db:
            return db.query(AuditEntry).filter(AuditEntry.action == "abort").all()

    rows = wait_for(audited, 10, "the abort attempt audited (written after the stop, on the fleet's database thread)")
    text = repr([(r.username, r.action, r.subject, r.detail) for r in rows])
    for row in rows:
        for value in (row.username, row.action, row.subject, *map(str, row.detail.values())):
            assert value is None or all(c.isprintable() for c in str(value)), value
    assert "\\\\x1b[2J\\\\r\\\\nFAKE" in text  # escaped, still readable


def test_served_files_never_follow_links_out_of_their_folder(client, settings, tmp_path):
    secret = tmp_path / "secret.txt"
    secret.write_text("not for the console")
    tele = settings.data_dir / "telemetry"
    tele.mkdir(parents=True, exist_ok=True)
    (tele / "link.mcap").symlink_to(secret)
    (tele / "real.mcap").write_bytes(b"\x89MCAP0\r\n")
    with client.app.state.sessions.begin() as db:
        db.add(Machine(id="m1", simulated=True))
        db.flush()
        for tid, name in (("tl", "link.mcap"), ("tr", "real.mcap")):
            db.add(Throw(id=tid, machine_id="m1", mode="2d", target_x_m=8, target_y_m=0, target_z_m=0,
                         status="landed", telemetry_path=f"telemetry/{name}"))
    assert client.get("/api/throws/tl/telemetry").status_code == 404
    assert client.get("/api/throws/tr/telemetry").status_code == 200

    run_id = finished_diagnosis_run(client.app.state, "m1", {}, profile={})
    report = job_dir(settings.data_dir, run_id) / "report"
    (report / "report.json").unlink()
    (report / "report.json").symlink_to(secret)
    base = f"/api/diagnosis/runs/{run_id}/files"
    r = client.get(f"{base}/report.json")
    assert r.status_code == 404 and "not for the console" not in r.text
    assert client.get(f"{base}/profile_fitted.json").status_code == 200


def test_domain_errors_map_to_one_answer_each(client):
    """One handler (server.api.errors): a Limited is 429 with Retry-After, a NotFound is 404, as
    {"detail": sentence} (a Refused's X-Refused-Condition: tests/test_control_chain.py)."""
    client.app.state.jobs.store.max_active_per_user = 0  # as if the admin had their limit of jobs queued
    r = client.post("/api/jobs", json={"kind": "probe"})
    assert r.status_code == 429 and r.headers["retry-after"] == "1" and "limit per user" in r.json()["detail"]
    r = client.post("/api/policies/999/promote", json={"machine_ids": ["m1"]})
    assert r.status_code == 404 and r.json() == {"detail": "no policy version 999"}
    r = client.post("/api/throws", json={"machine_id": "ghost", "mode": "2d", "target": [8.0, -0.292, 0.0]})
    assert r.status_code == 404 and r.json()["detail"] == "unknown machine 'ghost'"
