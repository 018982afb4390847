"""End to end on the Drake machine: ``slinger up --engine drake`` runs the simulated machine in
Drake (sim_twin.twin.drake_machine) behind the machine interface; the console's API path (preview in
the MuJoCo twin, then the throw) throws the deployed 2D policy at it, with the release check on."""

from __future__ import annotations

import time

import numpy as np
import pytest

from runtime.telemetry import read_telemetry
from sim_twin.twin.drake_plant import UntrackedPayloadTwin, plant_twin
from sim_twin.twin.profile import RealityProfile
from tests.conftest import SlingerUp
from tests.test_stack import TARGET_2D, _landed_throw, _wait_ready


def test_the_drake_plant_publishes_no_payload_tracking():
    twin = plant_twin("drake", RealityProfile(), 0, "m1")
    assert isinstance(twin, UntrackedPayloadTwin)
    state = twin.state()
    assert state.payload_pos_m is None and state.payload_vel_mps is None and state.payload_attached
    assert plant_twin("mujoco", RealityProfile(), 0, "m1").state().payload_pos_m is not None
    with pytest.raises(ValueError, match="unknown physics engine"):
        plant_twin("bullet", RealityProfile(), 0, "m1")


@pytest.mark.system
def test_slinger_up_engine_drake_throws_from_the_console_path(tmp_path):
    up = SlingerUp(tmp_path, real_policies=True)
    up.argv += ["--engine", "drake"]
    with up:
        up.wait_machine_online()
        http = up.http

        def previewed_throw():  # as the console does: preview, then the throw naming the preview
            for _ in range(20):  # the gripper may still swing after a reload: preview again once settled
                _wait_ready(http)
                p = http.post("/api/previews", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D, "rollouts": 1})
                assert p.status_code == 200 and p.json()["status"] == "ok", p.text
                r = http.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": TARGET_2D, "preview_id": p.json()["id"]})
                if not (r.status_code == 409 and "moved since the preview" in r.text):
                    return r
                time.sleep(1.0)
            return r

        row, _ = _landed_throw(http, previewed_throw)
        assert row["status"] == "landed", row
        assert np.hypot(row["downrange_error_m"], row["crossrange_error_m"]) < 0.5, row
        tel = read_telemetry(up.data_dir / "telemetry" / f"{row['id']}.mcap")
        assert "released" in list(tel["event_phase"]) and tel["gripper_open"].any()
        assert len(tel["payload_pos_m"]) == 0  # no payload tracking, as from a real machine
    assert up.returncode == 0, up.output[-3000:]
