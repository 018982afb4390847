"""The fleet topology without Docker (tests/fleet_site.py): a Zenoh router process, the server
and a worker on PostgreSQL, simulated machines on their own network namespaces as Zenoh
clients; one machine host's link is cut mid-throw and restored: no throw is lost, the machine's
valves go neutral, it rejoins and throws again. docker/compose.yaml names the same services."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import wait_for
from tests.fleet_site import SERVICES, Site, netns_available
from tests.fixtures import write_test_policy

REPO = Path(__file__).resolve().parent.parent
TARGET = [8.0, -0.292, 0.0]
FINAL = ("landed", "failed", "aborted", "lost")


def test_compose_names_every_service_the_process_test_starts():
    compose = yaml.safe_load((REPO / "docker" / "compose.yaml").read_text())
    commands = {name: (svc.get("command") or [None])[0] for name, svc in compose["services"].items()}
    assert set(SERVICES) <= set(commands.values()), commands
    assert "db" in compose["services"]  # PostgreSQL
    env = compose["services"]["worker"]["environment"]
    assert env["SLINGER_JOB_QUEUE_URL"].startswith("postgresql://")


def throw(site: Site, machine_id: str) -> str:
    """Preview (in the worker) and throw; returns the throw id."""
    p = site.http.post("/api/previews", json={"machine_id": machine_id, "mode": "2d", "target": TARGET, "rollouts": 1})
    assert p.status_code == 200 and p.json()["status"] == "ok", p.text
    r = site.http.post("/api/throws", json={"machine_id": machine_id, "mode": "2d", "target": TARGET,
                                            "preview_id": p.json()["id"]})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def status(site: Site, tid: str) -> str:
    return site.http.get(f"/api/throws/{tid}").json()["status"]


@pytest.mark.postgres
def test_cut_a_machine_hosts_link_mid_throw(tmp_path):
    reason = netns_available()
    if reason:
        pytest.skip(reason)
    policy = write_test_policy(tmp_path / "policies", "2d", release_after_bias=2.0)
    with Site(tmp_path, machines=2, policy=policy, netns=True) as site:
        wait_for(lambda: set(site.online()) == {"m1", "m2"}, 120, "both machines online through the router")
        t1, t2 = throw(site, "m1"), throw(site, "m2")
        wait_for(lambda: status(site, t1) != "requested", 30, "m1 throw under way")
        site.cut("m1")
        try:
            wait_for(lambda: "valves neutral" in site.log("plant-m1"), 20, "m1 valves neutral (plant watchdog)")
            assert wait_for(lambda: (s := status(site, t2)) in FINAL and s, 60) == "landed"  # m2 unaffected
            time.sleep(2.0)
        finally:
            site.restore("m1")
        final = wait_for(lambda: (s := status(site, t1)) in FINAL and s != "lost" and s, 90, "m1 result delivered")
        assert final in ("landed", "failed", "aborted"), site.log("runtime-m1")[-3000:]
        print("throw cut mid-way:", final, site.http.get(f"/api/throws/{t1}").json()["failure_reason"])
        wait_for(lambda: "m1" in site.online(), 60, "m1 rejoined")
        t3 = wait_for(lambda: _try_throw(site, "m1"), 60, "m1 accepts a throw again")
        assert wait_for(lambda: (s := status(site, t3)) in FINAL and s, 60) == "landed"
        rows = site.http.get("/api/throws", params={"limit": 10}).json()
        assert {r["id"] for r in rows} == {t1, t2, t3} and not [r for r in rows if r["status"] not in FINAL]


def _try_throw(site: Site, machine_id: str) -> str | None:
    try:
        return throw(site, machine_id)
    except AssertionError:
        return None
