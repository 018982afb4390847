"""One operator's 3D view (a viser client): the machine drawn from the twin's MJCF geometry and
the targeting overlay (range rings every metre, the mode's valid band, the 2D throwing line,
keep-out zones, the target with its reason when it cannot be served).

Everything here is client-scoped (``client.scene``): what one operator picks or sees is never
drawn for another. Frames: machine frame, z up, metres. Shapes are re-created per client on
connect (viser client state is ephemeral, see viser.ClientHandle).

The labels of the markers (target, impact, preview) are placed by server.console.scene_labels for the
camera the operator has (before the browser reports it: the framing camera), clear of each other,
of the markers, of the fixed labels and of the hanging gripper, each joined to its marker by a
leader line; they move when the camera, the gripper or the labels change (:meth:`ClientView.relabel`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from runtime.throw_geometry import ARM_PLANE_OFFSET_M, PLANE_TOLERANCE_M
from server.console.mjcf_chain import KinematicChain, mat_to_quat
from server.console.scene_labels import Box, PinholeCamera, fixed_label_box, gripper_footprint, place_labels

if TYPE_CHECKING:  # viser is imported by the scene process only (server.console.scene)
    import viser

RING_MAX_M = 14
"""Range rings at 1, 2, ... RING_MAX_M metres from the turn axis."""
BAND_GREEN, BAD_RED, KEEP_OUT_RED, TARGET_GREEN, RING_GREY = (30, 150, 70), (200, 30, 30), (220, 60, 60), (20, 120, 50), (90, 90, 90)
PAYLOAD_RED = (200, 40, 40)
REDRAW_TOL = 2e-3
"""Joint change (rad, m) below which the machine is not redrawn."""
LEADER_GREY = (40, 40, 40)
MACHINE_LABEL_M, MACHINE_LABEL_ANCHOR = (0.0, 0.0, 6.5), "bottom-center"
RING_LABELS_M = (5, 10)
"""Range rings with a distance label."""
RELABEL_PX = 4.0
"""Screen change (px) of the gripper's footprint below which labels stay where they are."""


class MachineGeometry:
    """Poses of the twin's geoms for a joint vector: the MJCF's kinematic chain evaluated with
    numpy (server.console.mjcf_chain; the API process never imports MuJoCo).

    Args:
        chain: the machine's chain (default: parsed from the twin's MJCF); the ground plane is
            not drawn.
    """

    def __init__(self, chain: KinematicChain | None = None):
        self.chain = chain or KinematicChain.from_mjcf()
        self.geoms = [g for g in self.chain.geoms if g.kind != "plane"]

    def shapes(self) -> list[tuple[str, str, np.ndarray, tuple[int, int, int]]]:
        """(name, kind "box" | "capsule" | "cylinder" | "sphere", size (3,), rgb 0-255) of every drawn geom."""
        return [(g.name or f"geom{i}", g.kind, g.size.copy(), g.rgb) for i, g in enumerate(self.geoms)]

    def poses(self, q) -> list[tuple[np.ndarray, tuple]]:
        """World (position (3,), wxyz) of every drawn geom at joint positions ``q`` (6,)."""
        return [(p, mat_to_quat(r)) for p, r in self.chain.geom_poses(np.asarray(q, dtype=float)[:6])]


def ring_segments(radii_m, n: int = 96) -> np.ndarray:
    """(len(radii) * n, 2, 3) line segments of ground circles around the turn axis, z = 0.02."""
    ang = np.linspace(0.0, 2 * math.pi, n + 1)
    out = []
    for r in radii_m:
        pts = np.stack([r * np.cos(ang), r * np.sin(ang), np.full(n + 1, 0.02)], axis=1)
        out.append(np.stack([pts[:-1], pts[1:]], axis=1))
    return np.concatenate(out).astype(np.float32)


def annulus_mesh(lo_m: float, hi_m: float, n: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (2n, 3) and faces of the ground ring lo_m..hi_m (the 3D mode's valid band)."""
    ang = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    inner = np.stack([lo_m * np.cos(ang), lo_m * np.sin(ang), np.full(n, 0.015)], axis=1)
    outer = np.stack([hi_m * np.cos(ang), hi_m * np.sin(ang), np.full(n, 0.015)], axis=1)
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, n + i, n + j], [i, n + j, j]]
    return np.concatenate([inner, outer]).astype(np.float32), np.array(faces, dtype=np.uint32)


