"""The 3D view without a browser: click ray -> ground target, targeting geometry, one private view
per console (viser clients bound by their websocket path), the machine posed from the twin's MJCF.

Viser clients are real websocket connections (the ``websockets`` client with viser's subprotocol),
so the binding of a view to its console goes through the same path a browser takes."""

from __future__ import annotations

import math
import time

import mujoco
import numpy as np
import pytest
import viser
from websockets.sync.client import connect

from runtime.protocol.messages import MachineState
from runtime.telemetry import TelemetryRecorder, write_mcap
from runtime.throw_geometry import ARM_PLANE_OFFSET_M
from server.console.scene import ConsoleScene, ground_point
from server.console.scene_view import camera_framing, snap_to_line, strip_mesh
from sim_twin.twin.model import load_model
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


def test_targeting_geometry_follows_the_cabin():
    yaw = 0.4
    c, s = math.cos(yaw), math.sin(yaw)
    p = snap_to_line(np.array([8.0 * c + 1.0 * -s, 8.0 * s + 1.0 * c]), yaw)  # 1 m left of the heading
    assert p[0] * c + p[1] * s == pytest.approx(8.0)  # same distance along the heading
    assert -p[0] * s + p[1] * c == pytest.approx(ARM_PLANE_OFFSET_M)  # on the throwing line
    assert snap_to_line(np.array([-5.0 * c, -5.0 * s]), yaw) is None  # behind the machine
    verts, faces = strip_mesh(yaw, 5.0, 10.0)
    radii = np.hypot(verts[:, 0], verts[:, 1])
    assert radii.min() == pytest.approx(5.0, abs=0.02) and radii.max() == pytest.approx(10.0, abs=0.02)
    assert faces.shape == (2, 3)
    pos, look = camera_framing(yaw, 5.0, 10.0)
    assert np.hypot(*look[:2]) == pytest.approx(7.5)  # looks at the middle of the band
    assert pos[2] > 5.0 and (pos[:2] - look[:2]) @ np.array([c, s]) < 0  # above and behind


class _Fleet:
    def __init__(self):
        self.states = {}

    def latest_states(self):
        return dict(self.states)

    def latest_state(self, machine_id):
        return self.states.get(machine_id)

    def is_online(self, machine_id):
        return machine_id in self.states


def _state(machine_id, q):
    return MachineState(machine_id=machine_id, stamp_s=time.monotonic(), q=q, qd=[0.0] * 6,
                        gripper_open=False, payload_attached=True, simulated=True)


Q1 = [0.3, -0.5, 1.5, 0.4, 0.1, 0.0]


@pytest.fixture
def scene():
    fleet = _Fleet()
    fleet.states = {"m1": _state("m1", Q1), "m2": _state("m2", [-1.0, -0.5, 1.5, 0.4, 0.0, 0.0])}
    changes = []

    def refusal(mid, mode, t):
        d = math.hypot(t[0], t[1])
        return None if 5.0 <= d <= 10.7 else f"out of range ({d:.1f} m)"

    s = ConsoleScene(fleet, port=free_port(), rate_hz=50, refusal=refusal, on_console_change=changes.append)
    s.changes = changes
    s.start()
    yield s
    s.stop()


def _view(scene, console_id, cookie: str | None = None, bound: bool = True):
    """Open a viser client of ``console_id``: a websocket with viser's subprotocol (and the
    ``Cookie`` header ``cookie``) that reports its camera (viser counts a client as connected
    from its first camera message). Returns (websocket, the view bound to the console), or with
    ``bound`` False (websocket, the new client's id), whatever the scene bound it to."""
    import msgspec

    from viser._messages import ViewerCameraMessage

    before = set(scene._views)
    ws = connect(f"ws://127.0.0.1:{scene.port}/c/{console_id}", subprotocols=[f"viser-v{viser.__version__}"],
                 max_size=None, max_queue=None, additional_headers={"Cookie": cookie} if cookie else None)
    cam = ViewerCameraMessage(wxyz=(1.0, 0.0, 0.0, 0.0), position=(-5.0, 0.0, 8.0), fov=1.0, near=0.01, far=100.0,
                              image_height=600, image_width=800, look_at=(6.0, 0.0, 0.0), up_direction=(0.0, 0.0, 1.0))
    ws.send(msgspec.msgpack.encode(cam.as_serializable_dict()))

    if not bound:
        (client_id,) = wait_for(lambda: tuple(set(scene._views) - before) or None, 10, "a view connected")  # ids start at 0
        return ws, client_id

    def bound_view():
        return next((v for cid, v in scene._views.values() if cid == console_id), None)

    return ws, wait_for(bound_view, 10, f"a view bound to {console_id}")


