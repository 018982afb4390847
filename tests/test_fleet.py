"""The fleet topology without Docker (tests/fleet_site.py): the Zenoh router, the site host
(server and worker on PostgreSQL) and each simulated machine on its own network namespace, every
Zenoh link mutual TLS with the site's access control. Peers without a site certificate (none, or
one of another CA) cannot open a link to the router, and a site certificate of another role (the
worker's) cannot get a ThrowRequest to a runtime; the server's role can (positive control). One
machine host's link is cut mid-throw and restored: no throw is lost, the machine's valves go
neutral, it rejoins and throws again. docker/compose.yaml names the same services, over TLS."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import pytest
import yaml
import zenoh

from runtime.protocol import keys
from runtime.protocol.messages import ThrowAck, ThrowRequest, decode, encode
from runtime.zenoh_session import TlsFiles, open_session
from server.site.certs import make_site

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
    zenoh_users = {n: s["command"] for n, s in compose["services"].items()
                   if s.get("command") and s["command"][0] in ("router", "server", "plant", "runtime")}
    for name, command in zenoh_users.items():  # every Zenoh link is TLS with the site's files
        endpoints = [command[i + 1] for i, a in enumerate(command) if a in ("--listen", "--connect")]
        assert endpoints and all(e.startswith("tls/") for e in endpoints), (name, command)
        assert "--tls-dir" in command and any(v.endswith(":/site:ro") for v in compose["services"][name]["volumes"]), name


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
        assert site.router_endpoint.startswith("tls/") and "127.0.0.1" not in site.base_url
        replies = _throw_requests_from_peers(site, tmp_path)
        assert replies.pop("site certificate, server role")[0] == "unsigned", replies  # reached the runtime
        assert all(r == [] or r == "no link" for r in replies.values()), replies
        assert replies["no certificate (plain TCP)"] == "no link" and replies["certificate of another CA"] == "no link"
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
        third = wait_for(lambda: (s := status(site, t3)) in FINAL and s, 60)
        assert third == "landed", (site.http.get(f"/api/throws/{t3}").json()["failure_reason"],
                                   site.log("plant-m1")[-1500:], site.log("runtime-m1")[-3000:])
        rows = site.http.get("/api/throws", params={"limit": 10}).json()
        assert {r["id"] for r in rows} == {t1, t2, t3} and not [r for r in rows if r["status"] not in FINAL]


def _throw_requests_from_peers(site: Site, tmp_path: Path) -> dict[str, list | str]:
    """An unsigned ThrowRequest for m1 from peers on the test's own namespace (it reaches the
    router's port over the bridge): the refusal reasons of the ThrowAcks that came back, or
    "no link" when the peer could not connect to the router at all."""
    other_ca = make_site(tmp_path / "other-ca", ["m1"], ips=[site.router_endpoint.split("/")[1].rsplit(":", 1)[0]])
    peers = {
        "no certificate (plain TCP)": (site.router_endpoint.replace("tls/", "tcp/"), None),
        "certificate of another CA": (site.router_endpoint, TlsFiles.from_site(other_ca.root, "server")),
        "site certificate, worker role": (site.router_endpoint, TlsFiles.from_site(site.site_dir, "worker")),
        "site certificate, server role": (site.router_endpoint, TlsFiles.from_site(site.site_dir, "server")),
    }
    out: dict[str, list | str] = {}
    for name, (endpoint, tls) in peers.items():
        req = ThrowRequest(throw_id=str(uuid.uuid4()), machine_id="m1", mode="2d", target_m=TARGET)
        try:
            with open_session("client", connect=[endpoint], tls=tls) as s:
                time.sleep(0.5)  # let the router propagate the runtime's queryable
                acks = [decode(ThrowAck, r.ok.payload.to_bytes()) for r in
                        s.get(keys.throw("m1"), payload=encode(req), timeout=2.0) if r.ok is not None]
            out[name] = [("unsigned" if "unsigned" in (a.reason or "") else a.reason) for a in acks if not a.accepted]
            assert not any(a.accepted for a in acks), (name, acks)
        except zenoh.ZError:
            out[name] = "no link"
    return out


def _try_throw(site: Site, machine_id: str) -> str | None:
    try:
        return throw(site, machine_id)
    except AssertionError:
        return None
