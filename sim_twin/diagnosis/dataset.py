"""Logged throws: a dataset directory of telemetry MCAPs plus measured impacts.

Layout (``format: slinger-throws/1``)::

    <dir>/index.json        {"format": "slinger-throws/1", "machine_id": "m1", "source": {...},
                             "throws": [{"throw_id": "...", "file": "throws/<id>.mcap",
                                         "mode": "2d", "target_m": [x, y, z],
                                         "impact_m": [x, y, 0] | null, "impact_stamp_s": t | null,
                                         "status": "landed", "policy_version": "..."}]}
    <dir>/throws/<id>.mcap  runtime.telemetry MCAP (100 Hz joint states, references, valve
                            commands, gripper command / open, payload state, phase events)

The measured impact is what the machine (or a camera) reports; the MCAP is what the runtime
recorded. :func:`generate` makes such a dataset with the simulated machine under any reality
profile (the runtime's ThrowExecutor and an ONNX policy in the loop, as in sim_twin.evaluate);
:func:`export_server_throws` writes the throws a server stored for one machine.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.telemetry import read_telemetry, write_mcap

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
        impact_t_s: measured impact time, s since swing start.
        t_s: (T,) s since swing start (0 at the first swinging row).
        q, qd: (T, 6) measured joint states; qd_ref, valve_u: (T, 4).
        cmd_row: row of the release command; open_row: first row with the payload free (None
            if the log does not say).
        payload_t_s, payload_pos_m: payload samples (s since swing start, (P, 3)).
    """

    throw_id: str
    mode: str
    target_m: np.ndarray
    impact_m: np.ndarray
    impact_t_s: float
    t_s: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qd_ref: np.ndarray
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


def from_telemetry(tel: dict, row: dict) -> LoggedThrow:
    """Build a LoggedThrow from ``runtime.telemetry.read_telemetry`` arrays and its index row.

    Raises:
        DatasetError: no swinging rows, no release command, or no measured impact.
    """
    tid = row.get("throw_id", "?")
    if tel["t_s"].size == 0:
        raise DatasetError(f"throw {tid}: telemetry has no joint states")
    if row.get("impact_m") is None or row.get("impact_stamp_s") is None:
        raise DatasetError(f"throw {tid}: no measured impact (impact_m and impact_stamp_s are required)")
    phase = tel["phase"]
    if len(phase) != len(tel["t_s"]):
        raise DatasetError(f"throw {tid}: {len(phase)} reference rows for {len(tel['t_s'])} joint-state rows")
    swing = np.flatnonzero(phase != "preparing")
    if swing.size == 0:
        raise DatasetError(f"throw {tid}: telemetry has no swinging phase")
    k0 = int(swing[0])
    cmd = np.flatnonzero(tel["gripper_cmd"][k0:])
    if cmd.size == 0:
        raise DatasetError(f"throw {tid}: no release command in the telemetry")
    opened = np.flatnonzero(tel["gripper_open"][k0:])
    t0 = float(tel["t_s"][k0])
    in_flight = tel["payload_t_s"] >= t0
    impact = np.asarray(row["impact_m"], dtype=float)
    arrays = [tel[k][k0:] for k in ("q", "qd", "qd_ref", "valve_u")]
    if not all(np.all(np.isfinite(a)) for a in arrays) or impact.shape != (3,) or not np.all(np.isfinite(impact)):
        raise DatasetError(f"throw {tid}: non-finite or misshaped values")
    return LoggedThrow(
        throw_id=str(tid),
        mode=str(row.get("mode", "2d")),
        target_m=np.asarray(row["target_m"], dtype=float),
        impact_m=impact,
        impact_t_s=float(row["impact_stamp_s"]) - t0,
        t_s=tel["t_s"][k0:] - t0,
        q=arrays[0],
        qd=arrays[1],
        qd_ref=arrays[2],
        valve_u=arrays[3],
        cmd_row=int(cmd[0]),
        open_row=int(opened[0]) if opened.size else None,
        payload_t_s=tel["payload_t_s"][in_flight] - t0,
        payload_pos_m=tel["payload_pos_m"][in_flight],
        meta={k: row[k] for k in ("policy_version", "status") if k in row},
    )


