"""The console's 3D view: a viser scene of the selected machine, the target and past throws.

:class:`ConsoleScene` owns the :class:`viser.ViserServer`. Scene names are paths
(``/machine/boom``, ``/target``, ``/throw/payload``). A drawing thread redraws the selected
machine from its latest MachineState at ``rate_hz`` (default 20 Hz) inside ``server.atomic()``;
the arm is drawn from :func:`runtime.machine.forward_kinematics` (no kinematics here).

Clicks: viser reports a click as a RAY (origin, direction, world frame = machine frame, z up);
:func:`ground_point` intersects it with the ground plane z = 0 and the result becomes the target.
"""

from __future__ import annotations

import logging
import math
import threading
from pathlib import Path

import numpy as np
import viser

from runtime.machine import CHASSIS_HEIGHT_M, CABIN_OFFSET_M, forward_kinematics
from runtime.throw_geometry import ARM_PLANE_OFFSET_M
from server.fleet import Fleet

log = logging.getLogger(__name__)

YELLOW, GREY, DARK, RED, BLUE, GREEN = (242, 190, 26), (200, 200, 200), (60, 60, 70), (220, 40, 40), (40, 90, 220), (40, 170, 60)
PLANE_LENGTH_M = 12.0
TRAJECTORY_POINTS = 300


def ground_point(ray_origin, ray_direction, max_range_m: float = 200.0) -> np.ndarray | None:
    """Intersection of a click ray with the ground plane z = 0.

    Args:
        ray_origin: (3,) ray origin, machine frame, m.
        ray_direction: (3,) ray direction (any length).
        max_range_m: ignore hits farther than this from the turn axis (near-horizon clicks).

    Returns:
        (3,) point with z = 0, or None if the ray does not point down to the ground.
    """
    o = np.asarray(ray_origin, dtype=float)
    d = np.asarray(ray_direction, dtype=float)
    if d[2] >= -1e-9 or o[2] <= 0.0:
        return None
    p = o + (-o[2] / d[2]) * d
    if not np.all(np.isfinite(p)) or np.hypot(p[0], p[1]) > max_range_m:
        return None
    p[2] = 0.0
    return p


def _yaw_wxyz(yaw_rad: float) -> tuple[float, float, float, float]:
    return (math.cos(yaw_rad / 2), 0.0, 0.0, math.sin(yaw_rad / 2))


def _segments(points: np.ndarray) -> np.ndarray:
    """(N, 3) polyline -> (N-1, 2, 3) line segments."""
    return np.stack([points[:-1], points[1:]], axis=1)


