"""Where the 3D view's labels go: never on top of each other, of another marker, or of the
hanging gripper, as the operator's camera sees them.

viser draws a label as screen-space text (constant pixel size, drawn over the geometry) centred
on a point of the scene. :func:`place_labels` projects every label's anchor (the marker it
names: target, impact, preview ellipse, release point) with the view's camera, then tries, in a
fixed order, boxes further and further from the anchor (up-right, up-left, right, left, up,
down-right, down-left, down; rings 30 px apart) until one fits on screen without touching an
obstacle (the gripper's screen footprint, the fixed labels, every marker) or a label already
placed; labels are placed in priority order (the target's first). A label that fits nowhere
goes to a stack at the top-left corner of the view. The chosen box centre is lifted back into the
scene at the anchor's depth, and a leader line joins it to its marker. Deterministic: the same
camera, machine pose and labels give the same places.

Frames: machine frame, z up, metres; screen pixels with x right, y down, origin top-left.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from runtime.machine import forward_kinematics

DEFAULT_FOV_RAD = math.radians(75.0)
"""viser's camera field of view (vertical) until the browser reports its own (viser.CameraHandle)."""
DEFAULT_SCREEN_PX = (1280, 720)
"""Canvas size assumed until the browser reports its own, px."""
CHAR_PX, LINE_PX = 8.0, 22.0
"""Width per character and height of one viser label line at ``font_screen_scale`` 1, px: viser
1.1 draws screen-mode labels with a 12 CSS px em (client/src/label/LabelRenderer.tsx), about 7 px
per character of its sans-serif font; these leave room for its background padding."""
GAP_PX = 6.0
"""Clear space kept around every box, px."""
MARKER_PX = 12.0
"""Half the side of the square kept free around every marker, px."""
RING_STEP_PX, RINGS = 30.0, 8
"""Candidate boxes: RINGS rings RING_STEP_PX apart around the anchor."""
GRIPPER_RADIUS_M = 0.7
"""Radius around the hanging gripper's key points (telescope tip, gripper centre, gripper
bottom) that its screen footprint covers, m: the gripper box's half diagonal (0.45 m wide, 1.0 m
high in the twin's MJCF) with a margin."""
GRIPPER_BOTTOM_DROP_M = 0.55
"""The gripper's bottom below its centre, m (half the gripper box's height, with a margin)."""


@dataclass(frozen=True)
class Box:
    """An axis-aligned screen box, px (x0 < x1, y0 < y1)."""

    x0: float
    y0: float
    x1: float
    y1: float

    def overlaps(self, other: Box, gap: float = 0.0) -> bool:
        """True if the boxes come closer than ``gap`` px."""
        return not (self.x1 + gap <= other.x0 or other.x1 + gap <= self.x0
                    or self.y1 + gap <= other.y0 or other.y1 + gap <= self.y0)

    @classmethod
    def around(cls, centre, half_w: float, half_h: float) -> Box:
        return cls(centre[0] - half_w, centre[1] - half_h, centre[0] + half_w, centre[1] + half_h)


@dataclass(frozen=True)
class PinholeCamera:
    """A perspective camera: position and look-at point (3,) m, up direction, vertical field of
    view (rad) and canvas size (px), as viser's camera reports them."""

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fov_rad: float = DEFAULT_FOV_RAD
    width_px: int = DEFAULT_SCREEN_PX[0]
    height_px: int = DEFAULT_SCREEN_PX[1]

    def _axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        f = np.asarray(self.look_at, float) - np.asarray(self.position, float)
        f /= np.linalg.norm(f)
        r = np.cross(f, np.asarray(self.up, float))
        if np.linalg.norm(r) < 1e-9:  # looking straight down the up axis
            r = np.cross(f, np.array([0.0, 1.0, 0.0]))
        r /= np.linalg.norm(r)
        return f, r, np.cross(r, f)

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (vertical field of view over the canvas height)."""
        return 0.5 * self.height_px / math.tan(0.5 * self.fov_rad)

    def project(self, p) -> tuple[np.ndarray, float] | None:
        """Pixel (x, y) (2,) and depth (m along the view direction) of scene point ``p`` (3,),
        or None when it lies behind the camera."""
        f, r, u = self._axes()
        d = np.asarray(p, float) - np.asarray(self.position, float)
        z = float(d @ f)
        if z <= 1e-6:
            return None
        k = self.focal_px / z
        return np.array([0.5 * self.width_px + k * float(d @ r), 0.5 * self.height_px - k * float(d @ u)]), z

    def unproject(self, xy, depth: float) -> np.ndarray:
        """The scene point (3,) seen at pixel ``xy`` at ``depth`` m (inverse of :meth:`project`)."""
        f, r, u = self._axes()
        k = depth / self.focal_px
        return (np.asarray(self.position, float) + depth * f + k * (xy[0] - 0.5 * self.width_px) * r
                - k * (xy[1] - 0.5 * self.height_px) * u)


@dataclass(frozen=True)
class Placement:
    """Where one label goes: its centre in the scene (3,) m (viser anchor ``center-center``),
    its screen box (px) and whether it went to the corner stack."""

    position_m: np.ndarray
    box: Box
    stacked: bool = False


def label_half_size(text: str) -> tuple[float, float]:
    """Half width and half height (px) of a label's screen box (:data:`CHAR_PX`, :data:`LINE_PX`)."""
    return 0.5 * (CHAR_PX * len(text) + 12.0), 0.5 * LINE_PX


