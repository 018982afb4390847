"""The logged-throw input format of the diagnosis, tolerant of what a real machine lacks.

A throw is one MCAP file (JSON message encoding, ``jsonschema`` schemas; times ``t_s`` in
seconds on one clock per throw), or the runtime's telemetry in ROS 2 form (CDR; read through
``runtime.telemetry.read_messages`` into the same fields). Topics and fields:

==================  ========  ==================================================================
topic               needed    fields
==================  ========  ==================================================================
/joint_states       yes       t_s, q (6,) rad/m, qd (6,) rad/s, m/s in JOINT_NAMES order; q[4:6],
                              qd[4:6] are the gripper IMU's pitch and roll (or give 4 values and
                              the /gripper_imu topic)
/gripper_imu        no        t_s, angle_rad (2,) pitch, roll; rate_radps (2,)
/valve_commands     yes       t_s, u (4,) in [-1, 1], ACTIVE_JOINTS order
/gripper            yes       t_s, command_open (bool: the release command); open (bool,
                              optional: payload free, measured)
/references         no        t_s, phase, qd_ref (4,): the Slinger runtime's joint-velocity
                              references; with them the replay runs the runtime's controller,
                              without them it replays the logged valve commands open loop
/payload            no        t_s, pos_m (3,), vel_mps (3,): payload tracking
==================  ========  ==================================================================

Rows are the /joint_states messages (100 Hz); the other topics are matched to them by time
(nearest earlier sample). The swing starts at the first /references row whose phase is not
"preparing", else at the first row with a valve command above 0.02, else at row 0.

Impacts: ``impact_m`` [x, y, 0] (machine frame, m) and ``impact_stamp_s`` in ``index.json``,
or an ``impacts.csv`` beside it with columns ``throw_id, impact_x_m, impact_y_m`` and optionally
``impact_stamp_s`` (the CSV wins). A throw without a measured impact is skipped with a warning.
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader

from runtime.telemetry import read_messages as read_telemetry_messages

log = logging.getLogger(__name__)

TOPICS = ("/joint_states", "/gripper_imu", "/valve_commands", "/gripper", "/references", "/payload", "/events")
REQUIRED = ("/joint_states", "/valve_commands", "/gripper")
START_U = 0.02  # valve command that counts as the swing's start when there are no references


class LogError(ValueError):
    """A logged throw cannot be read (the message says which field or topic is missing)."""


def read_messages(source) -> dict[str, list[dict]]:
    """All messages of the known topics of one MCAP file (path or bytes), by topic, as JSON-layout dicts.

    Raises:
        LogError: not a readable MCAP file.
    """
    import io

    per: dict[str, list[dict]] = {t: [] for t in TOPICS}
    try:
        with (io.BytesIO(bytes(source)) if isinstance(source, (bytes, bytearray)) else open(source, "rb")) as f:
            for _schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
                if channel.message_encoding == "cdr":  # the runtime's telemetry in ROS 2 form
                    return {**per, **read_telemetry_messages(source)}
                if channel.topic in per:
                    per[channel.topic].append(json.loads(message.data))
    except FileNotFoundError:
        raise
    except Exception as e:  # mcap raises several exception types for corrupt files
        raise LogError(f"not a readable MCAP file ({type(e).__name__}: {e})") from e
    return per


def _matched(rows_t: np.ndarray, msgs: list[dict], key: str, width: int | None, what: str, dtype=float) -> np.ndarray:
    """Values of ``key`` from ``msgs`` at the row times (nearest earlier message, else the first)."""
    if any(key not in m for m in msgs):
        raise LogError(f"{what}: field {key!r} missing")
    t = np.array([float(m["t_s"]) for m in msgs])
    v = np.asarray([m[key] for m in msgs], dtype=dtype)
    if width is not None and (v.ndim != 2 or v.shape[1] != width):
        raise LogError(f"{what}: {key} must have {width} values per message, got shape {v.shape}")
    idx = np.clip(np.searchsorted(t, rows_t + 1e-9, side="right") - 1, 0, len(t) - 1)
    return v[idx]


def arrays(per: dict[str, list[dict]]) -> dict:
    """Row-aligned arrays of one throw (see module doc).

    Returns:
        dict t_s (T,), q, qd (T, 6), valve_u (T, 4), gripper_cmd (T,) bool, gripper_open (T,)
        bool or None, qd_ref (T, 4) or None, phase (T,) str or None, payload_t_s (P,),
        payload_pos_m (P, 3), k0 (swing-start row).

    Raises:
        LogError: a required topic or field is missing or misshaped, or values are not finite.
    """
    missing = [t for t in REQUIRED if not per[t]]
    if missing:
        raise LogError(f"missing topics {missing} (needed: {list(REQUIRED)})")
    js = per["/joint_states"]
    t = np.array([float(m["t_s"]) for m in js])
    if np.any(np.diff(t) <= 0):
        raise LogError("/joint_states: t_s must increase")
    width = len(js[0].get("q", []))
    if width not in (4, 6):
        raise LogError(f"/joint_states: q must have 6 values (or 4 with /gripper_imu), got {width}")
    q = np.zeros((len(t), 6))
    qd = np.zeros((len(t), 6))
    q[:, :width] = _matched(t, js, "q", width, "/joint_states")
    qd[:, :width] = _matched(t, js, "qd", width, "/joint_states")
    if per["/gripper_imu"]:
        q[:, 4:6] = _matched(t, per["/gripper_imu"], "angle_rad", 2, "/gripper_imu")
        qd[:, 4:6] = _matched(t, per["/gripper_imu"], "rate_radps", 2, "/gripper_imu")
    elif width == 4:
        raise LogError("no gripper IMU: /joint_states has 4 values and there is no /gripper_imu topic")
    out: dict[str, Any] = {"t_s": t, "q": q, "qd": qd, "valve_u": _matched(t, per["/valve_commands"], "u", 4, "/valve_commands"),
           "gripper_cmd": _matched(t, per["/gripper"], "command_open", None, "/gripper", dtype=bool)}
    g = per["/gripper"]
    out["gripper_open"] = _matched(t, g, "open", None, "/gripper", dtype=bool) if all("open" in m for m in g) else None
    refs = per["/references"]
    out["qd_ref"] = _matched(t, refs, "qd_ref", 4, "/references") if refs else None
    out["phase"] = _matched(t, refs, "phase", None, "/references", dtype=str) if refs else None
    pay = per["/payload"]
    out["payload_t_s"] = np.array([float(m["t_s"]) for m in pay])
    out["payload_pos_m"] = np.asarray([m["pos_m"] for m in pay], dtype=float).reshape(-1, 3)
    for k in ("q", "qd", "valve_u"):
        if not np.all(np.isfinite(out[k])):
            raise LogError(f"non-finite values in {k}")
    if out["phase"] is not None and np.any(out["phase"] != "preparing"):
        k0 = int(np.flatnonzero(out["phase"] != "preparing")[0])
    else:
        moving = np.flatnonzero(np.any(np.abs(out["valve_u"]) > START_U, axis=1))
        k0 = int(moving[0]) if moving.size else 0
    out["k0"] = k0
    return out


def read_impacts_csv(path: Path) -> dict[str, dict]:
    """``impacts.csv`` rows by throw_id: {"impact_m": [x, y, 0], "impact_stamp_s": float|None}.
    Rows with an empty impact are returned with impact_m None.

    Raises:
        LogError: missing columns or unparsable numbers (with the line number).
    """
    out = {}
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        need = {"throw_id", "impact_x_m", "impact_y_m"}
        if not need <= set(reader.fieldnames or ()):
            raise LogError(f"{path}: needs columns {sorted(need)}, has {reader.fieldnames}")
        for i, row in enumerate(reader, start=2):
            try:
                x, y = row["impact_x_m"].strip(), row["impact_y_m"].strip()
                stamp = (row.get("impact_stamp_s") or "").strip()
                out[row["throw_id"]] = {"impact_m": [float(x), float(y), 0.0] if x and y else None,
                                        "impact_stamp_s": float(stamp) if stamp else None}
            except ValueError as e:
                raise LogError(f"{path} line {i}: {e}") from e
    return out
