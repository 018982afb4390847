"""Throw preview in the CPU digital twin: what the active policy would do from the machine's
current joint state, and how far the impact scatters.

:func:`preview_throw` runs runtime.executor.ThrowExecutor (the runtime's own observation builder,
ONNX policy, controller and state machine) on a :class:`SimulatedMachine` set to the given joint
state, WITHOUT a simulated reset: the states are handed to the executor as those of hardware, so
it neither requests a SimReset nor waits for one (it still waits for the passive joints to be
still, as on the machine). The nominal rollout opens the gripper after the profile's MEAN release
delay.

Monte Carlo over the release-delay jitter, cheaply and exactly: the gripper's motion does not
depend on when the payload leaves it (the twin does not model the payload's mass on the arm), so
the swing is run once while the gripper-centre state is recorded every 10 ms; for each sampled
delay d the payload is free at the first physics step that ends at or after ``release + d`` (as
in SimulatedMachine.step) and flies ballistically from the recorded state there. 200 rollouts
cost a few milliseconds on top of the one swing.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from runtime.executor import ExecutorConfig, ThrowExecutor
from runtime.machine import ACTIVE_JOINTS, clearance_violations, forward_kinematics
from runtime.observation import PHYSICS_PERIOD_S
from runtime.protocol.messages import MachineState, ThrowRequest
from runtime.throw_geometry import impact_errors
from sim_twin.model import PAYLOAD_RADIUS_M
from sim_twin.physics import ballistic_impact_time, ballistic_position
from sim_twin.plant import TwinMachine
from sim_twin.profile import RealityProfile
from sim_twin.simulated_machine import SimulatedMachine

DELAY_SIGMAS = 4.0
"""The swing is recorded up to mean + DELAY_SIGMAS sigma of the release delay after release."""
PATH_POINTS = 120


@dataclass
class PreviewRequest:
    """What to preview.

    Attributes:
        mode: "2d" or "3d".
        target_m: (3,) target, machine frame, m.
        q / qd: (6,) current joint positions / velocities of the machine.
        rollouts: Monte Carlo rollouts for the impact ellipse (0 or 1: the nominal one only).
        seed: seed of the sampled release delays.
        clearance_radius_m: the swing must stay within this distance of the turn axis.
    """

    mode: str
    target_m: list[float]
    q: list[float]
    qd: list[float]
    rollouts: int = 200
    seed: int = 0
    clearance_radius_m: float = 12.0


def _flight(p0: np.ndarray, v0: np.ndarray) -> tuple[np.ndarray, float]:
    """Impact point (z = 0) and flight time of a payload freed at p0 with v0 (as the twin)."""
    t = float(ballistic_impact_time(np, p0, v0, PAYLOAD_RADIUS_M))
    hit = ballistic_position(np, p0, v0, t)
    hit[2] = 0.0
    return hit, t


def _downsample(points: np.ndarray, n: int = PATH_POINTS) -> list[list[float]]:
    if len(points) == 0:
        return []
    idx = np.unique(np.linspace(0, len(points) - 1, min(n, len(points))).astype(int))
    return np.round(points[idx], 4).tolist()


def _ellipse(points_xy: np.ndarray, n: int = 64) -> dict | None:
    """1 sigma ellipse of 2D points: centre, semi-axes, angle of the major axis, outline."""
    if len(points_xy) < 3:
        return None
    mean = points_xy.mean(axis=0)
    cov = np.cov(points_xy.T)
    vals, vecs = np.linalg.eigh(cov)
    vals = np.clip(vals, 0.0, None)
    a, b = math.sqrt(vals[1]), math.sqrt(vals[0])
    major = vecs[:, 1]
    ang = np.linspace(0, 2 * math.pi, n + 1)
    outline = mean + np.outer(a * np.cos(ang), major) + np.outer(b * np.sin(ang), vecs[:, 0])
    return {"center_m": mean.tolist(), "semi_major_m": a, "semi_minor_m": b,
            "angle_rad": math.atan2(major[1], major[0]), "cov": cov.tolist(),
            "outline_m": np.round(outline, 4).tolist()}


def preview_throw(policy, req: PreviewRequest, profile: RealityProfile | None = None) -> dict:
    """Preview one throw; returns a JSON-ready summary (see the keys below).

    Args:
        policy: a loaded runtime.policy.PolicyRunner of ``req.mode``.
        req: the request and the machine's current state.
        profile: the twin's reality profile (default nominal).

    Returns:
        ``status`` ("ok" or "failed"), ``reason``; and when ok: ``impact_m``, ``downrange_error_m``,
        ``crossrange_error_m``, ``release_pos_m`` / ``release_vel_mps`` (payload free),
        ``release_command_pos_m``, ``duration_s`` (swing start to impact), ``release_after_s``,
        ``flight_s``, ``peak_joint_speeds`` {joint: rad/s or m/s}, ``clearance`` {inside,
        reasons, max_radius_m, cabin_sweep_rad [min, max]}, ``gripper_path_m``,
        ``payload_path_m``, ``mc`` {rollouts, impacts_m, sigma_downrange_m, sigma_crossrange_m,
        ellipse} (None for rollouts <= 1), ``timing_s`` {nominal, mc}.
    """
    t_start = time.perf_counter()
    profile = profile or RealityProfile()
    nominal = dataclasses.replace(profile, release_delay_std_s=0.0)
    sim = SimulatedMachine(nominal, seed=req.seed)
    q, qd = np.asarray(req.q, dtype=float), np.asarray(req.qd, dtype=float)
    sim.reset(q_active=q[:4])
    sim.data.qpos[:] = q
    sim.data.qvel[:] = qd
    import mujoco

    mujoco.mj_forward(sim.model, sim.data)
    twin = TwinMachine(sim, "preview")
    executor = ThrowExecutor({req.mode: policy}, config=ExecutorConfig(prepare_timeout_s=10.0))
    request = ThrowRequest(throw_id="preview", machine_id="preview", mode=req.mode, target_m=list(req.target_m))

    def hardware_state():
        # the executor sees the twin as hardware (no SimReset); built without validation or
        # payload fields (the executor checks finiteness itself, the payload is not needed)
        return MachineState.model_construct(
            schema_version=1, machine_id="preview", stamp_s=twin.sim_time_s(), q=sim.q.tolist(),
            qd=sim.qd.tolist(), gripper_open=sim.gripper_open, payload_attached=sim.payload_attached,
            payload_pos_m=None, payload_vel_mps=None, simulated=False, reset_count=None)

    refusal = executor.start(request, hardware_state())
    if refusal is not None:
        return {"status": "failed", "reason": refusal}
    t_hist, pos_hist, vel_hist, q_hist, qd_hist, flags, radii = [], [], [], [], [], [], []
    swing_t = release_t = None
    tail_s = profile.release_delay_mean_s + DELAY_SIGMAS * profile.release_delay_std_s + 2 * PHYSICS_PERIOD_S
    max_steps = int(round((10.0 + executor.config.prepare_timeout_s + 2.0) / PHYSICS_PERIOD_S))
    failure = None
    for _ in range(max_steps):
        state = hardware_state()
        out = executor.tick(state)
        for ev in out.events:
            if ev.phase == "swinging":
                swing_t = sim.time_s
        if out.finished is not None:
            failure = out.finished.failure_reason or out.finished.status
            break
        if out.gripper_open and release_t is None:
            release_t = sim.time_s
        sim.step(out.valve_u, out.gripper_open)
        if swing_t is not None:
            qi, qdi = sim.q, sim.qd
            pts = forward_kinematics(np, qi, qdi)
            t_hist.append(sim.time_s)
            pos_hist.append(pts.gripper_centre.copy())
            vel_hist.append(pts.gripper_centre_vel.copy())
            q_hist.append(qi)
            qd_hist.append(qdi)
            flags.append([bool(f) for f in clearance_violations(np, qi, pts)])
            radii.append(max(np.hypot(*pts.gripper_centre[:2]), np.hypot(*pts.hanger[:2])))
        if release_t is not None and sim.time_s >= release_t + tail_s:
            break
    else:
        failure = "the swing did not release within the twin's time budget"
    if failure is not None or release_t is None:
        return {"status": "failed", "reason": failure or "no release"}
    t_arr, p_arr, v_arr = np.array(t_hist), np.array(pos_hist), np.array(vel_hist)
    q_arr, qd_arr = np.array(q_hist), np.array(qd_hist)

    def open_index(delay_s):
        return np.minimum(np.searchsorted(t_arr, release_t + np.asarray(delay_s) - 1e-9), len(t_arr) - 1)

    k0 = int(open_index(profile.release_delay_mean_s))
    p0, v0 = p_arr[k0], v_arr[k0]
    impact, flight_s = _flight(p0, v0)
    down, cross = impact_errors(req.target_m, impact)
    fly_t = np.linspace(0.0, flight_s, 40)
    payload_path = np.array([ballistic_position(np, p0, v0, t) for t in fly_t])
    t_nominal = time.perf_counter() - t_start

    summary = {
        "status": "ok", "reason": None, "mode": req.mode, "target_m": list(map(float, req.target_m)),
        "impact_m": impact.tolist(), "downrange_error_m": down, "crossrange_error_m": cross,
        "release_pos_m": p0.tolist(), "release_vel_mps": v0.tolist(),
        "release_command_pos_m": p_arr[int(open_index(0.0))].tolist(),
        "release_after_s": float(release_t - swing_t), "flight_s": float(flight_s),
        "duration_s": float(t_arr[k0] - swing_t + flight_s),
        "peak_joint_speeds": {name: float(np.max(np.abs(qd_arr[: k0 + 1, i]))) for i, name in enumerate(ACTIVE_JOINTS)},
        "clearance": _clearance(q_arr[: k0 + 1], np.array(flags[: k0 + 1]), np.array(radii[: k0 + 1]),
                                req.clearance_radius_m),
        "gripper_path_m": _downsample(p_arr[: k0 + 1]),
        "payload_path_m": np.round(payload_path, 4).tolist(),
        "mc": None,
    }
    t1 = time.perf_counter()
    if req.rollouts > 1:
        summary["mc"] = _monte_carlo(req, profile, release_t, open_index, p_arr, v_arr)
    summary["timing_s"] = {"nominal": t_nominal, "mc": time.perf_counter() - t1}
    return summary


def _monte_carlo(req: PreviewRequest, profile: RealityProfile, release_t, open_index, p_arr, v_arr) -> dict:
    """Impacts of ``req.rollouts`` release delays drawn like SimulatedMachine.step draws them."""
    rng = np.random.default_rng(req.seed)
    tail = DELAY_SIGMAS * profile.release_delay_std_s
    delays = rng.normal(profile.release_delay_mean_s, profile.release_delay_std_s, req.rollouts)
    delays = np.clip(delays, max(0.0, profile.release_delay_mean_s - tail), profile.release_delay_mean_s + tail)
    idx = open_index(delays)
    cache = {int(k): _flight(p_arr[k], v_arr[k])[0] for k in np.unique(idx)}
    impacts = np.array([cache[int(k)] for k in idx])
    errs = np.array([impact_errors(req.target_m, p) for p in impacts])
    return {
        "rollouts": int(req.rollouts), "effects": ["release_delay"],
        "impacts_m": np.round(impacts[:, :2], 4).tolist(),
        "mean_impact_m": impacts.mean(axis=0).tolist(),
        "sigma_downrange_m": float(errs[:, 0].std()), "sigma_crossrange_m": float(errs[:, 1].std()),
        "ellipse": _ellipse(impacts[:, :2]),
    }


def _clearance(q: np.ndarray, flags: np.ndarray, radii: np.ndarray, radius_m: float) -> dict:
    """Does the swing stay inside the clearance zone: no ground/cabin/joint-limit violation
    (``flags`` per step: runtime.machine.clearance_violations) and the arm (``radii`` per step,
    m) within ``radius_m`` of the turn axis."""
    reasons = {why for i, why in enumerate(("ground", "cabin", "joint limit")) if len(flags) and flags[:, i].any()}
    max_r = float(radii.max()) if len(radii) else 0.0
    if max_r > radius_m:
        reasons.add(f"reach {max_r:.1f} m beyond the {radius_m:.1f} m clearance radius")
    return {"inside": not reasons, "reasons": sorted(reasons), "max_radius_m": max_r,
            "cabin_sweep_rad": [float(q[:, 0].min()), float(q[:, 0].max())] if len(q) else None,
            "radius_m": radius_m}
