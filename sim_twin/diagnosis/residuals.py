"""Residuals between logged and replayed throws, per channel and per phase.

Residual = logged - replayed. Channels, each with a scale (the size of a residual that matters)
and a group used for reporting:

=====================  ========  ======  =========================================================
channel                group     scale   samples
=====================  ========  ======  =========================================================
q.<active joint>       active    0.005   measured position, every logged row (rad or m)
qd.<active joint>      active    0.02    measured velocity (rad/s or m/s)
q.gripper_pitch/roll   passive   0.02    IMU angle (rad)
qd.gripper_pitch/roll  passive   0.10    IMU rate (rad/s)
release.delay          release   0.01    opening delay, logged - model expectation (s); J uses the
                                         mean over throws (the jitter is not reproducible per throw)
payload.held           payload   0.02    payload position while held, x/y/z (m)
payload.flight         payload   0.05    payload position in flight, released at the logged
                                         opening (m)
impact.downrange       impact    0.05    impact error along the target line (m)
impact.crossrange      impact    0.05    impact error across it, left positive (m)
=====================  ========  ======  =========================================================

Phases: swing (swing start to release command), release (command to payload free), flight
(payload free to impact). ``J = sum_channel mean(residual^2) / scale^2`` (release.delay: the
squared mean); :func:`features` returns the vector f with ``|f|^2 = J`` that the fit minimises.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from runtime.machine import JOINT_NAMES
from runtime.throw_geometry import impact_errors
from sim_twin.diagnosis.dataset import TICK_S, LoggedThrow
from sim_twin.diagnosis.replay import Replay

PHASES = ("swing", "release", "flight")
GROUPS = ("active", "passive", "release", "payload", "impact")


@dataclass(frozen=True)
class Channel:
    name: str
    group: str
    unit: str
    scale: float


def _channels() -> tuple[Channel, ...]:
    out = []
    for j, name in enumerate(JOINT_NAMES):
        active = j < 4
        lin = name == "telescope"
        out.append(Channel(f"q.{name}", "active" if active else "passive", "m" if lin else "rad", 0.005 if active else 0.02))
        out.append(Channel(f"qd.{name}", "active" if active else "passive", "m/s" if lin else "rad/s", 0.02 if active else 0.10))
    out += [
        Channel("release.delay", "release", "s", 0.01),
        Channel("payload.held", "payload", "m", 0.02),
        Channel("payload.flight", "payload", "m", 0.05),
        Channel("impact.downrange", "impact", "m", 0.05),
        Channel("impact.crossrange", "impact", "m", 0.05),
    ]
    return tuple(out)


CHANNELS = _channels()
CHANNEL_BY_NAME = {c.name: c for c in CHANNELS}
def expected_logged_delay(mean_s: float, std_s: float) -> float:
    """Expected logged opening delay (s) for a delay D = max(0, N(mean, std)): the payload is
    free at the first 10 ms row at or after command + D, so the logged delay is
    dt * ceil(D / dt) and its expectation dt * sum_j P(D > j dt) (smooth in mean and std; std is
    floored at 1 ms so that the fit sees a slope)."""
    std = max(float(std_s), 1e-3)
    j = np.arange(0, int(np.ceil((mean_s + 8 * std) / TICK_S)) + 1)
    z = (j * TICK_S - mean_s) / (std * np.sqrt(2.0))
    return float(TICK_S * np.sum(0.5 * np.vectorize(math.erfc)(z)))


def throw_residuals(th: LoggedThrow, rep: Replay, predicted: bool = False) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Residual samples of one throw: channel -> (values (S,), phase index (S,) into PHASES).

    Args:
        predicted: flight/impact released where the model's delay puts it (what the twin would
            predict) instead of at the logged opening.
    """
    L = len(th.t_s)
    open_row = th.open_row if th.open_row is not None else rep.cond["open_row"]
    rows = np.arange(L)
    ph_rows = np.where(rows < th.cmd_row, 0, np.where(rows < open_row, 1, 2))
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    dq, dqd = th.q - rep.meas_q[:L], th.qd - rep.meas_qd[:L]
    for j, name in enumerate(JOINT_NAMES):
        out[f"q.{name}"] = (dq[:, j], ph_rows)
        out[f"qd.{name}"] = (dqd[:, j], ph_rows)
    if th.open_delay_s is not None:
        d = th.open_delay_s - expected_logged_delay(rep.delay_mean_s, rep.delay_std_s)
        out["release.delay"] = (np.array([d]), np.array([1]))
    else:
        out["release.delay"] = (np.zeros(0), np.zeros(0, dtype=int))
    t_open = open_row * TICK_S
    held = th.payload_t_s < t_open - 1e-9
    n_held = min(int(held.sum()), len(rep.held_pos_m))
    hp = (th.payload_pos_m[held][:n_held] - rep.held_pos_m[:n_held]).reshape(-1)
    ph_held = np.repeat(np.where(np.arange(n_held) < th.cmd_row, 0, 1), 3)
    out["payload.held"] = (hp, ph_held)
    fl = rep.pred if predicted else rep.cond
    mask = (th.payload_t_s >= t_open - 1e-9) & (th.payload_t_s <= th.impact_t_s)
    fp = (th.payload_pos_m[mask] - fl["pos_m"][mask]).reshape(-1)
    out["payload.flight"] = (fp, np.full(fp.size, 2))
    down_log, cross_log = impact_errors(th.target_m, th.impact_m)
    down_rep, cross_rep = impact_errors(th.target_m, fl["impact_m"])
    out["impact.downrange"] = (np.array([down_log - down_rep]), np.array([2]))
    out["impact.crossrange"] = (np.array([cross_log - cross_rep]), np.array([2]))
    return out


