"""Convert another machine's logs (generic CSV or MCAP) into a diagnosis dataset (rosbag2 bags:
:mod:`sim_twin.diagnosis.rosbag`).

A mapping (JSON) says where each needed quantity is and how to scale it::

    {"machine_id": "excavator-7",
     "time": {"column": "stamp_ns", "scale": 1e-9},
     "joints": {                        # JOINT_NAMES -> column (and optional scale, offset)
        "cabin_turn": {"column": "slew_rad"}, "boom": {"column": "boom_deg", "scale": 0.0174533},
        "dipper": {"column": "stick_deg", "scale": 0.0174533}, "telescope": {"column": "tele_mm", "scale": 0.001},
        "gripper_pitch": {"column": "imu_pitch"}, "gripper_roll": {"column": "imu_roll"}},
     "rates": {"boom": {"column": "boom_rate"}, ...},       # optional: else central differences
     "valves": {"cabin_turn": {"column": "v_slew", "scale": 0.01}, ...},   # in [-1, 1]
     "release_command": {"column": "grip_open_cmd"},        # truthy = open commanded
     "open": {"column": "grip_open_sensor"},                # optional
     "mcap_topic": "/machine/state"}                        # MCAP input: the topic whose JSON
                                                            # messages hold the columns as fields

Inputs: one CSV (header row) or MCAP file per throw; the throw id is the file stem. Targets and
measured impacts come from a CSV: ``throw_id, target_x_m, target_y_m, impact_x_m, impact_y_m``
(impact cells may be empty: the throw is kept in the index and skipped by the diagnosis with a
warning). Output: a dataset directory (:mod:`dataset`) with logformat MCAPs.
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import numpy as np

from runtime.machine import ACTIVE_JOINTS, JOINT_NAMES
from sim_twin.diagnosis import dataset as ds
from sim_twin.diagnosis.reallog import RealLogSpec, write_log

log = logging.getLogger(__name__)


class ConvertError(ValueError):
    """The mapping or an input file cannot be used (the message says which and why)."""


def _table(path: Path, mapping: dict) -> dict[str, np.ndarray]:
    """Columns of one input file as float arrays."""
    if path.suffix.lower() == ".mcap":
        from mcap.reader import make_reader

        topic = mapping.get("mcap_topic")
        if not topic:
            raise ConvertError("MCAP input needs 'mcap_topic' in the mapping")

        rows = []
        try:
            with open(path, "rb") as f:
                for _s, ch, msg in make_reader(f).iter_messages(log_time_order=True):
                    if ch.topic == topic:
                        rows.append(json.loads(msg.data))
        except Exception as e:  # mcap raises several types
            raise ConvertError(f"{path}: not a readable MCAP file ({e})") from e
        if not rows:
            raise ConvertError(f"{path}: no messages on topic {topic!r}")
        keys = set().union(*rows)
        return {k: np.array([float(r.get(k, np.nan)) for r in rows]) for k in keys}
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        data: dict[str, list[float]] = {k: [] for k in reader.fieldnames or []}
        for i, row in enumerate(reader, start=2):
            for k, v in row.items():
                try:
                    data[k].append(float(v) if v not in ("", None) else np.nan)
                except ValueError:
                    if v.strip().lower() in ("true", "false"):
                        data[k].append(1.0 if v.strip().lower() == "true" else 0.0)
                    else:
                        raise ConvertError(f"{path} line {i}: column {k!r}: {v!r} is not a number") from None
    return {k: np.array(v) for k, v in data.items()}


def _col(table: dict, spec: dict | None, what: str, path: Path) -> np.ndarray:
    if not spec or "column" not in spec:
        raise ConvertError(f"mapping: {what} needs a 'column'")
    if spec["column"] not in table:
        raise ConvertError(f"{path}: column {spec['column']!r} ({what}) not found; has {sorted(table)}")
    return table[spec["column"]] * float(spec.get("scale", 1.0)) + float(spec.get("offset", 0.0))


def convert_throw(path: Path, mapping: dict) -> tuple[list[dict], list[dict]]:
    """Recorder-style rows and events of one throw (see module doc)."""
    table = _table(path, mapping)
    t = _col(table, mapping.get("time"), "time", path)
    if np.any(np.diff(t) <= 0):
        raise ConvertError(f"{path}: time must increase")
    q = np.stack([_col(table, mapping.get("joints", {}).get(j), f"joint {j}", path) for j in JOINT_NAMES], axis=1)
    rates = mapping.get("rates", {})
    qd = np.gradient(q, t, axis=0)
    for i, j in enumerate(JOINT_NAMES):
        if j in rates:
            qd[:, i] = _col(table, rates[j], f"rate {j}", path)
    u = np.stack([_col(table, mapping.get("valves", {}).get(j), f"valve {j}", path) for j in ACTIVE_JOINTS], axis=1)
    cmd = _col(table, mapping.get("release_command"), "release_command", path) > 0.5
    opened = _col(table, mapping["open"], "open", path) > 0.5 if mapping.get("open") else np.zeros(len(t), bool)
    for name, a in (("joints", q), ("rates", qd), ("valves", u)):
        if not np.all(np.isfinite(a)):
            raise ConvertError(f"{path}: non-finite {name}")
    t = t - t[0]
    rows = [{"t_s": float(t[i]), "q": q[i].tolist(), "qd": qd[i].tolist(), "qd_ref": [0.0] * 4, "u": np.clip(u[i], -1, 1).tolist(),
             "command_open": bool(cmd[i]), "open": bool(opened[i]), "phase": "swinging", "pos_m": None, "vel_mps": None} for i in range(len(t))]
    return rows, []


def read_targets(impacts_csv: Path) -> dict[str, tuple[list[float], list[float] | None]]:
    """Targets and measured impacts by throw id from ``throw_id, target_x_m, target_y_m,
    impact_x_m, impact_y_m`` (machine frame, m; empty impact cells: None).

    Raises:
        ConvertError: unreadable file, a missing column or a value that is not a number.
    """
    targets = {}
    try:
        with open(impacts_csv, newline="") as f:
            for row in csv.DictReader(f):
                ix, iy = (row.get("impact_x_m") or "").strip(), (row.get("impact_y_m") or "").strip()
                targets[row["throw_id"]] = ([float(row["target_x_m"]), float(row["target_y_m"]), 0.0],
                                            [float(ix), float(iy), 0.0] if ix and iy else None)
    except OSError as e:
        raise ConvertError(f"{impacts_csv}: {e}") from e
    except (KeyError, ValueError, TypeError) as e:
        raise ConvertError(f"{impacts_csv}: needs throw_id, target_x_m, target_y_m, impact_x_m, impact_y_m ({e})") from e
    return targets


def convert(inputs: list[Path], mapping_path: Path, impacts_csv: Path, out_dir: Path) -> Path:
    """Convert throw files into a dataset directory; returns its index path.

    Raises:
        ConvertError: bad mapping, missing columns, unreadable files or a throw without a target.
    """
    try:
        mapping = json.loads(Path(mapping_path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ConvertError(f"mapping {mapping_path}: {e}") from e
    targets = read_targets(impacts_csv)
    spec = RealLogSpec(open_flag=bool(mapping.get("open")), payload_channel=False)
    out = []
    for path in inputs:
        tid = Path(path).stem
        if tid not in targets:
            raise ConvertError(f"{path}: throw {tid!r} has no row in {impacts_csv}")
        rows, events = convert_throw(Path(path), mapping)
        target, impact = targets[tid]
        out.append(({"throw_id": tid, "mode": mapping.get("mode", "3d"), "target_m": target, "impact_m": impact, "impact_stamp_s": None,
                     "status": "landed"}, write_log(rows, events, spec, {"throw_id": tid, "source": str(path)})))
    log.info("converted %d throws from %s", len(out), mapping_path)
    return ds.write(out_dir, out, machine_id=mapping.get("machine_id", "external"), source={"converted_from": [str(p) for p in inputs]},
                    sensors=mapping.get("sensors"))
