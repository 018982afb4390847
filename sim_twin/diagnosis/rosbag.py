"""Convert a ROS 2 machine's rosbag2 recordings into a diagnosis dataset.

::

    slinger diagnose convert --mapping bridge.toml --impacts impacts.csv --out DIR BAG...

Each BAG is one throw (its id: the bag directory's name or the file's stem): a rosbag2 directory
(``metadata.yaml`` with ``mcap`` or ``sqlite3`` storage), or a single ``.mcap`` or ``.db3`` file,
read with rosbags and decoded with the ROS 2 Jazzy typestore (each topic's type is checked). The mapping is the ROS 2 bridge's file (runtime.ros2.config: topics, joint
names, units, valve layout) with these extra keys::

    machine_id = "excavator-7"     # the dataset's machine id (default "external")
    mode = "3d"                    # "2d" or "3d" (default "3d")
    [sensors]                      # the declared sensor spec (dataset.py), optional
    impact_sigma_m = 0.05

Topics used: joint states (``sensor_msgs/JointState``; the passive joints from the same message, the
passive-joint topic or the gripper IMU ``topics.imu``, runtime.ros2.imu), valve commands (``std_msgs/Float64MultiArray``), the gripper
command (``std_msgs/Bool``, true = open: the release command), the gripper state (``std_msgs/Bool``,
optional: the payload-free flag) and the payload (``nav_msgs/Odometry``, optional). Rows are the
joint-state messages; other topics are matched by the bag's receive time (newest earlier message).
Joint velocities come from the JointState or the IMU's angular velocity (central differences where
a JointState has none). Targets and measured impacts: the same CSV as ``convert`` (convert.read_targets).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np

from runtime.machine import ACTIVE_JOINTS, PASSIVE_JOINTS
from runtime.ros2 import types as rt
from runtime.ros2.config import BridgeConfig, ConfigError
from runtime.ros2.config import load as load_config
from runtime.ros2.imu import passive_from_imu
from sim_twin.diagnosis import dataset as ds
from sim_twin.diagnosis.convert import ConvertError, read_targets
from sim_twin.diagnosis.reallog import RealLogSpec, write_log

log = logging.getLogger(__name__)


class BagMapping(BridgeConfig):
    """The bridge mapping plus what a dataset needs (module doc)."""

    machine_id: str = "external"
    mode: Literal["2d", "3d"] = "3d"
    sensors: dict[str, float] | None = None


def load_mapping(path: str | Path) -> BagMapping:
    """Read a bag mapping (.toml, .json, .yaml).

    Raises:
        ConvertError: what runtime.ros2.config.load refuses, for this model.
    """
    try:
        return cast(BagMapping, load_config(path, BagMapping))  # load returns an instance of the model it is given
    except ConfigError as e:
        raise ConvertError(f"mapping {e}") from e


def is_rosbag(path: str | Path) -> bool:
    """A rosbag2 directory, a ``.db3`` file, or an MCAP file with CDR channels."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    if path.suffix == ".db3":
        return True
    if path.suffix == ".mcap":
        from mcap.reader import make_reader

        try:
            with open(path, "rb") as f:
                summary = make_reader(f).get_summary()
            return summary is not None and any(c.message_encoding == "cdr" for c in summary.channels.values())
        except Exception:  # noqa: BLE001 an unreadable file is not a bag; convert reports it
            return False
    return False


def _messages(path: Path, wanted: dict[str, str]) -> dict[str, list[tuple[float, Any]]]:  # rosbags messages: no static types
    """(receive time s, message) per wanted topic (topic -> expected type) of one bag.

    Raises:
        ConvertError: unreadable bag, a wanted topic of another type.
    """
    from rosbags.rosbag2 import Reader

    out: dict[str, list] = {t: [] for t in wanted}
    store = rt.typestore()
    try:
        with Reader(path) as reader:
            conns = []
            for c in reader.connections:
                if c.topic not in wanted:
                    continue
                if c.msgtype != wanted[c.topic]:
                    raise ConvertError(f"{path}: topic {c.topic} has type {c.msgtype}, expected {wanted[c.topic]}")
                conns.append(c)
            for conn, t_ns, raw in reader.messages(connections=conns):
                out[conn.topic].append((t_ns * 1e-9, store.deserialize_cdr(raw, conn.msgtype)))
    except ConvertError:
        raise
    except Exception as e:
        raise ConvertError(f"{path}: not a readable rosbag2 ({type(e).__name__}: {e})") from e
    return out


