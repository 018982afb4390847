"""Policy versions: upload validation (reasons), twin evaluation stored, promotion to a real
runtime over Zenoh (fetch, SHA-256, load between throws, confirm), rollback, compare, audit."""

from __future__ import annotations

import pytest

from tests.conftest import wait_for, wait_online
from tests.fixtures import write_test_policy
from tests.test_stack import machine  # noqa: F401 (real plant + runtime fixture)


def upload(client, path, mode="2d", name="p", **extra):
    with open(path, "rb") as f:
        return client.post("/api/policies", files={"file": (path.name, f, "application/octet-stream")},
                           data={"mode": mode, "name": name, **extra})


@pytest.fixture
def quick_eval(settings):
    settings.eval_distances_m = [8.0]
    settings.eval_throws = 2
    return settings


def test_upload_rejections_with_reasons(client, tmp_path, quick_eval):
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"this is not a model")
    r = upload(client, junk)
    assert r.status_code == 422 and "not a loadable ONNX model" in r.json()["detail"]
    p3 = write_test_policy(tmp_path / "p3", "3d")
    r = upload(client, p3, mode="2d")
    assert r.status_code == 422 and "features, mode 2d with 4 history steps needs 56" in r.json()["detail"]
    h8 = write_test_policy(tmp_path / "h8", "2d", history_steps=8)
    r = upload(client, h8)  # trained with 8 history steps, uploaded as the default 4: refused, the fit named
    assert r.status_code == 422 and "needs 56 (it fits 8 history steps: declare history_steps 8)" in r.json()["detail"]
    assert upload(client, h8, history_steps=0).status_code == 422
    nan = write_test_policy(tmp_path / "nan", "2d", release_after_bias=float("nan"))
    r = upload(client, nan)
    assert r.status_code == 422 and "non-finite" in r.json()["detail"]
    good = write_test_policy(tmp_path / "good", "2d")
    assert upload(client, good, target_min_m=9, target_max_m=8).status_code == 422
    assert upload(client, good, name="bad name!").status_code == 422
    assert client.post("/api/policies", data={"mode": "2d", "name": "x"}).status_code == 422  # no file
    assert client.get("/api/policies").json() == []


def test_upload_evaluates_in_the_twin_and_compare(client, tmp_path, quick_eval):
    good = write_test_policy(tmp_path / "good", "2d", release_after_bias=2.0)
    r = upload(client, good, name="good-v1", notes="first")
    assert r.status_code == 201, r.text
    p = r.json()
    assert p["has_file"] and p["target_range_m"] == [5.0, 10.7] and p["evaluation_status"] in ("pending", "running", "done")
    assert upload(client, good, name="again").status_code == 409
    done = wait_for(lambda: (x := client.get(f"/api/policies/{p['id']}").json())["evaluation_status"] == "done" and x, 60)
    t = done["metrics"]["targets"][0]
    assert t["target_m"] == 8.0 and t["throws"] == 2
    cmp = client.get("/api/policies/compare", params={"ids": [p["id"]]}).json()
    assert cmp[0]["twin"][0]["target_m"] == 8.0 and cmp[0]["logged"] == []
    assert client.get("/api/policies/compare", params={"ids": [999]}).status_code == 404
    assert [a["action"] for a in client.get("/api/audit", params={"action": "policy_upload"}).json()] == ["policy_upload"]
    # a policy that reads 8 control steps of history, declared at upload: stored with that layout and
    # evaluated in the twin, whose executor keeps 8 steps for it
    h8 = write_test_policy(tmp_path / "h8", "2d", release_after_bias=2.0, history_steps=8)
    r = upload(client, h8, name="h8", history_steps=8)
    assert r.status_code == 201, r.text
    done = wait_for(lambda: (x := client.get(f"/api/policies/{r.json()['id']}").json())["evaluation_status"] == "done" and x, 60)
    assert done["metrics"]["targets"][0]["throws"] == 2