def gripper_footprint(camera: PinholeCamera, q) -> Box | None:
    """The screen box (px) the hanging gripper covers at joint positions ``q`` (6,): its
    telescope tip, centre and bottom (runtime.machine.forward_kinematics) each widened by
    GRIPPER_RADIUS_M at its depth; None when it is behind the camera."""
    pts = forward_kinematics(np, np.asarray(q, float), np.zeros(6))
    centre = np.asarray(pts.gripper_centre, float)
    boxes = []
    for p in (np.asarray(pts.hanger, float), centre, centre - np.array([0.0, 0.0, GRIPPER_BOTTOM_DROP_M])):
        pr = camera.project(p)
        if pr is None:
            continue
        xy, z = pr
        rad = GRIPPER_RADIUS_M * camera.focal_px / z
        boxes.append(Box.around(xy, rad, rad))
    if not boxes:
        return None
    return Box(min(b.x0 for b in boxes), min(b.y0 for b in boxes), max(b.x1 for b in boxes), max(b.y1 for b in boxes))


def fixed_label_box(camera: PinholeCamera, position_m, text: str, anchor: str = "center-center") -> Box | None:
    """The screen box of a label that stays where it is (the machine's name, the range rings'
    distances), for :func:`place_labels` to keep clear of; ``anchor`` as viser's."""
    pr = camera.project(position_m)
    if pr is None:
        return None
    (x, y), _ = pr
    hw, hh = label_half_size(text)
    vert, horiz = anchor.split("-")
    x += {"left": hw, "center": 0.0, "right": -hw}[horiz]
    y += {"top": hh, "center": 0.0, "bottom": -hh}[vert]
    return Box.around((x, y), hw, hh)


def _candidates(anchor_xy: np.ndarray, hw: float, hh: float):
    """Box centres around a marker, nearest ring first, in a fixed order of directions."""
    for ring in range(RINGS):
        g = MARKER_PX + GAP_PX + ring * RING_STEP_PX
        dx, dy = hw + g, hh + g
        for sx, sy in ((1, -1), (-1, -1), (1, 0), (-1, 0), (0, -1), (1, 1), (-1, 1), (0, 1)):
            yield anchor_xy + np.array([sx * dx, sy * dy])


def place_labels(camera: PinholeCamera, labels: Sequence[tuple[str, object, str]],
                 obstacles: Sequence[Box] = ()) -> dict[str, Placement]:
    """Places for ``labels`` (key, anchor (3,) m, text), in this priority order (module doc).

    Args:
        camera: the view's camera.
        labels: the labels to place; a label whose anchor is behind the camera is left out.
        obstacles: screen boxes no label may touch (:func:`gripper_footprint`,
            :func:`fixed_label_box`).

    Returns:
        key -> :class:`Placement`. No two boxes come closer than GAP_PX; no box touches an
        obstacle or a marker's square (MARKER_PX), except boxes of the corner stack, which keep
        clear of the other labels only.
    """
    projected = []
    for key, anchor, text in labels:
        pr = camera.project(anchor)
        if pr is not None:
            projected.append((key, pr[0], pr[1], text))
    markers = [Box.around(xy, MARKER_PX, MARKER_PX) for _, xy, _, _ in projected]
    screen = Box(0.0, 0.0, float(camera.width_px), float(camera.height_px))
    taken: list[Box] = []
    out: dict[str, Placement] = {}
    stack_y = GAP_PX
    for key, xy, depth, text in projected:
        hw, hh = label_half_size(text)
        chosen = None
        for c in _candidates(xy, hw, hh):
            box = Box.around(c, hw, hh)
            inside = box.x0 >= screen.x0 and box.y0 >= screen.y0 and box.x1 <= screen.x1 and box.y1 <= screen.y1
            if inside and not any(box.overlaps(o, GAP_PX) for o in (*taken, *obstacles, *markers)):
                chosen = (c, box, False)
                break
        if chosen is None:  # nowhere near its marker: the corner stack, joined by its leader line
            box = Box(GAP_PX, stack_y, GAP_PX + 2 * hw, stack_y + 2 * hh)
            while any(box.overlaps(o, GAP_PX) for o in taken):
                box = Box(box.x0, box.y0 + LINE_PX / 2, box.x1, box.y1 + LINE_PX / 2)
            c = np.array([0.5 * (box.x0 + box.x1), 0.5 * (box.y0 + box.y1)])
            chosen = (c, box, True)
            stack_y = box.y1 + GAP_PX
        c, box, stacked = chosen
        taken.append(box)
        out[key] = Placement(camera.unproject(c, depth), box, stacked)
    return out