class ConsoleScene:
    """The 3D view. :meth:`start` serves it; :meth:`stop` shuts it down.

    Args:
        fleet: source of machine states.
        host / port: where viser listens (it moves on to the next free port; read :attr:`port`).
        rate_hz: machine redraw rate.

    Attributes:
        machine_id: machine shown (None: the first one heard, by id).
        mode: "2d" or "3d"; the 2D throwing plane is highlighted in 2D mode.
        target: (3,) target picked by a click (or typed), machine frame, m; None before.
    """

    def __init__(self, fleet: Fleet, host: str = "127.0.0.1", port: int = 8080, rate_hz: float = 20.0):
        self.fleet = fleet
        self.host, self.requested_port, self.rate_hz = host, port, rate_hz
        self.server: viser.ViserServer | None = None
        self.port: int | None = None
        self.machine_id: str | None = None
        self.mode: str = "2d"
        self.target: list[float] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.preview_names: list[str] = []
        """Scene names of the preview drawn last (under /preview)."""

    # --- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        self.server = viser.ViserServer(host=self.host, port=self.requested_port, label="Slinger", verbose=False)
        self.port = self.server.get_port()
        s = self.server.scene
        s.set_up_direction("+z")
        cam = self.server.initial_camera
        cam.position, cam.look_at, cam.up = (-7.0, -13.0, 13.0), (6.0, 0.0, 0.0), (0.0, 0.0, 1.0)
        self.server.gui.configure_theme(control_width="small", show_share_button=False)
        self.server.gui.main_panel.minimize()  # keep the view clear; the operator can open it
        s.add_grid("/ground", width=40.0, height=40.0, cell_size=1.0, section_size=5.0,
                   plane_color=(150, 165, 130), plane_opacity=0.35)
        s.add_box("/machine/chassis", color=GREY, dimensions=(4.0, 2.4, 1.0), position=(0, 0, CHASSIS_HEIGHT_M - 0.6))
        self._cabin = s.add_box("/machine/cabin", color=YELLOW, dimensions=(2.6, 2.0, 1.6))
        self._links = s.add_line_segments("/machine/arm", np.zeros((3, 2, 3)), YELLOW, thickness=0.25)
        self._rope = s.add_line_segments("/machine/rope", np.zeros((1, 2, 3)), DARK, thickness=0.12)
        self._gripper = s.add_box("/machine/gripper", color=DARK, dimensions=(0.9, 0.9, 1.0))
        self._payload = s.add_icosphere("/machine/payload", radius=0.3, color=RED, visible=False)
        self._plane = s.add_line_segments("/plane2d", np.zeros((1, 2, 3)), BLUE, thickness=0.05)
        self._label = s.add_label("/machine/label", "no machine", position=(0, 0, 5.0))
        self._plane_label = s.add_label("/plane2d/label", "2D throwing plane", position=(PLANE_LENGTH_M, 0, 0.3))
        s.on_click()(self._on_click)
        self._thread = threading.Thread(target=self._run, name="scene-draw", daemon=True)
        self._thread.start()
        log.info("3D view on http://%s:%d", self.host, self.port)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self.server is not None:
            self.server.stop()
            self.server = None

    # --- target --------------------------------------------------------------------------------
    def _on_click(self, event) -> None:  # viser.SceneClickEvent
        p = ground_point(event.ray_origin, event.ray_direction)
        if p is None:
            log.debug("click ray misses the ground: %s %s", event.ray_origin, event.ray_direction)
            return
        self.set_target(p.tolist())

    def set_target(self, target_m) -> None:
        """Make ``target_m`` ((3,), m) the target and mark it in the view."""
        t = [float(v) for v in target_m]
        self.target = t
        if self.server is not None:
            s = self.server.scene
            with self.server.atomic():
                s.add_cylinder("/target", radius=0.35, height=0.05, color=GREEN, position=(t[0], t[1], 0.03))
                s.add_label("/target/label", f"target {math.hypot(t[0], t[1]):.1f} m", position=(0, 0, 0.6))

    # --- machine -------------------------------------------------------------------------------
    def _selected(self) -> str | None:
        if self.machine_id is not None:
            return self.machine_id
        ids = sorted(self.fleet.latest_states())
        return ids[0] if ids else None

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        last_stamp = None
        while not self._stop.wait(period):
            mid = self._selected()
            state = self.fleet.latest_state(mid) if mid else None
            if state is None or state.stamp_s == last_stamp:
                continue
            last_stamp = state.stamp_s
            try:
                self.draw_machine(mid, state)
            except Exception:
                log.exception("drawing machine %s failed", mid)

    def draw_machine(self, machine_id: str, state) -> None:  # runtime MachineState
        """Pose every machine shape from one MachineState (one atomic update)."""
        q, qd = np.asarray(state.q), np.asarray(state.qd)
        pts = forward_kinematics(np, q, qd)
        turn = np.array([0.0, 0.0, CHASSIS_HEIGHT_M + CABIN_OFFSET_M[2]])
        arm = np.array([[turn, pts.boom_pivot], [pts.boom_pivot, pts.dipper_pivot], [pts.dipper_pivot, pts.hanger]])
        down = pts.gripper_centre - pts.hanger
        # gripper box: z axis along hanger -> centre (up), yaw of the cabin
        wxyz = _align_z(-down, q[0])
        c, s = math.cos(q[0]), math.sin(q[0])
        cabin_c = turn + np.array([-0.4 * c - 0.2 * s, -0.4 * s + 0.2 * c, 0.8])
        y0 = ARM_PLANE_OFFSET_M
        plane = np.array([[[y0 * -s, y0 * c, 0.02], [PLANE_LENGTH_M * c - y0 * s, PLANE_LENGTH_M * s + y0 * c, 0.02]]])
        kind = "SIMULATED machine" if state.simulated else "machine"
        with self.server.atomic():
            self._cabin.position = tuple(cabin_c)
            self._cabin.wxyz = _yaw_wxyz(q[0])
            self._links.points = arm
            self._rope.points = np.array([[pts.hanger, pts.gripper_centre]])
            self._gripper.position = tuple(pts.gripper_centre)
            self._gripper.wxyz = wxyz
            self._plane.points = plane
            self._plane.visible = self.mode == "2d"
            self._plane_label.position = tuple(plane[0, 1])
            self._label.text = f"{kind} {machine_id}"
            if state.payload_pos_m is not None and state.payload_attached is False:
                self._payload.position = tuple(state.payload_pos_m)
                self._payload.visible = True
            else:
                self._payload.visible = False

    # --- previews ------------------------------------------------------------------------------
    def show_preview(self, summary: dict) -> None:
        """Draw a preview (server.scene_preview): paths, release and its velocity, impact, 1 sigma
        ellipse, and in 3D mode the swept clearance zone."""
        if self.server is None:
            return
        from server.scene_preview import draw_preview

        self.preview_names = draw_preview(self.server, summary, summary.get("mode", self.mode))

    # --- throws --------------------------------------------------------------------------------
    def show_throw(self, telemetry_path: Path | None, impact_m, target_m) -> None:
        """Draw a finished throw: gripper path (FK of the recorded joints), payload path and
        impact. Missing telemetry just draws the impact."""
        if self.server is None:
            return
        s = self.server.scene
        gripper = payload = None
        if telemetry_path is not None and Path(telemetry_path).is_file():
            from runtime.telemetry import read_telemetry

            tel = read_telemetry(telemetry_path)
            idx = np.linspace(0, len(tel["q"]) - 1, min(len(tel["q"]), TRAJECTORY_POINTS)).astype(int)
            if len(idx) >= 2:
                gripper = np.array([forward_kinematics(np, tel["q"][i], tel["qd"][i]).gripper_centre for i in idx])
            if len(tel["payload_pos_m"]) >= 2:
                payload = np.asarray(tel["payload_pos_m"])
        with self.server.atomic():
            s.remove_by_name("/throw")
            s.add_frame("/throw", show_axes=False)
            if gripper is not None:
                s.add_line_segments("/throw/gripper_path", _segments(gripper), DARK, thickness=0.06)
            if payload is not None:
                s.add_line_segments("/throw/payload_path", _segments(payload), RED, thickness=0.06)
            if impact_m is not None:
                s.add_icosphere("/throw/impact", radius=0.3, color=RED, position=tuple(impact_m))
                err = math.hypot(impact_m[0] - target_m[0], impact_m[1] - target_m[1])
                s.add_label("/throw/impact/label", f"impact, {err:.2f} m from target", position=(0, 0, 0.8))


def _align_z(axis, yaw_rad: float) -> tuple[float, float, float, float]:
    """Quaternion (wxyz) of a frame whose z axis is ``axis`` and whose x axis follows the yaw."""
    z = np.asarray(axis, dtype=float)
    n = np.linalg.norm(z)
    if n < 1e-9:
        return _yaw_wxyz(yaw_rad)
    z = z / n
    x = np.array([math.cos(yaw_rad), math.sin(yaw_rad), 0.0])
    x = x - (x @ z) * z
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 0.0, 1.0]) - z[2] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return tuple(float(v) for v in viser.transforms.SO3.from_matrix(np.stack([x, y, z], axis=1)).wxyz)
