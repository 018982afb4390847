"""The 3D scene without a browser: click-ray -> ground target, drawing from states and telemetry."""

from __future__ import annotations

import time

import numpy as np
import pytest

from runtime.machine import forward_kinematics
from runtime.protocol.messages import MachineState
from runtime.telemetry import TelemetryRecorder, write_mcap
from server.scene import ConsoleScene, ground_point
from tests.conftest import free_port, wait_for


def test_ground_point_intersects_the_ray_with_z0():
    p = ground_point((0.0, 0.0, 10.0), (0.6, 0.0, -0.8))
    assert p == pytest.approx([7.5, 0.0, 0.0])
    p = ground_point((-5.0, -5.0, 4.0), (2.0, 1.0, -1.0))  # direction need not be unit length
    assert p == pytest.approx([3.0, -1.0, 0.0])
    assert ground_point((0, 0, 10), (1, 0, 0)) is None  # parallel to the ground
    assert ground_point((0, 0, 10), (0, 0, 1)) is None  # looking up
    assert ground_point((0, 0, -1), (0, 0, -1)) is None  # camera below the ground
    assert ground_point((0, 0, 1), (1, 0, -1e-6)) is None  # hit beyond the horizon limit


class _Fleet:
    def __init__(self, state):
        self.state = state

    def latest_states(self):
        return {"m1": self.state}

    def latest_state(self, machine_id):
        return self.state if machine_id == "m1" else None


def _state(q, simulated=True):
    return MachineState(machine_id="m1", stamp_s=time.monotonic(), q=q, qd=[0.0] * 6,
                        gripper_open=False, payload_attached=True, simulated=simulated)


@pytest.fixture
def scene():
    s = ConsoleScene(_Fleet(_state([0.3, -0.5, 1.5, 0.4, 0.1, 0.0])), port=free_port(), rate_hz=50)
    s.start()
    yield s
    s.stop()


def test_scene_draws_the_machine_from_forward_kinematics(scene):
    q = np.array([0.3, -0.5, 1.5, 0.4, 0.1, 0.0])
    pts = forward_kinematics(np, q, np.zeros(6))
    wait_for(lambda: np.allclose(scene._gripper.position, pts.gripper_centre), 5, "gripper drawn")
    assert np.allclose(scene._links.points[-1][1], pts.hanger)
    assert "SIMULATED machine m1" == scene._label.text
    # the 2D plane leaves the turn axis along the cabin heading
    start, end = scene._plane.points[0]
    heading = (end - start)[:2] / np.linalg.norm((end - start)[:2])
    assert heading == pytest.approx([np.cos(0.3), np.sin(0.3)], abs=1e-6)
    scene.mode = "3d"
    scene.fleet.state = _state(list(q))  # new stamp -> redraw
    wait_for(lambda: scene._plane.visible is False, 5, "plane hidden in 3D mode")


def test_click_sets_target_and_throw_is_drawn(scene, tmp_path):
    class Click:
        ray_origin, ray_direction = (0.0, 0.0, 10.0), (0.6, 0.0, -0.8)

    scene._on_click(Click())
    assert scene.target == pytest.approx([7.5, 0.0, 0.0])
    rec = TelemetryRecorder()
    for i in range(20):
        rec.record(0.01 * i, [0.3, -0.5 + 0.02 * i, 1.5, 0.4, 0.0, 0.0], [0.0] * 6, [0.0] * 4, [0.0] * 4, i > 9, i > 10,
                   "swinging", payload_pos_m=[4 + 0.2 * i, 0.0, 4 - 0.2 * i], payload_vel_mps=[2.0, 0.0, -2.0])
    path = tmp_path / "t.mcap"
    path.write_bytes(write_mcap(rec))
    scene.show_throw(path, [7.0, 0.1, 0.0], scene.target)
    names = scene.server.scene._handle_from_node_name
    assert {"/throw/gripper_path", "/throw/payload_path", "/throw/impact"} <= set(names)
    assert len(names["/throw/payload_path"].points) == 19
    scene.show_throw(None, None, scene.target)  # a new throw replaces the old drawing
    assert "/throw/payload_path" not in scene.server.scene._handle_from_node_name


def test_scene_reports_the_port_viser_really_uses():
    """Viser moves on to the next free port when the asked one is busy; the scene must say so."""
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        s = ConsoleScene(_Fleet(_state([0.0, -0.5, 1.5, 0.4, 0.0, 0.0])), port=taken)
        s.start()
        try:
            assert s.port is not None and s.port != taken
        finally:
            s.stop()