def strip_mesh(cabin_turn_rad: float, lo_m: float, hi_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (4, 3) and faces of the 2D mode's valid band: the throwing line from lo_m to
    hi_m (distance from the turn axis), PLANE_TOLERANCE_M either side."""
    c, s = math.cos(cabin_turn_rad), math.sin(cabin_turn_rad)
    u, n = np.array([c, s]), np.array([-s, c])
    y0 = ARM_PLANE_OFFSET_M
    pts = []
    for r, lat in ((lo_m, -1), (lo_m, 1), (hi_m, 1), (hi_m, -1)):
        x = math.sqrt(max(r * r - y0 * y0, 0.0))
        p = x * u + (y0 + lat * PLANE_TOLERANCE_M) * n
        pts.append([p[0], p[1], 0.02])
    return np.array(pts, dtype=np.float32), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)


def line_point(cabin_turn_rad: float, along_m: float) -> np.ndarray:
    """(2,) point of the 2D throwing line ``along_m`` metres out along the cabin's heading."""
    c, s = math.cos(cabin_turn_rad), math.sin(cabin_turn_rad)
    return np.array([along_m * c - ARM_PLANE_OFFSET_M * s, along_m * s + ARM_PLANE_OFFSET_M * c])


def snap_to_line(xy, cabin_turn_rad: float) -> np.ndarray | None:
    """Project a ground point onto the 2D throwing line (None when it lies behind the machine)."""
    c, s = math.cos(cabin_turn_rad), math.sin(cabin_turn_rad)
    along = xy[0] * c + xy[1] * s
    if along <= 0.0:
        return None
    return line_point(cabin_turn_rad, along)


def camera_framing(cabin_turn_rad: float, lo_m: float, hi_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera (position, look_at) that frames the throwing area: from above, behind and to the
    left of the machine, looking at the middle of the valid band along the cabin's heading.

    Steep (about 50 degrees down) and to the side, so that the gripper hanging over the band
    (between the camera and the ground) is seen beside the throwing line, not on the targets it
    aims at; behind, so that downrange points up the screen."""
    u = np.array([math.cos(cabin_turn_rad), math.sin(cabin_turn_rad), 0.0])
    left = np.array([-u[1], u[0], 0.0])
    look = 0.5 * (lo_m + hi_m) * u
    pos = look - 0.85 * hi_m * u + 0.55 * hi_m * left + np.array([0.0, 0.0, 1.25 * hi_m])
    return pos, look


class ClientView:
    """The client-scoped shapes of one viser client. Call :meth:`build` once after connecting.

    Args:
        client: viser ClientHandle.
        geometry: the twin's geometry (shared, used under the scene's lock).
    """

    def __init__(self, client, geometry: MachineGeometry):
        self.client, self.geometry = client, geometry
        self.handles: list = []
        self.payload: viser.IcosphereHandle | None = None
        self.label: viser.LabelHandle | None = None
        self.last_q: np.ndarray | None = None
        self.framed_for: tuple | None = None
        """(machine, mode, ...) the camera was last framed for."""
        self.drawn_for: tuple | None = None
        """(machine, mode, band, cabin angle) the band was last drawn for."""
        self.labels: dict[str, tuple[tuple[float, float, float], str]] = {}
        """Marker labels: scene name of the marker -> (anchor (3,) m, text); placed by :meth:`relabel`."""
        self.placements: dict = {}
        """Marker scene name -> server.console.scene_labels.Placement last drawn."""
        self._label_key: tuple | None = None

    def build(self, zones) -> None:
        """Machine shapes, range rings with labels at 5 m and 10 m, keep-out zones."""
        s = self.client.scene
        with self.client.atomic():
            for name, kind, size, rgb in self.geometry.shapes():
                path = f"/machine/{name}"
                if kind == "box":
                    h = s.add_box(path, color=rgb, dimensions=tuple(2 * size))
                elif kind in ("capsule", "cylinder"):
                    h = s.add_cylinder(path, radius=float(size[0]), height=float(2 * size[1]), color=rgb)
                else:
                    h = s.add_icosphere(path, radius=float(size[0]), color=rgb)
                self.handles.append(h)
            self.payload = s.add_icosphere("/machine/payload", radius=0.3, color=PAYLOAD_RED, visible=False)
            self.label = s.add_label("/machine/label", "no machine", position=MACHINE_LABEL_M, anchor=MACHINE_LABEL_ANCHOR)
            s.add_line_segments("/rings", ring_segments(range(1, RING_MAX_M + 1)), RING_GREY, thickness=0.03)
            for r in RING_LABELS_M:
                s.add_label(f"/rings/label_{r}", f"{r} m", position=(0.0, -r - 0.1, 0.05), anchor="top-center")
            for i, z in enumerate(zones):
                cx, cy = z.center_m
                s.add_cylinder(f"/keep_out/{i}", radius=z.radius_m, height=0.04, color=KEEP_OUT_RED,
                               opacity=0.45, position=(cx, cy, 0.02))
                s.add_label(f"/keep_out/{i}/label", f"keep out: {z.name}", position=(0.0, 0.0, 0.3),
                            anchor="bottom-center")

    def draw_machine(self, label: str, q, payload_pos=None) -> None:
        """Pose the machine from joint positions ``q`` (6,); the payload where it flies. A pose
        within REDRAW_TOL of the last one drawn is skipped: viser renders on demand, so a still
        machine costs the browser nothing."""
        if self.payload is None or self.label is None:
            raise RuntimeError("ClientView.draw_machine before ClientView.build")
        q = np.asarray(q, dtype=float)
        same = (self.last_q is not None and np.max(np.abs(q - self.last_q)) < REDRAW_TOL
                and label == self.label.text and payload_pos is None and not self.payload.visible)
        if same:
            return
        self.last_q = q
        poses = self.geometry.poses(q)
        with self.client.atomic():
            for h, (p, wxyz) in zip(self.handles, poses):
                h.position, h.wxyz = tuple(p), wxyz
            self.label.text = label
            if payload_pos is not None:
                self.payload.position, self.payload.visible = tuple(payload_pos), True
            else:
                self.payload.visible = False

    def draw_band(self, mode: str, cabin_turn_rad: float, band_m: tuple[float, float]) -> None:
        """The valid band of ``mode`` (ring in 3D, strip along the throwing line in 2D) and the line."""
        s = self.client.scene
        lo, hi = band_m
        with self.client.atomic():
            s.remove_by_name("/band")
            if mode == "3d":
                verts, faces = annulus_mesh(lo, hi)
            else:
                verts, faces = strip_mesh(cabin_turn_rad, lo, hi)
                a, b = line_point(cabin_turn_rad, 0.5), line_point(cabin_turn_rad, RING_MAX_M)
                s.add_line_segments("/band/line", np.array([[[*a, 0.03], [*b, 0.03]]]), (40, 90, 220), thickness=0.05)
            s.add_mesh_simple("/band/area", verts, faces, color=BAND_GREEN, opacity=0.5, side="double")

    def frame_camera(self, cabin_turn_rad: float, band_m: tuple[float, float], key: tuple) -> None:
        """Point the camera at the throwing area once per ``key`` (machine, mode): the operator
        may orbit freely afterwards."""
        if self.framed_for == key:
            return
        cam = self.client.camera
        try:
            cam.position  # noqa: B018 (viser asserts until the browser reported its camera)
        except AssertionError:
            return  # not ready yet: the next frame tries again
        self.framed_for = key
        pos, look = camera_framing(cabin_turn_rad, *band_m)
        cam.up_direction = (0.0, 0.0, 1.0)
        cam.position = tuple(pos)
        cam.look_at = tuple(look)

    def draw_target(self, target_m, reason: str | None) -> None:
        """The target: green with its distance when it can be served, red with the reason when not."""
        s = self.client.scene
        with self.client.atomic():
            s.remove_by_name("/target")
            if target_m is None:
                self.set_labels("/target", [])
                return
            x, y = target_m[0], target_m[1]
            ok = reason is None
            s.add_cylinder("/target", radius=0.35, height=0.06, color=TARGET_GREEN if ok else BAD_RED,
                           position=(x, y, 0.04))
            text = f"target {math.hypot(x, y):.1f} m" if ok else f"cannot throw here: {reason}"
            self.set_labels("/target", [("/target", (x, y, 0.06), text)])

    def clear(self, *names: str) -> None:
        """Remove the shapes ``names`` (scene names) and their markers' labels."""
        with self.client.atomic():
            for n in names:
                self.client.scene.remove_by_name(n)
            for n in names:
                self.set_labels(n, [], relabel=False)
        self.relabel()

    # --- labels ----------------------------------------------------------------------------------
    def set_labels(self, prefix: str, labels, relabel: bool = True) -> None:
        """Replace the marker labels under ``prefix`` (scene names starting with it) by ``labels``:
        (marker's scene name, anchor (3,) m, text) in priority order; then place all labels."""
        for key in [k for k in self.labels if k == prefix or k.startswith(prefix + "/")]:
            del self.labels[key]
            self._remove_label(key)
        for key, anchor, text in labels:
            x, y, z = (float(v) for v in anchor)
            self.labels[key] = ((x, y, z), str(text))
        if relabel:
            self.relabel()

    def camera(self) -> PinholeCamera:
        """The operator's camera as the browser reported it, else the framing camera."""
        cam = self.client.camera
        try:
            return PinholeCamera(tuple(cam.position), tuple(cam.look_at), tuple(cam.up_direction), float(cam.fov),
                                 int(cam.image_width) or 1280, int(cam.image_height) or 720)
        except AssertionError:  # viser asserts until the browser reported its camera
            lo_hi = self.framed_for[2] if self.framed_for else (5.0, 10.7)
            cabin = float(self.last_q[0]) if self.last_q is not None else 0.0
            pos, look = camera_framing(cabin, *lo_hi)
            return PinholeCamera(tuple(pos), tuple(look))

    def relabel(self) -> None:
        """Place the marker labels (server.console.scene_labels.place_labels) for the current camera and
        gripper, and move those whose place changed. Cheap when nothing changed."""
        cam = self.camera()
        obstacles = [b for b in self.fixed_boxes(cam) if b is not None]
        grip = gripper_footprint(cam, self.last_q) if self.last_q is not None else None
        if grip is not None:
            obstacles.append(grip)
        key = (cam, tuple(self.labels.items()),
               tuple(tuple(round(v / RELABEL_PX) for v in (b.x0, b.y0, b.x1, b.y1)) for b in obstacles))
        if key == self._label_key:
            return
        self._label_key = key
        placed = place_labels(cam, [(k, a, t) for k, (a, t) in self.labels.items()], obstacles)
        s = self.client.scene
        with self.client.atomic():
            for k, p in placed.items():
                anchor, text = self.labels[k]
                node = _label_node(k)
                s.add_label(f"/labels/{node}", text, position=tuple(p.position_m), anchor="center-center")
                s.add_line_segments(f"/leaders/{node}", np.array([[anchor, p.position_m]], dtype=np.float32), LEADER_GREY,
                                    thickness=0.02)
            for k in set(self.placements) - set(placed):
                self._remove_label(k)
        self.placements = placed

    def fixed_boxes(self, cam: PinholeCamera) -> list[Box | None]:
        """Screen boxes of the labels that do not move: the machine's name, the rings' distances."""
        boxes = [fixed_label_box(cam, MACHINE_LABEL_M, self.label.text if self.label is not None else "", MACHINE_LABEL_ANCHOR)]
        boxes += [fixed_label_box(cam, (0.0, -r - 0.1, 0.05), f"{r} m", "top-center") for r in RING_LABELS_M]
        return boxes

    def _remove_label(self, key: str) -> None:
        node = _label_node(key)
        self.client.scene.remove_by_name(f"/labels/{node}")
        self.client.scene.remove_by_name(f"/leaders/{node}")
        self.placements.pop(key, None)


def _label_node(key: str) -> str:
    """The scene node name of a marker's label: its scene name without slashes."""
    return key.strip("/").replace("/", "_")
