"""Integration: the real simulated machine and the real runtime (subprocesses, as `slinger up`
starts them) with the server on loopback Zenoh; throws go through the HTTP API.

The test policy (tests.fixtures.write_test_policy, release_after_bias=2.0) releases at once, so
a throw is short: swing start -> release -> flight -> impact.
"""

from __future__ import annotations

import subprocess
from pathlib import Path
import time

import httpx
import numpy as np
import pytest

from runtime.telemetry import read_telemetry
from runtime.throw_geometry import impact_errors
from server.site.stack import Children, resolve_policy, slinger_command
from tests.conftest import TEST_POLICY_CHECK, SlingerUp, login, wait_for, wait_online
from tests.fixtures import write_test_policy

REPO = Path(__file__).resolve().parents[1]

TARGET_2D = [8.0, -0.292, 0.0]


LOAD_FAULT = "machine fault: behind real time"
LOAD_FAILURES = (LOAD_FAULT, "machine link lost")
"""What a machine too loaded to keep real time makes of a throw (plant behind, states late)."""
LOAD_REFUSALS = (LOAD_FAULT, "machine offline (no recent state)")
"""What it makes of a throw request: the runtime's last state older than its link timeout (0.2 s)."""


def _landed_throw(http, post, attempts: int = 4, machine_id: str = "m1"):
    """``post()`` a throw for ``machine_id`` once the runtime reports it ready (as the console's
    Throw button waits: the server seeing the machine's states does not mean the runtime does yet,
    its link to the machine may still be forming), and wait for its final row. On a loaded machine
    the simulated machine may fall behind real time: the runtime then rightly refuses the throw
    (422) or fails it (LOAD_FAILURES); wait for it to keep up and try again. Returns (the final row,
    throws stored)."""
    stored = 0
    for _ in range(attempts):
        _wait_ready(http, machine_id)
        r = post()
        if r.status_code == 422 and any(reason in r.text for reason in LOAD_REFUSALS):
            time.sleep(2.0)
            continue
        assert r.status_code == 202, r.text
        stored += 1
        tid = r.json()["id"]
        row = wait_for(lambda: _landed_or_final(lambda: http.get(f"/api/throws/{tid}").json()), 60, "throw end")
        if not (row["status"] == "failed" and (row.get("failure_reason") or "").startswith(LOAD_FAILURES)):
            return row, stored
        time.sleep(2.0)
    return row, stored


def _wait_ready(http, machine_id: str = "m1", timeout_s: float = 60.0) -> None:
    """Wait until the machine reports ready, as the console's Throw button does: after a landing
    the simulated machine loads the next payload RELOAD_AFTER_LANDING_S of simulated time later,
    which on a loaded host takes longer in wall time."""
    def ready():
        return any(m["id"] == machine_id and m.get("ready") for m in http.get("/api/machines").json())
    wait_for(ready, timeout_s, f"{machine_id} ready")


def _landed_or_final(get_row):
    row = get_row()
    return row if row["status"] in ("landed", "failed", "aborted") else None


@pytest.fixture
def machine(tmp_path, zenoh_endpoint, settings):
    """Real plant + runtime for m1 connecting to the server's endpoint; stopped afterwards. The
    runtime gets m1's command key from the server's site directory (made here, as `slinger up` does)."""
    from server.site.certs import make_site

    site = make_site(settings.resolved_site_dir, ["m1"])
    policy = write_test_policy(tmp_path / "policies", "2d", release_after_bias=2.0)
    children = Children()
    link = ["--connect", zenoh_endpoint, "--listen", "tcp/127.0.0.1:0"]
    children.spawn("plant", slinger_command("plant", "--machine-id", "m1", "--seed", "3", *link), tmp_path / "logs")
    children.spawn("runtime", slinger_command("runtime", "--machine-id", "m1", "--policy-2d", str(policy), *link,
                                              "--command-key", str(site.command_key("m1")), *TEST_POLICY_CHECK,
                                              "--outbox-dir", str(tmp_path / "outbox")), tmp_path / "logs")
    yield policy
    children.stop(grace_s=15)
    for c in children.items:
        assert c.proc.returncode is not None


def test_throw_with_real_plant_and_runtime(client, machine, settings, throw_count):
    m = wait_online(client, "m1", timeout_s=60)
    assert m["simulated"] is True and m["policies"] == {"2d": "test-linear"}

    row, stored = _landed_throw(client, lambda: client.post("/api/throws", json={"machine_id": "m1", "mode": "2d",
                                                                                "target": TARGET_2D}))
    assert row["status"] == "landed", row
    tid = row["id"]
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
    assert throw_count() == stored

    # an out-of-plane 2D target is refused before reaching the runtime
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": [0.0, 8.0, 0.0]})
    assert r.status_code == 422 and "plane" in r.json()["detail"]
    # the runtime has no 3D policy: its refusal comes back as 422 with its reason
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "3d", "target": [6.0, 5.0, 0.0]})
    assert r.status_code == 422 and r.json()["detail"]
    assert throw_count() == stored


def test_resolve_policy_explains_what_is_missing(tmp_path):
    assert resolve_policy(None, tmp_path / "throw2d.onnx")[1] == f"no policy at {tmp_path / 'throw2d.onnx'}"
    (tmp_path / "p.onnx").write_bytes(b"x")
    assert "no manifest" in resolve_policy(tmp_path / "p.onnx", tmp_path / "d.onnx")[1]
    policy = write_test_policy(tmp_path, "2d")
    assert resolve_policy(policy, tmp_path / "d.onnx") == (policy, None)