def _names(view):
    return set(view.client.scene._handle_from_node_name)


def test_each_console_has_its_own_view_target_and_machine(scene, tmp_path):
    a, b = scene.open_console("ann"), scene.open_console("bob")
    scene.update_console(a, machine_id="m1", mode="2d")
    scene.update_console(b, machine_id="m2", mode="3d")
    ws_a, va = _view(scene, a.console_id)
    ws_b, vb = _view(scene, b.console_id)
    try:
        # the machine of each view is posed from the twin's MJCF (mujoco forward kinematics)
        model = load_model()
        data = mujoco.MjData(model)
        data.qpos[:] = Q1
        mujoco.mj_kinematics(model, data)
        gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "gripper")
        wait_for(lambda: np.allclose(va.client.scene._handle_from_node_name["/machine/gripper"].position,
                                     data.geom_xpos[gid], atol=1e-5), 10, "gripper of m1 posed")
        assert {"/machine/cabin", "/machine/boom", "/machine/dipper", "/machine/telescope", "/machine/rotator"} <= _names(va)
        # each view is drawn by the scene's own refresh: m2's view may be drawn a beat after m1's
        wait_for(lambda: va.label.text == "SIMULATED machine m1" and vb.label.text == "SIMULATED machine m2",
                 10, "each view labelled with its own machine")
        wait_for(lambda: "/band/area" in _names(va) and "/band/area" in _names(vb), 10, "valid bands drawn")
        assert "/band/line" in _names(va) and "/band/line" not in _names(vb)  # the 2D line only in 2D
        assert "/rings" in _names(va)

        # a click in ann's view sets ann's target (snapped onto m1's 2D line), not bob's
        class Click:
            ray_origin, ray_direction = (0.0, 0.0, 10.0), (0.6, 0.0, -0.8)

        scene._on_click(va.client.client_id, Click())
        assert a.target is not None and b.target is None
        assert -a.target[0] * math.sin(0.3) + a.target[1] * math.cos(0.3) == pytest.approx(ARM_PLANE_OFFSET_M, abs=1e-3)
        assert a.snapped and a.target_reason is None
        assert scene.changes[-1]["console_id"] == a.console_id
        assert "/target" in _names(va) and "/target" not in _names(vb)
        # bob types an unreachable target: kept where typed (3D), marked with the reason
        scene.update_console(b, target=[20.0, 1.0, 0.0])
        assert b.target == [20.0, 1.0, 0.0] and b.target_reason == "out of range (20.0 m)" and not b.snapped
        assert "cannot throw here" in vb.client.scene._handle_from_node_name["/labels/target"].text

        # a finished throw is drawn in the views of its machine only
        rec = TelemetryRecorder()
        for i in range(20):
            rec.record(0.01 * i, Q1, [0.0] * 6, [0.0] * 4, [0.0] * 4, i > 9, i > 10, "swinging",
                       payload_pos_m=[4 + 0.2 * i, 0.0, 4 - 0.2 * i], payload_vel_mps=[2.0, 0.0, -2.0])
        mcap = tmp_path / "t.mcap"
        mcap.write_bytes(write_mcap(rec))
        scene.show_throw("m1", mcap, [7.0, 0.1, 0.0], a.target)
        assert {"/throw/payload_path", "/throw/impact"} <= _names(va) and "/throw/impact" not in _names(vb)

        # switching machine drops the old machine's target, preview and throw from the view
        scene.update_console(a, machine_id="m2")
        assert a.target is None
        assert not {"/throw/impact", "/target"} & _names(va)
    finally:
        ws_a.close()
        ws_b.close()
    wait_for(lambda: not scene._views, 10, "views dropped on disconnect")


