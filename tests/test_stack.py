"""Integration: the real simulated machine and the real runtime (subprocesses, as `slinger up`
starts them) with the server on loopback Zenoh; throws go through the HTTP API.

The test policy (tests.fixtures.write_test_policy, release_after_bias=2.0) releases at once, so
a throw is short: swing start -> release -> flight -> impact.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from runtime.telemetry import read_telemetry
from runtime.throw_geometry import impact_errors
from server.stack import Children, resolve_policy, slinger_command
from tests.conftest import free_port, wait_for, wait_online
from tests.fixtures import write_test_policy

TARGET_2D = [8.0, -0.292, 0.0]


def _landed_or_final(get_row):
    row = get_row()
    return row if row["status"] in ("landed", "failed", "aborted") else None


@pytest.fixture
def machine(tmp_path, zenoh_endpoint):
    """Real plant + runtime for m1 connecting to the server's endpoint; stopped afterwards."""
    policy = write_test_policy(tmp_path / "policies", "2d", release_after_bias=2.0)
    children = Children()
    link = ["--connect", zenoh_endpoint, "--listen", "tcp/127.0.0.1:0"]
    children.spawn("plant", slinger_command("plant", "--machine-id", "m1", "--seed", "3", *link), tmp_path / "logs")
    children.spawn("runtime", slinger_command("runtime", "--machine-id", "m1", "--policy-2d", str(policy), *link,
                                              "--outbox-dir", str(tmp_path / "outbox")), tmp_path / "logs")
    yield policy
    children.stop(grace_s=15)
    for c in children.items:
        assert c.proc.returncode is not None


def test_throw_with_real_plant_and_runtime(client, machine, settings, throw_count):
    m = wait_online(client, "m1", timeout_s=60)
    assert m["simulated"] is True and m["policies"] == {"2d": "test-linear"}

    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D})
    assert r.status_code == 202, r.text
    tid = r.json()["id"]
    row = wait_for(lambda: _landed_or_final(lambda: client.get(f"/api/throws/{tid}").json()), 60, "throw end")
    assert row["status"] == "landed", row
    assert row["policy_version"] == "test-linear"
    impact = row["impact"]
    assert impact is not None and abs(impact[2]) < 0.5 and np.hypot(impact[0], impact[1]) > 2.0
    down, cross = impact_errors(TARGET_2D, impact)
    assert row["downrange_error_m"] == pytest.approx(down, abs=1e-6)
    assert row["crossrange_error_m"] == pytest.approx(cross, abs=1e-6)
    assert row["released_at"] is not None and row["completed_at"] >= row["requested_at"]

    path = settings.data_dir / "telemetry" / f"{tid}.mcap"
    tel = read_telemetry(path)
    n = len(tel["t_s"])
    assert n > 10 and tel["q"].shape == (n, 6) and np.all(np.diff(tel["t_s"]) > 0)
    assert tel["gripper_cmd"][-1] and tel["gripper_open"].any()  # released, and it opened
    assert len(tel["payload_pos_m"]) > 0
    assert "released" in list(tel["event_phase"])
    assert client.get(row["telemetry_url"]).content == path.read_bytes()
    assert throw_count() == 1

    # an out-of-plane 2D target is refused before reaching the runtime
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": [0.0, 8.0, 0.0]})
    assert r.status_code == 422 and "plane" in r.json()["detail"]
    # the runtime has no 3D policy: its refusal comes back as 422 with its reason
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "3d", "target": [6.0, 5.0, 0.0]})
    assert r.status_code == 422 and r.json()["detail"]
    assert throw_count() == 1


def test_resolve_policy_explains_what_is_missing(tmp_path):
    assert resolve_policy(None, tmp_path / "throw2d.onnx")[1] == f"no policy at {tmp_path / 'throw2d.onnx'}"
    (tmp_path / "p.onnx").write_bytes(b"x")
    assert "no manifest" in resolve_policy(tmp_path / "p.onnx", tmp_path / "d.onnx")[1]
    policy = write_test_policy(tmp_path, "2d")
    assert resolve_policy(policy, tmp_path / "d.onnx") == (policy, None)


def test_slinger_up_end_to_end_and_ctrl_c(tmp_path):
    """`slinger up` as the operator runs it; Ctrl-C (SIGINT) stops server, plant and runtime."""
    policy = write_test_policy(tmp_path / "policies", "2d", release_after_bias=2.0)
    port, zport, vport = free_port(), free_port(), free_port()
    log = open(tmp_path / "up.log", "wb")
    proc = subprocess.Popen(
        slinger_command("up", "--policy-2d", str(policy), "--data-dir", str(tmp_path / "var"),
                        "--port", str(port), "--zenoh-port", str(zport), "--viser-port", str(vport)),
        stdout=log, stderr=subprocess.STDOUT, start_new_session=True, cwd=tmp_path,
    )
    base = f"http://127.0.0.1:{port}"
    try:
        def online():
            try:
                ms = httpx.get(f"{base}/api/machines", timeout=2).json()
            except httpx.HTTPError:
                return None
            return ms and ms[0]["online"] and ms[0]["cabin_turn_rad"] is not None and ms[0]

        m = wait_for(online, 90, "slinger up: m1 online")
        assert m["id"] == "m1" and m["simulated"]
        assert httpx.get(f"{base}/api/scene").json()["viser_port"] == vport
        assert "Slinger" in httpx.get(f"{base}/", follow_redirects=True).text
        r = httpx.post(f"{base}/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D}, timeout=10)
        assert r.status_code == 202, r.text
        tid = r.json()["id"]
        row = wait_for(lambda: _landed_or_final(lambda: httpx.get(f"{base}/api/throws/{tid}").json()), 60, "throw end")
        assert row["status"] == "landed" and row["impact"] is not None
        assert (tmp_path / "var" / "telemetry" / f"{tid}.mcap").is_file()
    finally:
        os.kill(proc.pid, signal.SIGINT)
        try:
            rc = proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            raise
        finally:
            log.close()
    out = (tmp_path / "up.log").read_text()
    assert rc == 0, out[-3000:]
    assert f"Slinger console: http://127.0.0.1:{port}/" in out
    # the children are gone too (they have their own sessions; up must have stopped them)
    ps = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout
    assert str(tmp_path / "var" / "outbox") not in ps