def test_slinger_up_end_to_end_and_ctrl_c(tmp_path):
    """`slinger up` as the operator runs it; Ctrl-C (SIGINT) stops server, plant and runtime."""
    with SlingerUp(tmp_path) as up:
        m = up.wait_machine_online()
        assert m["simulated"] and m["policies"] == {"2d": "test-linear"}
        http = up.http
        assert http.get("/api/scene").json()["viser_port"] == up.viser_port
        assert "Slinger" in http.get("/", follow_redirects=True).text
        r = http.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D})
        assert r.status_code == 422 and r.headers["x-refused-condition"] == "preview_missing"  # the server gates
        def previewed_throw():  # _landed_throw calls it once the machine is ready
            p = http.post("/api/previews", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D, "rollouts": 1})
            assert p.status_code == 200 and p.json()["status"] == "ok", p.text
            return http.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D,
                                                  "preview_id": p.json()["id"]})

        row, _ = _landed_throw(http, previewed_throw)
        assert row["status"] == "landed" and row["impact"] is not None, row
        tid = row["id"]
        assert (up.data_dir / "telemetry" / f"{tid}.mcap").is_file()
    assert up.returncode == 0, up.output[-3000:]
    assert f"Slinger console: http://127.0.0.1:{up.port}/" in up.output
    # the children are gone too (they run in their own sessions; up must have stopped them)
    ps = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout
    assert str(up.data_dir / "outbox") not in ps


def test_slinger_up_throws_with_the_deployed_policies_and_the_release_check_on(tmp_path):
    """The main job as an operator runs it: the repository's deployed policies (2D and 3D) on the
    simulated machine, the runtime's release check ON. A previewed throw per mode lands near its
    target (2D sigma ~0.1 m, 3D ~0.2 m in the site matrix: bounds at several sigma)."""
    import json

    with SlingerUp(tmp_path, real_policies=True) as up:
        up.wait_machine_online()
        deployed = {mode: json.loads((REPO / "policies" / f"throw{mode}.json").read_text())["name"] for mode in ("2d", "3d")}
        http = up.http
        wait_for(lambda: [m["policies"] for m in http.get("/api/machines").json()] == [deployed], 30, "deployed policies reported")
        for mode, target, bound_m in (("2d", TARGET_2D, 0.5), ("3d", [6.0, 5.0, 0.0], 1.2)):
            def previewed_throw():
                for _ in range(20):  # after a throw the gripper swings on: preview again until it has settled
                    _wait_ready(http)  # the next payload loaded, the machine at rest
                    p = http.post("/api/previews", json={"machine_id": "m1", "mode": mode, "target": target, "rollouts": 1})
                    assert p.status_code == 200 and p.json()["status"] == "ok", p.text
                    r = http.post("/api/throws", json={"machine_id": "m1", "mode": mode, "target": target,
                                                       "preview_id": p.json()["id"], "confirm_clearance": mode == "3d"})
                    if not (r.status_code == 409 and "moved since the preview" in r.text):
                        return r
                    time.sleep(1.0)
                return r

            row, _ = _landed_throw(http, previewed_throw)
            assert row["status"] == "landed", row
            assert np.hypot(row["downrange_error_m"], row["crossrange_error_m"]) < bound_m, row
            tel = read_telemetry(up.data_dir / "telemetry" / f"{row['id']}.mcap")
            assert "released" in list(tel["event_phase"])
    assert up.returncode == 0, up.output[-3000:]


def test_slinger_up_without_policy_refuses_the_runtime(tmp_path):
    """No policy: the server and the simulated machine run, the runtime is not started.
    No user yet: `slinger up` creates a local admin and prints its credentials once."""
    import re

    up = SlingerUp(tmp_path, create_admin=False)
    i = up.argv.index("--policy-2d")
    up.argv[i + 1] = str(tmp_path / "missing.onnx")
    with up:
        import time

        wait_for(lambda: httpx.get(f"{up.base_url}/api/health", timeout=2).status_code == 200
                 if _reachable(up.base_url) else None, 60, "server up")
        assert httpx.get(f"{up.base_url}/api/machines").status_code == 401  # not logged in
        match = wait_for(lambda: re.search(r"user: admin\s+password: (\S+)", up.log_text()), 30, "credentials")
        http = httpx.Client(base_url=up.base_url, timeout=10)
        login(http, "admin", match.group(1))
        wait_for(lambda: http.get("/api/machines").json(), 60, "plant state")
        time.sleep(1.0)
        ms = http.get("/api/machines").json()
        http.close()
        assert [(m["id"], m["online"], m["simulated"]) for m in ms] == [("m1", False, True)]
    assert up.returncode == 0
    assert "NOT starting any runtime" in up.output and "missing.onnx" in up.output


def _reachable(base: str) -> bool:
    try:
        httpx.get(f"{base}/api/health", timeout=1)
        return True
    except httpx.HTTPError:
        return False


def test_slinger_up_prints_credentials_only_once(tmp_path):
    """A second `slinger up` on the same data finds the admin and prints no password."""
    from server.db.session import make_engine, make_sessionmaker
    from server.db.migrate import upgrade
    from server.accounts.cli import ensure_local_admin
    from server.accounts.auth import user_count

    url = f"sqlite:///{tmp_path / 'v.db'}"
    upgrade(url)
    import contextlib
    import io

    for expect in (True, False):
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf):
            ensure_local_admin(url)
        assert ("password:" in buf.getvalue()) is expect
    engine = make_engine(url)
    with make_sessionmaker(engine)() as db:
        assert user_count(db) == 1
    engine.dispose()
