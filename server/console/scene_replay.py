"""A recorded throw replayed in one console's 3D view, on the timeline of the History page's plots.

The History page opens a console (server.console.scene) and seeks it (``PUT /api/consoles/{id}/replay``)
to the time its plots' cursor shows; the scene then poses that console's machine from the
recording instead of the machine's live state, and flies the payload where it flew. Time is the
plots' time: seconds from the first joint state of the recording (web/js/plots.js subtracts the
same first time from the joint states and the payload samples).

Frames: machine frame, z up, metres; joint vectors in chain order (docs/architecture.md, Terms).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runtime.machine import forward_kinematics

TRAJECTORY_POINTS = 300
"""Points at most of a drawn recorded path (gripper centre, payload)."""


def recorded_paths(tel: dict[str, np.ndarray]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The gripper centre's path (forward kinematics of the recorded joints, at most
    TRAJECTORY_POINTS points, (K, 3) m) and the payload's recorded path ((M, 3) m) of a
    recording (runtime.telemetry.read_telemetry); None for a path with fewer than 2 points."""
    n = len(tel["q"])
    idx = np.linspace(0, n - 1, min(n, TRAJECTORY_POINTS)).astype(int) if n else np.array([], dtype=int)
    gripper = (np.array([forward_kinematics(np, tel["q"][i], tel["qd"][i]).gripper_centre for i in idx])
               if len(idx) >= 2 else None)
    payload = np.asarray(tel["payload_pos_m"], dtype=float) if len(tel["payload_pos_m"]) >= 2 else None
    return gripper, payload


@dataclass
class Replay:
    """One recorded throw, loaded for a console's replay.

    Attributes:
        throw_id / machine_id: the throw and its machine.
        t_s: (N,) joint-state times, s from the first (strictly increasing after loading).
        q: (N, 6) joint positions (rad, telescope m).
        payload_t_s: (M,) payload sample times on the same clock, s; payload_pos_m (M, 3) m.
        gripper_path_m / payload_path_m: the drawn paths (:func:`recorded_paths`), or None.
        impact_m / target_m: (3,) m or None.
        shown_t_s: the time the view shows, s (set by :meth:`seek`).
    """

    throw_id: str
    machine_id: str
    t_s: np.ndarray
    q: np.ndarray
    payload_t_s: np.ndarray
    payload_pos_m: np.ndarray
    gripper_path_m: np.ndarray | None
    payload_path_m: np.ndarray | None
    impact_m: list[float] | None
    target_m: list[float] | None
    shown_t_s: float = 0.0

    @classmethod
    def load(cls, throw_id: str, machine_id: str, telemetry_path: Path, impact_m=None, target_m=None) -> Replay:
        """Read a throw's MCAP telemetry (runtime.telemetry).

        Raises:
            ValueError: the recording has no joint states (nothing to replay), or is not MCAP.
        """
        from runtime.telemetry import read_telemetry

        try:
            tel = read_telemetry(telemetry_path)
        except Exception as e:  # mcap's own errors: an unreadable file is a bad recording
            raise ValueError(f"the telemetry of throw {throw_id} cannot be read: {e}") from e
        t, q = np.asarray(tel["t_s"], dtype=float), np.asarray(tel["q"], dtype=float)
        if len(t) == 0 or q.shape != (len(t), 6):
            raise ValueError(f"the telemetry of throw {throw_id} has no joint states to replay")
        keep = np.concatenate([[True], np.diff(t) > 0])  # np.interp needs increasing times
        t0 = float(t[0])
        pt = np.asarray(tel["payload_t_s"], dtype=float)
        pp = np.asarray(tel["payload_pos_m"], dtype=float).reshape(-1, 3)
        pkeep = np.concatenate([[True], np.diff(pt) > 0]) if len(pt) else np.zeros(0, dtype=bool)
        gripper, payload = recorded_paths(tel)
        return cls(throw_id, machine_id, t[keep] - t0, q[keep], pt[pkeep] - t0, pp[pkeep], gripper, payload,
                   list(impact_m) if impact_m is not None else None, list(target_m) if target_m is not None else None)

    @property
    def duration_s(self) -> float:
        """Length of the joint-state recording, s."""
        return float(self.t_s[-1])

    def seek(self, t_s: float) -> float:
        """Show time ``t_s`` (s, clamped to [0, duration]); returns the time shown."""
        self.shown_t_s = float(np.clip(t_s, 0.0, self.duration_s))
        return self.shown_t_s

    def pose(self, t_s: float | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """Joint positions (6,) at ``t_s`` (default: the shown time; linear between samples) and
        the payload's position (3,) m while it flies (between its first and last recorded
        sample), else None."""
        t = self.shown_t_s if t_s is None else float(t_s)
        q = np.array([np.interp(t, self.t_s, self.q[:, j]) for j in range(6)])
        payload = None
        if len(self.payload_t_s) and self.payload_t_s[0] <= t <= self.payload_t_s[-1]:
            payload = np.array([np.interp(t, self.payload_t_s, self.payload_pos_m[:, k]) for k in range(3)])
        return q, payload

    def public(self) -> dict:
        """What a console page reads (ConsoleOut.replay): throw, shown time and duration, s."""
        return {"throw_id": self.throw_id, "t_s": round(self.shown_t_s, 4), "duration_s": round(self.duration_s, 4)}