def test_a_replay_poses_the_console_machine_from_the_recording_at_the_seeked_time(scene, tmp_path):
    from server.console.scene_replay import Replay
    from tests.fixtures import write_swing_telemetry

    t, q = write_swing_telemetry(tmp_path / "swing.mcap")
    a, b = scene.open_console("ann"), scene.open_console("ann")
    scene.update_console(a, machine_id="m1")
    scene.update_console(b, machine_id="m1")
    ws_a, va = _view(scene, a.console_id)
    ws_b, vb = _view(scene, b.console_id)
    try:
        replay = Replay.load("th-1", "m1", tmp_path / "swing.mcap", impact_m=[8.0, 0.5, 0.0], target_m=[8.2, 0.4, 0.0])
        assert replay.duration_s == pytest.approx(2.0)
        scene.start_replay(a, replay)
        assert {"/throw/gripper_path", "/throw/payload_path", "/throw/impact"} <= _names(va)
        assert "/throw/impact" not in _names(vb)  # the other console shows the live machine
        for want in (0.0, 1.234, 1.7, 5.0):
            shown = scene.seek_replay(a, want)
            assert shown == pytest.approx(min(want, 2.0))
            expect = [np.interp(shown, t, q[:, j]) for j in range(6)]
            assert va.last_q == pytest.approx(expect, abs=1e-9)  # drawn before seek_replay returned
            assert va.label.text == f"REPLAY of throw th-1 on m1: t = {shown:.2f} s"
            assert va.payload.visible == (shown >= 1.5)  # the payload flies after the release
        assert a.public()["replay"] == {"throw_id": "th-1", "t_s": 2.0, "duration_s": 2.0}
        wait_for(lambda: vb.last_q is not None and np.allclose(vb.last_q, Q1), 10, "the other console posed live")
        time.sleep(0.2)  # the drawing thread keeps the replayed pose, not the live one
        assert va.last_q == pytest.approx(q[-1]) and vb.last_q == pytest.approx(Q1)
        scene.stop_replay(a)
        wait_for(lambda: np.allclose(va.last_q, Q1), 10, "back to the live machine")
        assert "/throw/impact" not in _names(va) and a.public()["replay"] is None
        with pytest.raises(ValueError, match="replays no throw"):
            scene.seek_replay(a, 1.0)
        (tmp_path / "bad.mcap").write_bytes(b"not mcap")
        with pytest.raises(ValueError, match="cannot be read"):
            Replay.load("th-2", "m1", tmp_path / "bad.mcap")
    finally:
        ws_a.close()
        ws_b.close()


def test_a_drawing_pass_in_flight_does_not_draw_a_stale_pose_over_a_sought_replay(scene, tmp_path):
    """The drawing thread computes the replay's pose while the operator seeks: the pose it computed
    must not land over the sought one after seek_replay has drawn it (it did while the pose was taken
    outside the scene's lock: a CI run saw another time's pose right after seek_replay returned)."""
    import threading

    from server.console.scene_replay import Replay
    from tests.fixtures import write_swing_telemetry

    t, q = write_swing_telemetry(tmp_path / "swing.mcap")
    a = scene.open_console("ann")
    scene.update_console(a, machine_id="m1")
    ws_a, va = _view(scene, a.console_id)
    replay = Replay.load("th-1", "m1", tmp_path / "swing.mcap")
    entered, go = threading.Event(), threading.Event()
    plain_pose, plain_draw = replay.pose, va.draw_machine
    drawn: list[tuple[str, np.ndarray]] = []

    def held_pose(t_s=None):  # the drawing thread is held once it has computed its pose
        pose = plain_pose(t_s)
        if threading.current_thread() is scene._thread and not go.is_set():
            entered.set()
            go.wait(10)
        return pose

    def logged_draw(label, q_, payload=None):
        drawn.append((threading.current_thread().name, np.array(q_, dtype=float)))
        plain_draw(label, q_, payload)

    try:
        scene.start_replay(a, replay)  # shows t = 0
        va.draw_machine = logged_draw
        replay.pose = held_pose
        assert entered.wait(10), "the drawing thread computed a pose"
        sought = []
        seeker = threading.Thread(target=lambda: sought.append(scene.seek_replay(a, 1.234)), name="seeker")
        seeker.start()
        time.sleep(0.3)  # sought and drawn by now, or waiting for the drawing pass
        go.set()
        seeker.join(10)
        time.sleep(0.2)  # later drawing passes
        assert sought == [pytest.approx(1.234)]
        want = np.array([np.interp(1.234, t, q[:, j]) for j in range(6)])
        names = [name for name, _ in drawn]
        assert "seeker" in names, names
        after_seek = drawn[names.index("seeker"):]
        assert all(np.allclose(p, want, atol=1e-9) for _, p in after_seek), [(n, p[0]) for n, p in after_seek]
    finally:
        go.set()
        ws_a.close()


