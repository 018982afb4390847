"""A throw's 100 Hz telemetry: recorded in memory by the executor, stored as MCAP.

MCAP layout (JSON message encoding, one ``jsonschema`` schema per channel; log and publish times
are the machine's monotonic stamps in nanoseconds):

================  =====================================================================
channel           message
================  =====================================================================
/joint_states     t_s, q (6,) rad/m, qd (6,) rad/s, m/s  (JOINT_NAMES order)
/references       t_s, phase, qd_ref (4,) rad/s, m/s after safety clipping (ACTIVE_JOINTS)
/valve_commands   t_s, u (4,) in [-1, 1]
/gripper          t_s, command_open (runtime command), open (payload free, measured)
/payload          t_s, pos_m (3,), vel_mps (3,), machine frame; only ticks where known
/events           t_s, phase, detail: the throw's phase changes
================  =====================================================================

MCAP metadata record ``throw`` holds string fields (throw_id, mode, policy_version, ...).
:func:`read_telemetry` turns a file back into numpy arrays for tests and server-side replay.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

_ARR = {"type": "array", "items": {"type": "number"}}
_SCHEMAS: dict[str, dict] = {
    "/joint_states": {"t_s": {"type": "number"}, "q": _ARR, "qd": _ARR},
    "/references": {"t_s": {"type": "number"}, "phase": {"type": "string"}, "qd_ref": _ARR},
    "/valve_commands": {"t_s": {"type": "number"}, "u": _ARR},
    "/gripper": {"t_s": {"type": "number"}, "command_open": {"type": "boolean"}, "open": {"type": "boolean"}},
    "/payload": {"t_s": {"type": "number"}, "pos_m": _ARR, "vel_mps": _ARR},
    "/events": {"t_s": {"type": "number"}, "phase": {"type": "string"}, "detail": {"type": ["string", "null"]}},
}


@dataclass
class TelemetryRecorder:
    """In-memory per-tick record of one throw (pure data, no I/O).

    Call :meth:`record` once per 100 Hz tick and :meth:`event` on every phase change.
    """

    rows: list[dict] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)

    def record(self, t_s: float, q, qd, qd_ref, valve_u, gripper_cmd: bool, gripper_open: bool, phase: str, payload_pos_m=None, payload_vel_mps=None) -> None:
        """Append one tick. Vectors: q, qd (6,), qd_ref, valve_u (4,), payload (3,) or None."""
        self.rows.append(
            {
                "t_s": float(t_s),
                "q": [float(v) for v in q],
                "qd": [float(v) for v in qd],
                "qd_ref": [float(v) for v in qd_ref],
                "u": [float(v) for v in valve_u],
                "command_open": bool(gripper_cmd),
                "open": bool(gripper_open),
                "phase": phase,
                "pos_m": None if payload_pos_m is None else [float(v) for v in payload_pos_m],
                "vel_mps": None if payload_vel_mps is None else [float(v) for v in payload_vel_mps],
            }
        )

    def event(self, t_s: float, phase: str, detail: str | None = None) -> None:
        self.events.append({"t_s": float(t_s), "phase": phase, "detail": detail})

    def __len__(self) -> int:
        return len(self.rows)


def _ns(t_s: float) -> int:
    return max(0, int(round(t_s * 1e9)))


def write_mcap(recorder: TelemetryRecorder, metadata: dict[str, str] | None = None) -> bytes:
    """Serialise a recording to MCAP bytes (zstd-compressed chunks).

    Args:
        recorder: the throw's recording.
        metadata: string key/values stored as the MCAP metadata record ``throw``.
    """
    buf = io.BytesIO()
    writer = Writer(buf, compression=CompressionType.ZSTD)
    writer.start(profile="", library="slinger-runtime")
    channels: dict[str, int] = {}
    for topic, props in _SCHEMAS.items():
        schema = {"type": "object", "properties": props, "required": list(props)}
        sid = writer.register_schema(name=f"slinger{topic.replace('/', '.')}", encoding="jsonschema", data=json.dumps(schema).encode())
        channels[topic] = writer.register_channel(topic=topic, message_encoding="json", schema_id=sid)
    seq = 0

    def put(topic: str, t_s: float, msg: dict) -> None:
        nonlocal seq
        writer.add_message(channels[topic], log_time=_ns(t_s), data=json.dumps(msg).encode(), publish_time=_ns(t_s), sequence=seq)
        seq += 1

    for r in recorder.rows:
        t = r["t_s"]
        put("/joint_states", t, {"t_s": t, "q": r["q"], "qd": r["qd"]})
        put("/references", t, {"t_s": t, "phase": r["phase"], "qd_ref": r["qd_ref"]})
        put("/valve_commands", t, {"t_s": t, "u": r["u"]})
        put("/gripper", t, {"t_s": t, "command_open": r["command_open"], "open": r["open"]})
        if r["pos_m"] is not None and r["vel_mps"] is not None:
            put("/payload", t, {"t_s": t, "pos_m": r["pos_m"], "vel_mps": r["vel_mps"]})
    for e in recorder.events:
        put("/events", e["t_s"], e)
    writer.add_metadata("throw", {k: str(v) for k, v in (metadata or {}).items()})
    writer.finish()
    return buf.getvalue()


def _open(source: bytes | bytearray | str | Path) -> IO[bytes]:
    if isinstance(source, (bytes, bytearray)):
        return io.BytesIO(bytes(source))
    return open(source, "rb")


def read_telemetry(source: bytes | bytearray | str | Path) -> dict[str, np.ndarray]:
    """Read an MCAP telemetry file back into arrays.

    Args:
        source: MCAP bytes or a file path.

    Returns:
        dict with ``t_s`` (N,), ``q`` (N, 6), ``qd`` (N, 6), ``qd_ref`` (N, 4), ``phase`` (N,)
        str, ``valve_u`` (N, 4), ``gripper_cmd`` (N,) bool, ``gripper_open`` (N,) bool,
        ``payload_t_s`` (M,), ``payload_pos_m`` (M, 3), ``payload_vel_mps`` (M, 3),
        ``event_t_s`` (E,), ``event_phase`` (E,) str, ``event_detail`` (E,) object (str or None).

    Raises:
        mcap.exceptions.McapError (or ValueError) for a file that is not valid MCAP.
    """
    per: dict[str, list[dict]] = {t: [] for t in _SCHEMAS}
    with _open(source) as f:
        for _schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
            if channel.topic in per:
                per[channel.topic].append(json.loads(message.data))

    def arr(topic: str, key: str, width: int | None = None, dtype=float) -> np.ndarray:
        rows = [m[key] for m in per[topic]]
        if width is not None and not rows:
            return np.zeros((0, width), dtype=dtype)
        return np.asarray(rows, dtype=dtype)

    return {
        "t_s": arr("/joint_states", "t_s"),
        "q": arr("/joint_states", "q", 6),
        "qd": arr("/joint_states", "qd", 6),
        "qd_ref": arr("/references", "qd_ref", 4),
        "phase": arr("/references", "phase", dtype=str),
        "valve_u": arr("/valve_commands", "u", 4),
        "gripper_cmd": arr("/gripper", "command_open", dtype=bool),
        "gripper_open": arr("/gripper", "open", dtype=bool),
        "payload_t_s": arr("/payload", "t_s"),
        "payload_pos_m": arr("/payload", "pos_m", 3),
        "payload_vel_mps": arr("/payload", "vel_mps", 3),
        "event_t_s": arr("/events", "t_s"),
        "event_phase": arr("/events", "phase", dtype=str),
        "event_detail": np.asarray([m["detail"] for m in per["/events"]], dtype=object),
    }


def read_metadata(source: bytes | bytearray | str | Path) -> dict[str, str]:
    """The ``throw`` metadata record of a telemetry file (empty dict if absent)."""
    with _open(source) as f:
        for record in make_reader(f).iter_metadata():
            if record.name == "throw":
                return dict(record.metadata)
    return {}
