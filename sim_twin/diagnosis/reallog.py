"""Logs like a real machine's, made from the simulated machine's throws (benchmark, tests).

A real machine has encoders and a gripper IMU with noise, a release command but usually no
"payload free" sensor and no payload tracking, and an impact measurement with its own error
that is sometimes missing. :class:`RealLogSpec` says which of that to imitate:

* :class:`SensorNoise` (a user-style effect, ``sim_twin.diagnosis.reallog:SensorNoise``) adds
  white noise to every measured joint channel, so the runtime's controller and the policy see
  the noisy values (it goes into the generating profile);
* :func:`write_log` writes the throw's MCAP in the :mod:`logformat` format without the dropped
  channels; :func:`degrade_row` adds impact noise and drops some impacts.
"""

from __future__ import annotations

import io
import json
from dataclasses import asdict, dataclass

import numpy as np
from mcap.writer import CompressionType, Writer

from sim_twin.twin.effects import Effect, Param

_ARR = {"type": "array", "items": {"type": "number"}}


@dataclass(frozen=True)
class RealLogSpec:
    """How to degrade generated logs (1-sigma noise values; the declared sensor spec).

    Attributes:
        encoder_sigma_rad: active-joint position noise (rad, m for the telescope).
        encoder_rate_sigma: active-joint velocity noise (rad/s, m/s).
        imu_angle_sigma_rad / imu_rate_sigma_radps: gripper IMU noise (pitch, roll).
        impact_sigma_m: impact measurement noise per horizontal axis.
        payload_channel / open_flag: keep /payload tracking / the payload-free flag.
        missing_impact_fraction: share of landed throws whose impact is not measured.
        declare: write the spec into index.json "sensors" (a site that knows its sensors).
    """

    encoder_sigma_rad: float = 0.002
    encoder_rate_sigma: float = 0.01
    imu_angle_sigma_rad: float = 0.005
    imu_rate_sigma_radps: float = 0.03
    impact_sigma_m: float = 0.05
    payload_channel: bool = False
    open_flag: bool = False
    missing_impact_fraction: float = 0.07
    declare: bool = True

    def noise_effect(self) -> dict:
        """The generating profile's entry for :class:`SensorNoise`."""
        return {"effect": f"{__name__}:SensorNoise", "params": {
            "encoder_sigma_rad": self.encoder_sigma_rad, "encoder_rate_sigma": self.encoder_rate_sigma,
            "imu_angle_sigma_rad": self.imu_angle_sigma_rad, "imu_rate_sigma_radps": self.imu_rate_sigma_radps}}

    def sensors(self) -> dict:
        """The declared sensor spec (index.json "sensors")."""
        return {k: v for k, v in asdict(self).items() if k.endswith(("_rad", "_sigma", "_radps", "_m"))}


class SensorNoise(Effect):
    """White Gaussian noise on every measured joint channel (encoders and gripper IMU)."""

    name = "sensor_noise"
    summary = "white noise on encoders and gripper IMU"
    stage = "measurement"
    params = (
        Param("encoder_sigma_rad", "rad", 0.0, 0.0, 0.05, "active position noise", "CHOSEN", stochastic=True),
        Param("encoder_rate_sigma", "rad/s", 0.0, 0.0, 0.5, "active velocity noise", "CHOSEN", stochastic=True),
        Param("imu_angle_sigma_rad", "rad", 0.0, 0.0, 0.05, "IMU angle noise", "CHOSEN", stochastic=True),
        Param("imu_rate_sigma_radps", "rad/s", 0.0, 0.0, 0.5, "IMU rate noise", "CHOSEN", stochastic=True),
    )

    def measure(self, hist_q, hist_qd, dt_s, rng):
        q, qd = np.array(hist_q[0], dtype=float, copy=True), np.array(hist_qd[0], dtype=float, copy=True)
        if rng is not None:
            sq = np.array([self.encoder_sigma_rad] * 4 + [self.imu_angle_sigma_rad] * 2)
            sqd = np.array([self.encoder_rate_sigma] * 4 + [self.imu_rate_sigma_radps] * 2)
            q = q + rng.normal(0.0, 1.0, q.shape) * sq
            qd = qd + rng.normal(0.0, 1.0, qd.shape) * sqd
        return q, qd


def write_log(rows: list[dict], events: list[dict], spec: RealLogSpec, metadata: dict[str, str]) -> bytes:
    """MCAP bytes of one throw in the logformat topics, without the channels ``spec`` drops.

    Args:
        rows: runtime.telemetry.TelemetryRecorder rows (t_s, q, qd, qd_ref, u, command_open,
            open, phase, pos_m, vel_mps).
    """
    buf = io.BytesIO()
    w = Writer(buf, compression=CompressionType.ZSTD)
    w.start(profile="", library="slinger-reallog")
    props: dict[str, dict[str, object]] = {
        "/joint_states": {"t_s": {"type": "number"}, "q": _ARR, "qd": _ARR},
        "/references": {"t_s": {"type": "number"}, "phase": {"type": "string"}, "qd_ref": _ARR},
        "/valve_commands": {"t_s": {"type": "number"}, "u": _ARR},
        "/gripper": {"t_s": {"type": "number"}, "command_open": {"type": "boolean"}, **({"open": {"type": "boolean"}} if spec.open_flag else {})},
        "/events": {"t_s": {"type": "number"}, "phase": {"type": "string"}, "detail": {"type": ["string", "null"]}},
    }
    if spec.payload_channel:
        props["/payload"] = {"t_s": {"type": "number"}, "pos_m": _ARR, "vel_mps": _ARR}
    ch = {}
    for topic, p in props.items():
        sid = w.register_schema(name=f"slinger{topic.replace('/', '.')}", encoding="jsonschema",
                                data=json.dumps({"type": "object", "properties": p, "required": list(p)}).encode())
        ch[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
    seq = 0

    def put(topic, t, msg):
        nonlocal seq
        ns = max(0, int(round(t * 1e9)))
        w.add_message(ch[topic], log_time=ns, data=json.dumps(msg).encode(), publish_time=ns, sequence=seq)
        seq += 1

    for r in rows:
        t = r["t_s"]
        put("/joint_states", t, {"t_s": t, "q": r["q"], "qd": r["qd"]})
        put("/references", t, {"t_s": t, "phase": r["phase"], "qd_ref": r["qd_ref"]})
        put("/valve_commands", t, {"t_s": t, "u": r["u"]})
        put("/gripper", t, {"t_s": t, "command_open": r["command_open"], **({"open": r["open"]} if spec.open_flag else {})})
        if spec.payload_channel and r["pos_m"] is not None:
            put("/payload", t, {"t_s": t, "pos_m": r["pos_m"], "vel_mps": r["vel_mps"]})
    for e in events:
        put("/events", e["t_s"], e)
    w.add_metadata("throw", {k: str(v) for k, v in metadata.items()})
    w.finish()
    return buf.getvalue()


def degrade_row(row: dict, spec: RealLogSpec, rng: np.random.Generator) -> dict:
    """Index row with the impact measured with noise, or missing (None) for a share of throws."""
    row = dict(row)
    if row.get("impact_m") is not None:
        if rng.uniform() < spec.missing_impact_fraction:
            row["impact_m"] = None
        else:
            imp = np.asarray(row["impact_m"], dtype=float)
            imp[:2] += rng.normal(0.0, spec.impact_sigma_m, 2)
            row["impact_m"] = imp.tolist()
    return row