def test_a_view_binds_to_its_console_only_with_the_owners_session(scene):
    """With ``authorise`` (the app's: the session cookie of the view's websocket), the console id
    alone does not bind a view: without a session, or with another user's, clicks do nothing."""
    scene.authorise = {"tok-ann": "ann", "tok-bob": "bob"}.get
    a = scene.open_console("ann")
    scene.update_console(a, machine_id="m1", mode="2d")

    class Click:
        ray_origin, ray_direction = (0.0, 0.0, 10.0), (0.6, 0.0, -0.8)

    opened = []
    try:
        for cookie in (None, "slinger_session=tok-bob", "slinger_session=forged", "x=1; slinger_session"):
            ws, client_id = _view(scene, a.console_id, cookie, bound=False)
            opened.append(ws)
            assert scene._views[client_id][0] is None, cookie  # bound to no console
            scene._on_click(client_id, Click())
            assert scene.get_console(a.console_id).target is None, cookie
        ws, client_id = _view(scene, a.console_id, "theme=dark; slinger_session=tok-ann", bound=False)
        opened.append(ws)
        assert scene._views[client_id][0] == a.console_id
        scene._on_click(client_id, Click())
        assert scene.get_console(a.console_id).target is not None
    finally:
        for ws in opened:
            ws.close()


def test_scene_reports_the_port_viser_really_uses():
    """Viser moves on to the next free port when the asked one is busy; the scene must say so."""
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        s = ConsoleScene(_Fleet(), port=taken)
        s.start()
        try:
            assert s.port is not None and s.port != taken
        finally:
            s.stop()


def test_console_api_keeps_each_console_to_its_user(settings):
    """POST /api/consoles opens a console of the caller; another user gets 403 on it, a viewer
    may look but not set a target; unknown consoles are 404; GET /api/scene says the port."""
    from fastapi.testclient import TestClient

    from server.app import create_app
    from tests.conftest import ADMIN, add_user, login

    settings.viser_enabled, settings.viser_port = True, free_port()
    with TestClient(create_app(settings)) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        add_user(c.app.state.sessions, "vera", "viewer-pass-12", "viewer")
        login(c, *ADMIN)
        con = c.post("/api/consoles").json()
        bound, _, token = con["viser_path"].rpartition("/")  # /c/<console_id>/<view_token>: the view's secret
        assert bound == f"/c/{con['console_id']}" and len(token) >= 16
        assert con["viser_port"] == c.get("/api/scene").json()["viser_port"]
        r = c.put(f"/api/consoles/{con['console_id']}", json={"machine_id": "m1", "mode": "3d", "target": [8.0, 1.0, 0.0]})
        assert r.status_code == 200 and r.json()["target"] == [8.0, 1.0, 0.0]
        assert r.json()["target_reason"] == "no state from machine m1"  # judged at once, before any Preview
        assert c.put(f"/api/consoles/{con['console_id']}", json={"mode": "4d"}).status_code == 422
        assert c.get("/api/consoles/nope").status_code == 404
        c.cookies.clear()
        login(c, "vera", "viewer-pass-12")
        assert c.get(f"/api/consoles/{con['console_id']}").status_code == 403
        mine = c.post("/api/consoles").json()["console_id"]
        assert c.put(f"/api/consoles/{mine}", json={"mode": "3d"}).status_code == 200
        r = c.put(f"/api/consoles/{mine}", json={"target": [8.0, 0.0, 0.0]})
        assert r.status_code == 403 and "operator" in r.json()["detail"]


def test_a_site_view_host_name_reaches_the_console_and_its_frame_policy(settings):
    """Settings.viser_public_host: every console's answer names it (the page loads the 3D view
    from there, web/js/common.js embedViser) and the pages' CSP lets them frame it; unset, the
    answer leaves the choice to the page; a malformed name is refused at start."""
    from fastapi.testclient import TestClient
    from pydantic import ValidationError

    from server.app import create_app
    from server.config import Settings
    from tests.conftest import ADMIN, add_user, login

    with pytest.raises(ValidationError):
        Settings(viser_public_host="view.site.example/evil")
    settings.viser_enabled, settings.viser_port = True, free_port()
    settings.viser_public_host = "view.site.example"
    with TestClient(create_app(settings)) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        login(c, *ADMIN)
        assert c.post("/api/consoles").json()["viser_host"] == "view.site.example"
        assert "http://view.site.example:*" in c.get("/console/index.html").headers["content-security-policy"]
    settings.viser_public_host, settings.viser_port = None, free_port()
    with TestClient(create_app(settings)) as c:  # the same database: the admin exists
        login(c, *ADMIN)
        assert c.post("/api/consoles").json()["viser_host"] is None