def _before(times: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Index of the newest sample at or before each of ``t`` (-1: none yet)."""
    return np.searchsorted(times, t + 1e-9, side="right") - 1


def convert_bag(path: Path, mapping: BagMapping) -> list[dict]:
    """Recorder-style rows (runtime.telemetry.TelemetryRecorder fields) of one bag.

    Raises:
        ConvertError: unreadable bag, missing topics or joints, time not increasing, non-finite values.
    """
    t = mapping.topics
    wanted: dict[str, str] = {}
    for topic, typename in ((t.joint_states, rt.JOINT_STATE), (t.valve_command, rt.FLOAT64_MULTI_ARRAY), (t.gripper_command, rt.BOOL),
                            (t.passive_joint_states, rt.JOINT_STATE), (t.gripper_state, rt.BOOL), (t.payload, rt.ODOMETRY),
                            (t.imu, rt.IMU)):
        if topic and wanted.setdefault(topic, typename) != typename:
            raise ConvertError(f"mapping: topic {topic} is named for both {wanted[topic]} and {typename}")
    msgs = _messages(Path(path), wanted)
    for topic in (t.joint_states, t.valve_command, t.gripper_command) + ((t.imu,) if t.imu else ()):
        if not msgs[topic]:
            raise ConvertError(f"{path}: no messages on {topic} ({wanted[topic]})")
    rows_t = np.array([tm for tm, _m in msgs[t.joint_states]])
    if np.any(np.diff(rows_t) <= 0):
        raise ConvertError(f"{path}: {t.joint_states} receive times must increase")

    def joints(topic: str, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ts, q, qd = [], [], []
        for tm, m in msgs[topic]:
            got = mapping.to_slinger(names, list(m.name), m.position, m.velocity)
            if got is None:
                raise ConvertError(f"{path}: a JointState on {topic} lacks one of "
                                   f"{[mapping.joint(j).name for j in names]} or is not finite")
            ts.append(tm)
            q.append(got[0])
            qd.append(got[1] if len(m.velocity) else [np.nan] * len(names))
        return np.array(ts), np.array(q), np.array(qd)

    def matched(topic: str, values: np.ndarray, default) -> np.ndarray:
        times = np.array([tm for tm, _m in msgs[topic]])
        idx = _before(times, rows_t)
        out = values[np.clip(idx, 0, None)] if len(values) else np.zeros((len(rows_t),) + np.shape(default))
        out = np.array(out, dtype=float)
        out[idx < 0] = default
        return out

    _, q_act, qd_act = joints(t.joint_states, ACTIVE_JOINTS)
    q = np.zeros((len(rows_t), 6))
    qd = np.full((len(rows_t), 6), np.nan)
    q[:, :4], qd[:, :4] = q_act, qd_act
    if t.imu:
        imu = [m for _t, m in msgs[t.imu]]
        idx = np.clip(_before(np.array([tm for tm, _m in msgs[t.imu]]), rows_t), 0, None)
        qd_known = np.nan_to_num(qd_act)
        for i, k in enumerate(idx):
            o, w = imu[k].orientation, imu[k].angular_velocity
            try:
                q[i, 4:], qd[i, 4:] = passive_from_imu(q_act[i], qd_known[i], (o.x, o.y, o.z, o.w), (w.x, w.y, w.z))
            except ValueError as e:
                raise ConvertError(f"{path}: {t.imu}: {e}") from e
    else:
        ts, q_pas, qd_pas = joints(mapping.passive_topic, PASSIVE_JOINTS)
        if t.passive_joint_states:
            idx = np.clip(_before(ts, rows_t), 0, None)
            q_pas, qd_pas = q_pas[idx], qd_pas[idx]
        q[:, 4:], qd[:, 4:] = q_pas, qd_pas
    if len(rows_t) > 1:
        grad = np.gradient(q, rows_t, axis=0)
        qd = np.where(np.isnan(qd), grad, qd)
    else:
        qd = np.nan_to_num(qd)
    valves = []
    for _tm, m in msgs[t.valve_command]:
        u = mapping.valve_u(m.data)
        if u is None:
            raise ConvertError(f"{path}: {t.valve_command} has {len(m.data)} elements, the mapping needs {mapping.valve_array_size}")
        valves.append(u)
    u = np.clip(matched(t.valve_command, np.array(valves), [0.0] * 4), -1.0, 1.0)
    cmd = matched(t.gripper_command, np.array([float(m.data) for _t, m in msgs[t.gripper_command]]), 0.0) > 0.5
    opened = (matched(t.gripper_state, np.array([float(m.data) for _t, m in msgs[t.gripper_state]]), 0.0) > 0.5
              if t.gripper_state and msgs.get(t.gripper_state) else np.zeros(len(rows_t), bool))
    pay = None
    if t.payload and msgs.get(t.payload):
        pv = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z,
                        m.twist.twist.linear.x, m.twist.twist.linear.y, m.twist.twist.linear.z] for _t, m in msgs[t.payload]])
        pay = matched(t.payload, pv, [np.nan] * 6)
    for name, a in (("joints", q), ("rates", qd), ("valves", u)):
        if not np.all(np.isfinite(a)):
            raise ConvertError(f"{path}: non-finite {name}")
    t0 = rows_t[0]
    rows = []
    for i in range(len(rows_t)):
        pay_i = pay[i] if pay is not None and np.all(np.isfinite(pay[i])) else None
        rows.append({"t_s": float(rows_t[i] - t0), "q": q[i].tolist(), "qd": qd[i].tolist(), "qd_ref": [0.0] * 4, "u": u[i].tolist(),
                     "command_open": bool(cmd[i]), "open": bool(opened[i]), "phase": "swinging",
                     "pos_m": pay_i[:3].tolist() if pay_i is not None else None, "vel_mps": pay_i[3:].tolist() if pay_i is not None else None})
    return rows


def throw_id(path: Path) -> str:
    """A bag's throw id: the directory's name or the file's stem."""
    path = Path(path)
    return path.name if path.is_dir() else path.stem


def convert(inputs: list[Path], mapping_path: Path, impacts_csv: Path, out_dir: Path) -> Path:
    """Convert rosbag2 bags (one per throw) into a dataset directory; returns its index path.

    Raises:
        ConvertError: bad mapping, unreadable bags, missing topics or joints, a throw without a target.
    """
    mapping = load_mapping(mapping_path)
    targets = read_targets(impacts_csv)
    spec = RealLogSpec(open_flag=bool(mapping.topics.gripper_state), payload_channel=bool(mapping.topics.payload))
    out = []
    for path in inputs:
        tid = throw_id(path)
        if tid not in targets:
            raise ConvertError(f"{path}: throw {tid!r} has no row in {impacts_csv}")
        rows = convert_bag(Path(path), mapping)
        target, impact = targets[tid]
        out.append(({"throw_id": tid, "mode": mapping.mode, "target_m": target, "impact_m": impact, "impact_stamp_s": None,
                     "status": "landed"}, write_log(rows, [], spec, {"throw_id": tid, "source": str(path)})))
    log.info("converted %d rosbag2 throws with %s", len(out), mapping_path)
    return ds.write(out_dir, out, machine_id=mapping.machine_id, source={"converted_from": [str(p) for p in inputs], "format": "rosbag2"},
                    sensors=mapping.sensors)


__all__ = ["BagMapping", "convert", "convert_bag", "is_rosbag", "load_mapping", "throw_id"]