def test_only_admins_upload_and_promote(client, tmp_path):
    from tests.conftest import add_user, login

    add_user(client.app.state.sessions, "otto", "operator-pass", "operator")
    client.cookies.clear()
    login(client, "otto", "operator-pass")
    assert upload(client, write_test_policy(tmp_path, "2d")).status_code == 403
    assert client.post("/api/policies/1/promote", json={"machine_ids": ["m1"]}).status_code == 403
    assert client.post("/api/policies/rollback", json={"machine_id": "m1", "mode": "2d"}).status_code == 403
    assert client.get("/api/policies").status_code == 200


def test_promote_offline_machine_fails_with_reason(client, tmp_path, quick_eval):
    p = upload(client, write_test_policy(tmp_path, "2d"), name="pz").json()
    deps = client.post(f"/api/policies/{p['id']}/promote", json={"machine_ids": ["ghost"]}).json()
    assert deps[0]["status"] == "failed" and "offline" in deps[0]["reason"]
    assert client.post("/api/policies/999/promote", json={"machine_ids": ["m1"]}).status_code == 404
    r = client.post("/api/policies/rollback", json={"machine_id": "ghost", "mode": "2d"})
    assert r.status_code == 409 and "no previous" in r.json()["detail"]


def test_promote_and_rollback_on_a_real_runtime(client, machine, tmp_path, quick_eval):  # noqa: F811
    wait_online(client, "m1", timeout_s=60)
    a = upload(client, write_test_policy(tmp_path / "a", "2d", name="pa", seed=1, release_after_bias=2.0), name="pa").json()
    b = upload(client, write_test_policy(tmp_path / "b", "2d", name="pb", seed=2, release_after_bias=2.0), name="pb").json()

    def runs(name):
        return wait_for(lambda: client.get("/api/machines").json()[0]["policies"].get("2d") == name, 30, f"m1 runs {name}")

    for p in (a, b):
        deps = client.post(f"/api/policies/{p['id']}/promote", json={"machine_ids": ["m1"]}).json()
        assert deps[0]["status"] == "offered", deps
        runs(p["name"])
    d = wait_for(lambda: (x := client.get("/api/policies/deployments").json())[0]["status"] == "active" and x, 10)
    assert [x["policy_version"] for x in d[:2]] == ["pb", "pa"]

    # a throw now runs the promoted version
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": [8.0, -0.292, 0.0]})
    assert r.status_code == 202 and r.json()["policy_version"] == "pb"
    wait_for(lambda: client.get(f"/api/throws/{r.json()['id']}").json()["status"] in ("landed", "failed"), 60)

    r = client.post("/api/policies/rollback", json={"machine_id": "m1", "mode": "2d"})
    assert r.status_code == 200 and r.json()["policy_version"] == "pa"
    runs("pa")
    actions = [x["action"] for x in client.get("/api/audit").json()]
    assert actions.count("promote") == 2 and actions.count("rollback") == 1


def test_unconfirmed_promotion_times_out_with_reason(client, tmp_path, quick_eval):
    from datetime import timedelta

    from server.db.models import Machine, PolicyDeployment
    from server.db.types import utcnow
    from server.policies.versions import OFFER_TIMEOUT_S

    p = upload(client, write_test_policy(tmp_path, "2d"), name="pt").json()
    with client.app.state.sessions.begin() as db:
        db.add(Machine(id="m9", simulated=True))
        db.flush()
        db.add_all([
            PolicyDeployment(machine_id="m9", mode="2d", policy_version_id=p["id"], status="offered",
                             requested_by="admin", requested_at=utcnow() - timedelta(seconds=OFFER_TIMEOUT_S + 5)),
            PolicyDeployment(machine_id="m9", mode="2d", policy_version_id=p["id"], status="offered",
                             requested_by="admin", requested_at=utcnow()),
        ])
    deps = client.get("/api/policies/deployments", params={"machine_id": "m9"}).json()
    assert [d["status"] for d in deps] == ["offered", "failed"]  # newest first: the fresh offer waits
    assert "no confirmation" in deps[1]["reason"]