def features(throws: list[LoggedThrow], reps: list[Replay], stride: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The fit's residual vector over a set of throws.

    Returns:
        (f (m,), throw index (m,), -1 for dataset-level features): ``|f|^2 = J``; trajectory
        channels subsampled by ``stride``.
    """
    per = [throw_residuals(th, r) for th, r in zip(throws, reps)]
    counts = {c.name: 0 for c in CHANNELS}
    for res in per:
        for c in CHANNELS:
            counts[c.name] += len(res[c.name][0][::stride]) if c.group in ("active", "passive") else len(res[c.name][0])
    parts, owner = [], []
    for n, res in enumerate(per):
        for c in CHANNELS:
            v = res[c.name][0]
            if c.name == "release.delay":
                continue
            if c.group in ("active", "passive"):
                v = v[::stride]
            if not counts[c.name] or not v.size:
                continue
            parts.append(v / (c.scale * np.sqrt(counts[c.name])))
            owner.append(np.full(v.size, n))
    delays = [res["release.delay"][0] for res in per if res["release.delay"][0].size]
    if delays:
        parts.append(np.array([np.mean(np.concatenate(delays)) / CHANNEL_BY_NAME["release.delay"].scale]))
        owner.append(np.array([-1]))
    return np.concatenate(parts), np.concatenate(owner)


def gap(f: np.ndarray) -> float:
    """J from a feature vector."""
    return float(np.sum(f * f))


def decompose(throws: list[LoggedThrow], reps: list[Replay], predicted: bool = False) -> dict:
    """Per-channel and per-phase summary over a set of throws.

    Returns:
        {"channels": {name: {"rms", "unit", "scale", "share", "by_phase": {phase: rms}}},
         "phases": {phase: share of J}, "groups": {group: share}, "J": J,
         "impact": {"rms_m", "mean_downrange_m", "mean_crossrange_m"}}
        where "share" is the fraction of J the channel (phase, group) carries.
    """
    per = [throw_residuals(th, r, predicted) for th, r in zip(throws, reps)]
    chans, contrib, phase_j = {}, {}, np.zeros(len(PHASES))
    for c in CHANNELS:
        v = np.concatenate([res[c.name][0] for res in per]) if per else np.zeros(0)
        ph = np.concatenate([res[c.name][1] for res in per]) if per else np.zeros(0, dtype=int)
        if not v.size:
            continue
        ms = float(np.mean(v * v))
        j = (float(np.mean(v)) ** 2 if c.name == "release.delay" else ms) / c.scale**2
        contrib[c.name] = j
        for k in range(len(PHASES)):
            sel = ph == k
            if sel.any():
                phase_j[k] += j * float(np.sum(v[sel] ** 2)) / max(float(np.sum(v * v)), 1e-300)
        chans[c.name] = {
            "rms": float(np.sqrt(ms)), "unit": c.unit, "scale": c.scale, "group": c.group,
            "by_phase": {PHASES[k]: float(np.sqrt(np.mean(v[ph == k] ** 2))) for k in range(len(PHASES)) if np.any(ph == k)},
        }
    total = sum(contrib.values())
    for name, j in contrib.items():
        chans[name]["share"] = j / total if total > 0 else 0.0
    groups = {g: sum(j for n, j in contrib.items() if CHANNEL_BY_NAME[n].group == g) / total if total > 0 else 0.0 for g in GROUPS}
    down = np.array([res["impact.downrange"][0][0] for res in per])
    cross = np.array([res["impact.crossrange"][0][0] for res in per])
    return {
        "J": total,
        "channels": chans,
        "groups": groups,
        "phases": {PHASES[k]: float(phase_j[k] / total) if total > 0 else 0.0 for k in range(len(PHASES))},
        "impact": {"rms_m": float(np.sqrt(np.mean(down**2 + cross**2))), "mean_downrange_m": float(down.mean()), "mean_crossrange_m": float(cross.mean())},
    }


def spreads(throws: list[LoggedThrow], reps: list[Replay]) -> dict:
    """Spread statistics for stochastic parameters (Effect.estimate_spread): std of the logged
    opening delays, and std of first differences of the passive residual (white noise)."""
    delays = np.array([th.open_delay_s for th in throws if th.open_delay_s is not None])
    dq = np.concatenate([np.diff(th.q[:, 4:6] - r.meas_q[: len(th.t_s), 4:6], axis=0).ravel() for th, r in zip(throws, reps)])
    dqd = np.concatenate([np.diff(th.qd[:, 4:6] - r.meas_qd[: len(th.t_s), 4:6], axis=0).ravel() for th, r in zip(throws, reps)])
    return {
        "release_delay_s": float(np.std(delays, ddof=1)) if delays.size > 1 else None,
        "passive_q_hf_rad": float(np.std(dq)) if dq.size else None,
        "passive_qd_hf_radps": float(np.std(dqd)) if dqd.size else None,
        "tick_s": TICK_S,
    }