def test_replay_route_loads_seeks_and_refuses_with_reasons(settings):
    """PUT /api/consoles/{id}/replay (viewers too: the page's own view): 404 for an unknown throw,
    409 for one without telemetry or with an unreadable one, 422 for a bad time; the answer says
    the time shown (clamped to the recording); DELETE goes back to the live machine."""
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.db.models import Machine, Throw
    from tests.conftest import add_user, login
    from tests.fixtures import write_swing_telemetry

    settings.viser_enabled, settings.viser_port = True, free_port()
    with TestClient(create_app(settings)) as c:
        data_dir = c.app.state.settings.data_dir
        write_swing_telemetry(data_dir / "telemetry" / "th-1.mcap")
        (data_dir / "telemetry" / "th-bad.mcap").write_bytes(b"not an mcap file")
        with c.app.state.sessions.begin() as db:
            db.add(Machine(id="m1", simulated=True))
            for tid, path in (("th-1", "telemetry/th-1.mcap"), ("th-none", None), ("th-bad", "telemetry/th-bad.mcap")):
                db.add(Throw(id=tid, machine_id="m1", mode="2d", target_x_m=8.0, target_y_m=0.0, target_z_m=0.0,
                             status="landed", telemetry_path=path))
        add_user(c.app.state.sessions, "vera", "viewer-pass-12", "viewer")
        login(c, "vera", "viewer-pass-12")
        cid = c.post("/api/consoles").json()["console_id"]
        url = f"/api/consoles/{cid}/replay"
        r = c.put(url, json={"throw_id": "nope", "t_s": 0.0})
        assert r.status_code == 404 and "no throw nope" in r.json()["detail"]
        r = c.put(url, json={"throw_id": "th-none", "t_s": 0.0})
        assert r.status_code == 409 and "no telemetry" in r.json()["detail"]
        r = c.put(url, json={"throw_id": "th-bad", "t_s": 0.0})
        assert r.status_code == 409 and "cannot be read" in r.json()["detail"]
        assert c.put(url, json={"throw_id": "th-1", "t_s": -1.0}).status_code == 422
        r = c.put(url, json={"throw_id": "th-1", "t_s": 0.75})
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["machine_id"] == "m1" and body["replay"] == {"throw_id": "th-1", "t_s": 0.75, "duration_s": 2.0}
        assert c.put(url, json={"throw_id": "th-1", "t_s": 60.0}).json()["replay"]["t_s"] == 2.0  # clamped
        r = c.delete(url)
        assert r.status_code == 200 and r.json()["replay"] is None


def test_console_routes_answer_409_while_the_3d_view_is_disabled(settings):
    """Without the 3D view every console route refuses with 409 (not a server error)."""
    from fastapi.testclient import TestClient

    from server.app import create_app
    from tests.conftest import ADMIN, add_user, login

    settings.viser_enabled = False
    with TestClient(create_app(settings)) as c:
        add_user(c.app.state.sessions, *ADMIN, "admin")
        login(c, *ADMIN)
        assert c.post("/api/consoles").status_code == 409
        r = c.put("/api/consoles/any", json={"mode": "3d"})
        assert r.status_code == 409 and "disabled" in r.json()["detail"]
        assert c.post("/api/consoles/any/preview", json={"preview_id": "p"}).status_code == 409


def test_a_console_flood_never_evicts_another_users_console():
    """520 console openings by one viewer (issue 24 finding 6: they pushed the operator's console
    out of a global 500-entry LRU) leave the operator's console open; the viewer keeps its limit."""
    from server.console.scene import MAX_CONSOLES_PER_USER, ConsoleLimit

    s = ConsoleScene(_Fleet())  # not started: consoles are plain state
    mine = s.open_console("otto")
    for _ in range(520):
        s.open_console("vera")
    assert s.get_console(mine.console_id) is mine
    assert sum(c.username == "vera" for c in s.consoles.values()) == MAX_CONSOLES_PER_USER

    s = ConsoleScene(_Fleet())
    s.max_consoles, s.max_per_user = 4, 100
    mine = s.open_console("otto")
    for name in ("vera", "ann", "bob"):
        s.open_console(name)
    with pytest.raises(ConsoleLimit, match="consoles open"):
        s.open_console("newcomer")  # refused, not made by closing someone else's
    again = s.open_console("otto")  # at the limit, a user replaces their own oldest
    assert s.get_console(mine.console_id) is None and s.get_console(again.console_id) is again
    assert {c.username for c in s.consoles.values()} == {"otto", "vera", "ann", "bob"}