def load(directory: str | Path) -> tuple[list[LoggedThrow], dict]:
    """Read a dataset directory; throws that did not land are skipped (logged).

    Returns:
        (landed throws in index order, the index dict).

    Raises:
        DatasetError: missing/invalid index, unreadable or corrupt MCAP, a landed throw without
            a measured impact, or no landed throw at all.
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
    throws: list[LoggedThrow] = []
    for row in index["throws"]:
        tid = row.get("throw_id", "?")
        if row.get("status", "landed") != "landed":
            log.info("throw %s: status %s, skipped", tid, row.get("status"))
            continue
        path = directory / str(row.get("file", ""))
        try:
            tel = read_telemetry(path)
        except FileNotFoundError as e:
            raise DatasetError(f"throw {tid}: telemetry file {path} not found") from e
        except Exception as e:  # mcap raises several exception types for corrupt files
            raise DatasetError(f"throw {tid}: telemetry {path} is not a readable MCAP file ({type(e).__name__}: {e})") from e
        throws.append(from_telemetry(tel, row))
    if not throws:
        raise DatasetError(f"{directory}: no landed throws to diagnose")
    log.info("dataset %s: %d landed throws", directory, len(throws))
    return throws, index


def write(directory: str | Path, rows: list[tuple[dict, bytes]], machine_id: str, source: dict | None = None) -> Path:
    """Write a dataset: ``rows`` are (index row without 'file', MCAP bytes). Returns the index path."""
    directory = Path(directory)
    (directory / "throws").mkdir(parents=True, exist_ok=True)
    out = []
    for row, mcap in rows:
        rel = f"throws/{row['throw_id']}.mcap"
        (directory / rel).write_bytes(mcap)
        out.append({**row, "file": rel})
    index = {"format": FORMAT, "machine_id": machine_id, "source": source or {}, "throws": out}
    path = directory / "index.json"
    path.write_text(json.dumps(index, indent=1) + "\n")
    return path


def _throw_worker(args) -> tuple[dict, bytes] | None:
    policy_path, profile_dict, seed, distance_m, mode = args
    from runtime.executor import ThrowExecutor
    from runtime.policy import PolicyRunner
    from runtime.protocol.messages import ThrowRequest
    from sim_twin.evaluate import target_on_axis
    from sim_twin.plant import TwinMachine, run_throw
    from sim_twin.profile import RealityProfile
    from sim_twin.simulated_machine import SimulatedMachine

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
    return row, write_mcap(outcome.telemetry, meta)


_policy_cache: dict = {}


def generate(directory, profile_dict: dict, throws: int, policy_path: str | Path, distances_m=(7.5, 8.0, 8.5, 9.0, 9.5), seed: int = 0, mode: str = "2d", workers: int = 1) -> Path:
    """Throw ``throws`` times with the simulated machine under ``profile_dict`` (targets cycle
    through ``distances_m``; seed ``seed * 10007 + i`` for throw i) and write a dataset.

    Returns:
        the index path. Throws the policy fails are kept in the index with their status.
    """
    jobs = [(str(policy_path), profile_dict, seed * 10007 + i, float(distances_m[i % len(distances_m)]), mode) for i in range(throws)]
    if workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=workers) as pool:
            results = list(pool.map(_throw_worker, jobs, chunksize=max(1, throws // (4 * workers))))
    else:
        results = [_throw_worker(j) for j in jobs]
    rows = [r for r in results if r is not None]
    log.info("generated %d throws (%d landed) under profile %s", len(rows), sum(r[0]["status"] == "landed" for r in rows), profile_dict.get("name"))
    return write(directory, rows, machine_id="sim", source={"generator": "sim_twin.diagnosis.dataset.generate", "seed": seed, "policy": str(policy_path)})
