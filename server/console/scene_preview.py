"""Drawing a preview in the 3D view (viser): gripper and payload paths, the release point with its
velocity vector, the predicted impact, the 1 sigma impact ellipse and, in 3D mode, the swept
clearance zone. Every shape lives under ``/preview`` so one call replaces the previous preview.
Drawn client-scoped (one operator's view): the numbers are in the console page, so the labels
are the release speed and the ellipse's name (:func:`preview_labels`, placed with the view's
other labels by server.console.scene_labels); a failed preview is said by the target's own label.
"""

from __future__ import annotations

import math

import numpy as np

from runtime.machine import CABIN_RADIUS_M

DARK, ORANGE, PURPLE, MAGENTA, CLEAR = (60, 60, 70), (240, 140, 20), (120, 60, 200), (210, 30, 150), (250, 200, 40)
VELOCITY_ARROW_S = 0.3
"""The release velocity vector is drawn as the distance flown in this time (m per m/s)."""


def _segments(points) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    return np.stack([p[:-1], p[1:]], axis=1)


def clearance_sector(cabin_sweep_rad, radius_m: float, inner_m: float = CABIN_RADIUS_M, n: int = 48):
    """Vertices and faces of the ground annulus sector swept by the arm: cabin angles
    [min, max] (widened by 10 degrees each side), radii inner_m..radius_m, at z = 0.02."""
    lo, hi = cabin_sweep_rad
    lo, hi = lo - math.radians(10), hi + math.radians(10)
    ang = np.linspace(lo, hi, n)
    inner = np.stack([inner_m * np.cos(ang), inner_m * np.sin(ang), np.full(n, 0.02)], axis=1)
    outer = np.stack([radius_m * np.cos(ang), radius_m * np.sin(ang), np.full(n, 0.02)], axis=1)
    verts = np.concatenate([inner, outer])
    faces = []
    for i in range(n - 1):
        faces += [[i, n + i, n + i + 1], [i, n + i + 1, i + 1]]
    outline = np.concatenate([inner, outer[::-1], inner[:1]])
    return verts.astype(np.float32), np.array(faces, dtype=np.uint32), outline


def draw_preview(client, summary: dict, mode: str) -> list[str]:
    """Draw ``summary`` (sim_twin.preview.preview) in one viser client (``client.scene``, ``client.atomic``);
    returns the scene names drawn."""
    s = client.scene
    names = []

    def add(name, fn, *args, **kwargs):
        fn(name, *args, **kwargs)
        names.append(name)

    with client.atomic():
        s.remove_by_name("/preview")
        add("/preview", s.add_frame, show_axes=False)
        if summary.get("status") != "ok":
            return names
        if len(summary["gripper_path_m"]) >= 2:
            add("/preview/gripper_path", s.add_line_segments, _segments(summary["gripper_path_m"]), DARK, thickness=0.05)
        if len(summary["payload_path_m"]) >= 2:
            add("/preview/payload_path", s.add_line_segments, _segments(summary["payload_path_m"]), ORANGE, thickness=0.05)
        p0, v0 = np.array(summary["release_pos_m"]), np.array(summary["release_vel_mps"])
        add("/preview/release", s.add_icosphere, radius=0.18, color=PURPLE, position=tuple(p0))
        add("/preview/release_velocity", s.add_line_segments,
            np.array([[p0, p0 + VELOCITY_ARROW_S * v0]]), PURPLE, thickness=0.08)
        add("/preview/impact", s.add_icosphere, radius=0.22, color=ORANGE, position=tuple(summary["impact_m"]))
        ell = (summary.get("mc") or {}).get("ellipse")
        if ell:
            outline = np.array(ell["outline_m"])
            pts = np.column_stack([outline, np.full(len(outline), 0.04)])
            add("/preview/ellipse", s.add_line_segments, _segments(pts), MAGENTA, thickness=0.06)
        clr = summary.get("clearance") or {}
        if mode == "3d" and clr.get("cabin_sweep_rad"):
            verts, faces, outline = clearance_sector(clr["cabin_sweep_rad"], clr["max_radius_m"] + 1.0)
            add("/preview/clearance_zone", s.add_mesh_simple, verts, faces, color=CLEAR, opacity=0.3, side="double")
            add("/preview/clearance_outline", s.add_line_segments, _segments(outline), CLEAR, thickness=0.05)
    return names


def preview_labels(summary: dict) -> list[tuple[str, tuple[float, float, float], str]]:
    """The preview's labels (marker's scene name, anchor (3,) m, text), in priority order: the
    1 sigma ellipse (anchored at its centre on the ground), the release speed (at the release
    point); none for a failed preview."""
    if summary.get("status") != "ok":
        return []
    out = []
    ell = (summary.get("mc") or {}).get("ellipse")
    if ell:
        c = np.asarray(ell["outline_m"], dtype=float).mean(axis=0)
        out.append(("/preview/ellipse", (float(c[0]), float(c[1]), 0.04), "1σ landing area"))
    p0, v0 = summary["release_pos_m"], np.asarray(summary["release_vel_mps"], dtype=float)
    out.append(("/preview/release", (float(p0[0]), float(p0[1]), float(p0[2])), f"release {np.linalg.norm(v0):.1f} m/s"))
    return out
