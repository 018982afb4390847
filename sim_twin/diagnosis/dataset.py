"""Logged throws: a dataset directory of telemetry MCAPs plus measured impacts.

Layout (``format: slinger-throws/1``)::

    <dir>/index.json        {"format": "slinger-throws/1", "machine_id": "m1", "source": {...},
                             "sensors": {"impact_sigma_m": 0.05, ...}          (optional),
                             "throws": [{"throw_id": "...", "file": "throws/<id>.mcap",
                                         "mode": "2d", "target_m": [x, y, z],
                                         "impact_m": [x, y, 0] | null, "impact_stamp_s": t | null,
                                         "status": "landed", "policy_version": "..."}]}
    <dir>/throws/<id>.mcap  one throw's log (:mod:`sim_twin.diagnosis.logformat`: joint encoders,
                            gripper IMU, valve commands, release command; references, the
                            payload-free flag and payload tracking optional)
    <dir>/impacts.csv       optional: throw_id, impact_x_m, impact_y_m[, impact_stamp_s]

``sensors`` declares the sensor spec (1 sigma): ``impact_sigma_m`` (impact measurement),
``encoder_sigma_rad``, ``imu_angle_sigma_rad``, ``imu_rate_sigma_radps``; without it the
diagnosis measures the noise from the log (:mod:`sim_twin.diagnosis.noise`).

The measured impact is what the machine (or a camera) reports. :func:`generate` makes such a
dataset with the simulated machine under any reality profile (the runtime's ThrowExecutor and an
ONNX policy in the loop, as in sim_twin.evaluation.evaluate), optionally degraded like a real machine's log
(:mod:`sim_twin.diagnosis.reallog`); the server exports the throws it stored for one machine.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.telemetry import write_mcap
from sim_twin.diagnosis import logformat as lf

log = logging.getLogger(__name__)

FORMAT = "slinger-throws/1"
TICK_S = 0.01


class DatasetError(ValueError):
    """A dataset or one of its throws cannot be used (the message says which and why)."""


@dataclass
class LoggedThrow:
    """One landed throw as logged, from swing start to the last tick.

    Attributes:
        throw_id, mode: identity.
        target_m / impact_m: (3,) machine frame, m (impact measured).
        impact_t_s: measured impact time, s since swing start (None: not logged).
        t_s: (T,) s since swing start (0 at the first swinging row).
        q, qd: (T, 6) measured joint states; valve_u: (T, 4); qd_ref: (T, 4) or None (no
            runtime references: the replay feeds the logged valve commands).
        cmd_row: row of the release command; open_row: first row with the payload free (None
            if the log does not say).
        payload_t_s, payload_pos_m: payload samples (s since swing start, (P, 3)); P may be 0.
    """

    throw_id: str
    mode: str
    target_m: np.ndarray
    impact_m: np.ndarray
    impact_t_s: float | None
    t_s: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qd_ref: np.ndarray | None
    valve_u: np.ndarray
    cmd_row: int
    open_row: int | None
    payload_t_s: np.ndarray
    payload_pos_m: np.ndarray
    meta: dict = field(default_factory=dict)

    @property
    def distance_m(self) -> float:
        """Horizontal distance of the target from the turn axis, m."""
        return float(math.hypot(self.target_m[0], self.target_m[1]))

    @property
    def open_delay_s(self) -> float | None:
        return None if self.open_row is None else float(self.t_s[self.open_row] - self.t_s[self.cmd_row])


def from_log(a: dict, row: dict) -> LoggedThrow:
    """Build a LoggedThrow from :func:`logformat.arrays` and its index row (impact required).

    Raises:
        DatasetError: no rows after the swing start, no release command, or a misshaped impact.
    """
    tid = row.get("throw_id", "?")
    k0 = a["k0"]
    if len(a["t_s"]) - k0 < 10:
        raise DatasetError(f"throw {tid}: fewer than 10 rows after the swing start")
    cmd = np.flatnonzero(a["gripper_cmd"][k0:])
    if cmd.size == 0:
        raise DatasetError(f"throw {tid}: no release command in the log")
    impact = np.asarray(row["impact_m"], dtype=float)
    if impact.shape != (3,) or not np.all(np.isfinite(impact)):
        raise DatasetError(f"throw {tid}: impact_m must be 3 finite numbers, got {row['impact_m']!r}")
    opened = np.flatnonzero(a["gripper_open"][k0:]) if a["gripper_open"] is not None else np.zeros(0, dtype=int)
    t0 = float(a["t_s"][k0])
    keep = a["payload_t_s"] >= t0
    stamp = row.get("impact_stamp_s")
    return LoggedThrow(
        throw_id=str(tid),
        mode=str(row.get("mode", "2d")),
        target_m=np.asarray(row["target_m"], dtype=float),
        impact_m=impact,
        impact_t_s=None if stamp is None else float(stamp) - t0,
        t_s=a["t_s"][k0:] - t0,
        q=a["q"][k0:],
        qd=a["qd"][k0:],
        qd_ref=None if a["qd_ref"] is None else a["qd_ref"][k0:],
        valve_u=a["valve_u"][k0:],
        cmd_row=int(cmd[0]),
        open_row=int(opened[0]) if opened.size else None,
        payload_t_s=a["payload_t_s"][keep] - t0,
        payload_pos_m=a["payload_pos_m"][keep],
        meta={k: row[k] for k in ("policy_version", "status") if k in row},
    )


def load(directory: str | Path) -> tuple[list[LoggedThrow], dict]:
    """Read a dataset directory. Throws that did not land are skipped; landed throws without a
    measured impact are skipped with a warning (``index["skipped"]`` lists both with reasons).

    Returns:
        (usable throws in index order, the index dict).

    Raises:
        DatasetError: missing/invalid index or impacts.csv, unreadable or corrupt MCAP, a log
            without a required channel, or no usable throw at all.
    """
    directory = Path(directory)
    index_path = directory / "index.json"
    try:
        index = json.loads(index_path.read_text())
    except FileNotFoundError as e:
        raise DatasetError(f"{index_path} not found: a dataset is a directory with index.json and throws/*.mcap") from e
    except json.JSONDecodeError as e:
        raise DatasetError(f"{index_path} is not valid JSON: {e}") from e
    if index.get("format") != FORMAT or not isinstance(index.get("throws"), list):
        raise DatasetError(f"{index_path}: expected format {FORMAT!r} with a 'throws' list")
    csv_path = directory / "impacts.csv"
    try:
        impacts = lf.read_impacts_csv(csv_path) if csv_path.is_file() else {}
    except lf.LogError as e:
        raise DatasetError(str(e)) from e
    throws: list[LoggedThrow] = []
    skipped: list[dict] = []
    for row in index["throws"]:
        tid = row.get("throw_id", "?")
        row = {**row, **impacts.get(str(tid), {})}
        if row.get("status", "landed") != "landed":
            log.info("throw %s: status %s, skipped", tid, row.get("status"))
            skipped.append({"throw_id": tid, "reason": f"status {row.get('status')}"})
            continue
        if row.get("impact_m") is None:
            log.warning("throw %s: no measured impact, skipped", tid)
            skipped.append({"throw_id": tid, "reason": "no measured impact"})
            continue
        path = directory / str(row.get("file", ""))
        try:
            arr = lf.arrays(lf.read_messages(path))
        except FileNotFoundError as e:
            raise DatasetError(f"throw {tid}: telemetry file {path} not found") from e
        except lf.LogError as e:
            raise DatasetError(f"throw {tid}: telemetry {path}: {e}") from e
        throws.append(from_log(arr, row))
    index["skipped"] = skipped
    if not throws:
        raise DatasetError(f"{directory}: no landed throws with a measured impact to diagnose")
    log.info("dataset %s: %d usable throws, %d skipped", directory, len(throws), len(skipped))
    return throws, index


def write(directory: str | Path, rows: list[tuple[dict, bytes]], machine_id: str, source: dict | None = None, sensors: dict | None = None) -> Path:
    """Write a dataset: ``rows`` are (index row without 'file', MCAP bytes); ``sensors`` the
    declared sensor spec (optional). Returns the index path."""
    directory = Path(directory)
    (directory / "throws").mkdir(parents=True, exist_ok=True)
    out = []
    for row, mcap in rows:
        rel = f"throws/{row['throw_id']}.mcap"
        (directory / rel).write_bytes(mcap)
        out.append({**row, "file": rel})
    index = {"format": FORMAT, "machine_id": machine_id, "source": source or {}, "throws": out}
    if sensors:
        index["sensors"] = sensors
    path = directory / "index.json"
    path.write_text(json.dumps(index, indent=1) + "\n")
    return path


def _throw_worker(args) -> tuple[dict, bytes] | None:
    policy_path, profile_dict, seed, distance_m, mode, spec = args
    from runtime.executor import ThrowExecutor
    from runtime.policy import PolicyRunner
    from runtime.protocol.messages import ThrowRequest
    from sim_twin.evaluation.evaluate import target_on_axis
    from sim_twin.twin.profile import RealityProfile
    from sim_twin.twin.simulated_machine import SimulatedMachine
    from sim_twin.twin.twin_machine import TwinMachine, run_throw

    policy = _policy_cache.get(policy_path) or _policy_cache.setdefault(policy_path, PolicyRunner.load(policy_path))
    sim = SimulatedMachine(RealityProfile.from_dict(profile_dict), seed=seed)
    sim.reset(cabin_turn=0.0 if mode == "2d" else None)
    twin = TwinMachine(sim, "sim")
    req = ThrowRequest(throw_id=f"t{seed:06d}", machine_id="sim", mode=mode, target_m=target_on_axis(mode, distance_m))
    outcome, _ = run_throw(twin, ThrowExecutor({mode: policy}), req)
    if outcome is None:
        return None
    row = {
        "throw_id": req.throw_id, "mode": mode, "target_m": list(req.target_m), "status": outcome.status,
        "policy_version": outcome.policy_version, "seed": seed,
        "impact_m": None if outcome.impact_m is None else outcome.impact_m.tolist(),
        "impact_stamp_s": None if outcome.impact is None else outcome.impact.impact_stamp_s,
        "release_stamp_s": outcome.release_stamp_s, "opening_stamp_s": outcome.opening_stamp_s,
    }
    meta = {"throw_id": req.throw_id, "mode": mode, "status": outcome.status, "policy_version": outcome.policy_version, "target_m": json.dumps(list(req.target_m))}
    if spec is None:
        return row, write_mcap(outcome.telemetry, meta)
    from sim_twin.diagnosis import reallog

    row = reallog.degrade_row(row, spec, np.random.default_rng([seed, 7]))
    row.pop("opening_stamp_s")
    return row, reallog.write_log(outcome.telemetry.rows, outcome.telemetry.events, spec, meta)


_policy_cache: dict = {}


DISTANCES_M = {"2d": (7.5, 8.0, 8.5, 9.0, 9.5), "3d": (7.0, 7.5, 8.0, 8.5, 9.0)}
"""Target distances per mode (the policies' evaluated range, docs/training.md)."""


def generate(directory, profile_dict: dict, throws: int, policy_path: str | Path, distances_m=None, seed: int = 0, mode: str = "2d",
             workers: int = 1, real_log=None, per_throw: list[dict] | None = None) -> Path:
    """Throw ``throws`` times with the simulated machine under ``profile_dict`` (targets cycle
    through ``distances_m``, default DISTANCES_M[mode]; seed ``seed * 10007 + i`` for throw i)
    and write a dataset.

    Args:
        mode: "2d" or "3d" (the policy must be for that mode).
        real_log: a :class:`sim_twin.diagnosis.reallog.RealLogSpec` to make logs like a real
            machine's (sensor noise in the loop, channels dropped, impact noise, missing
            impacts), or None for the runtime's full telemetry.
        per_throw: one profile dict per throw (in throw order; overrides ``profile_dict``): a
            machine that changes during the log (the benchmark's ``drifting`` kind).

    Returns:
        the index path. Throws the policy fails are kept in the index with their status.

    Raises:
        ValueError: unknown mode, or a per_throw list of another length.
    """
    if mode not in DISTANCES_M:
        raise ValueError(f"mode must be one of {sorted(DISTANCES_M)}, got {mode!r}")
    distances_m = distances_m or DISTANCES_M[mode]
    if per_throw is not None and len(per_throw) != throws:
        raise ValueError(f"per_throw must hold one profile per throw ({throws}), got {len(per_throw)}")
    profiles = list(per_throw) if per_throw is not None else [profile_dict] * throws
    if real_log is not None:
        profiles = [{**p, "effects": list(p.get("effects", [])) + [real_log.noise_effect()]} for p in profiles]
    jobs = [(str(policy_path), profiles[i], seed * 10007 + i, float(distances_m[i % len(distances_m)]), mode, real_log) for i in range(throws)]
    if workers > 1:
        from sim_twin.twin.pools import process_pool

        with process_pool(workers) as pool:
            results = list(pool.map(_throw_worker, jobs, chunksize=max(1, throws // (4 * workers))))
    else:
        results = [_throw_worker(j) for j in jobs]
    rows = [r for r in results if r is not None]
    log.info("generated %d throws (%d landed) under profile %s", len(rows), sum(r[0]["status"] == "landed" for r in rows), profile_dict.get("name"))
    sensors = real_log.sensors() if real_log is not None and real_log.declare else None
    return write(directory, rows, machine_id="sim", sensors=sensors,
                 source={"generator": "sim_twin.diagnosis.dataset.generate", "seed": seed, "policy": str(policy_path), "mode": mode,
                         "real_log": None if real_log is None else {k: getattr(real_log, k) for k in real_log.__dataclass_fields__}})
