"""Throw preview in the CPU digital twin: what the active policy would do from the machine's
current joint state, and how far the impact may scatter on this site.

:func:`preview_throw` runs runtime.executor.ThrowExecutor (the runtime's own observation builder,
ONNX policy, controller and state machine) on a :class:`SimulatedMachine` set to the given joint
state, WITHOUT a simulated reset: the states are handed to the executor as those of hardware, so
it neither requests a SimReset nor waits for one (it still waits for the passive joints to be
still, as on the machine). The nominal rollout runs the profile's centre values and opens the
gripper after the MEAN release delay; its payload leaves from the profile's grasp point and flies
under its flight effects (drag, wind).

The Monte Carlo (``rollouts`` > 1) covers what is not known (:mod:`sim_twin.twin.uncertainty`):

1. ``param_rollouts`` full twin rollouts at scrambled Sobol points over the profile's
   uncertainty block (parameter ranges, a diagnosis' fitted 1 sigma) and the start state (encoder
   and IMU error on the start pose, residual passive swing below the executor's still threshold);
2. per full rollout, ``rollouts / param_rollouts`` release delays drawn from that rollout's own
   (mean, std), cheaply and exactly: the gripper's motion does not depend on when the payload
   leaves it (the twin does not model the payload's mass on the arm), so the swing is recorded
   every 10 ms and for a delay d the payload is free at the first physics step that ends at or
   after ``release + d`` (as in SimulatedMachine.step) and flies from the recorded state there.

A profile without an uncertainty block still gets the default start-state model. Rollouts whose
swing fails under their drawn parameters are counted (``mc.failed_rollouts``), not drawn.
The 1 sigma ellipse is that of the sampled impacts' covariance; its calibration against throws
of the simulated machine is tests/benchmarks/preview_calibration.py.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from runtime.executor import ExecutorConfig, ThrowExecutor
from runtime.machine import ACTIVE_JOINTS, clearance_violations, forward_kinematics
from runtime.observation import PHYSICS_PERIOD_S
from runtime.protocol.messages import MachineState, ThrowRequest
from runtime.release_check import DEFAULT_RADIUS_M, ReleaseCheck
from runtime.throw_geometry import impact_errors
from sim_twin.twin.effects.payload import FLIGHT_DT_S, grasp_point, integrate_flight
from sim_twin.twin.effects.release import ReleaseDelay
from sim_twin.twin.model import PAYLOAD_RADIUS_M
from sim_twin.twin.physics import ballistic_impact_time, ballistic_position
from sim_twin.twin.profile import RealityProfile
from sim_twin.twin.simulated_machine import SimulatedMachine
from sim_twin.twin.twin_machine import TwinMachine
from sim_twin.twin.uncertainty import NO_START_UNCERTAINTY, StartUncertainty, parse, sample_profile, unit_points

DELAY_SIGMAS = 4.0
"""The swing is recorded up to mean + DELAY_SIGMAS sigma of the release delay after release."""
PATH_POINTS = 120
MC_FLIGHT_DT_S = 0.02
"""RK4 step of the Monte Carlo's flights under drag or wind: the drag acceleration changes
slowly, so against the twin's 5 ms the impact moves by well under a millimetre."""
JITTER_PER_ROLLOUT = 12
"""At least this many release delays per full rollout: ``rollouts // 12`` full rollouts at most."""
PARAM_ROLLOUTS = 16
"""Default full rollouts of the Monte Carlo (a power of two keeps the Sobol points balanced):
about 0.02 CPU s each in 2D and 0.04 in 3D on the 2-core development VM (0.33 / 0.63 CPU s per
ellipse, tests/benchmarks/bench_preview_cpu.py, 2026-11-26)."""

DEFAULT_SITE_PROFILE = Path(__file__).resolve().parent.parent / "profiles" / "nominal_uncertain.json"
"""The nominal machine with the parameter ranges a well-tuned HEAP-class machine is known to
(values CHOSEN, listed in the file), used when the site has no profile of its own."""


def site_profile(manifest: dict | None = None, path: str | Path | None = None) -> RealityProfile:
    """The profile a preview of a policy version samples: the version's own fitted site profile
    (manifest ``site_profile``, written by ``slinger adapt``), else the profile file ``path``,
    else :data:`DEFAULT_SITE_PROFILE`.

    Raises:
        ValueError / OSError: an unreadable or invalid profile (the message says which).
    """
    if manifest and manifest.get("site_profile"):
        return RealityProfile.from_dict(manifest["site_profile"])
    return RealityProfile.load(path or DEFAULT_SITE_PROFILE)


@dataclass
class PreviewRequest:
    """What to preview.

    Attributes:
        mode: "2d" or "3d".
        target_m: (3,) target, machine frame, m.
        q / qd: (6,) current (measured) joint positions / velocities of the machine.
        rollouts: Monte Carlo impacts for the ellipse (0 or 1: the nominal rollout only).
        seed: seed of the Sobol points and the sampled release delays.
        clearance_radius_m: the swing must stay within this distance of the turn axis.
        param_rollouts: full twin rollouts over the uncertain parameters and start state
            (at most ``rollouts // JITTER_PER_ROLLOUT``, at least 1).
        release_check_radius_m: the release check as the machine's runtime runs it
            (runtime.executor.ExecutorConfig.release_check_radius_m; None: off). The server
            sets it from its settings (server.config.Settings.release_check_radius_m).
    """

    mode: str
    target_m: list[float]
    q: list[float]
    qd: list[float]
    rollouts: int = 200
    seed: int = 0
    clearance_radius_m: float = 12.0
    param_rollouts: int = PARAM_ROLLOUTS
    release_check_radius_m: float | None = DEFAULT_RADIUS_M


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


@dataclass
class _Payload:
    """What the payload does under one concrete profile: opening delay (mean, std, s), grasp
    offset ((3,) m in the gripper frame, or None) and extra flight acceleration (or None)."""

    delay_mean_s: float
    delay_std_s: float
    grasp_offset: np.ndarray | None
    flight_accel: Callable | None  # (pos, vel) -> extra acceleration, m/s^2

    @classmethod
    def of(cls, profile: RealityProfile) -> _Payload:
        stack = profile.stack()
        mean_s, std_s = stack.release_delay(profile.release_delay_mean_s, profile.release_delay_std_s)
        return cls(float(mean_s), float(std_s), stack.grasp_offset(), stack.flight_accel if stack.has("flight_accel") else None)


@dataclass
class _Swing:
    """One recorded twin swing: true joint states after every physics step from swing start to
    ``DELAY_SIGMAS`` sigma past the mean opening, and what the payload does under its profile."""

    payload: _Payload
    swing_t: float
    release_t: float
    t: np.ndarray  # (N,) simulated time after each step, s
    qpos: np.ndarray  # (N, 6) true joint positions
    qvel: np.ndarray  # (N, 6) true joint velocities
    meas_q: np.ndarray  # (N, 6) measured positions (what the executor saw)
    meas_qd: np.ndarray  # (N, 6) measured velocities

    def open_index(self, delay_s) -> np.ndarray:
        """Index of the first recorded step that ends at or after release + delay_s."""
        return np.minimum(np.searchsorted(self.t, self.release_t + np.asarray(delay_s) - 1e-9), len(self.t) - 1)

    def payload_free(self, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K, 3) position and velocity of the payload freed at steps ``k`` (K,), as
        SimulatedMachine._open_payload computes them (grasp offset included)."""
        k = np.atleast_1d(k)
        if self.payload.grasp_offset is None and len(k) == 1:
            pts = forward_kinematics(np, self.qpos[k[0]], self.qvel[k[0]])
            return pts.gripper_centre[None].copy(), pts.gripper_centre_vel[None].copy()
        return grasp_point(self.qpos[k], self.qvel[k], self.payload.grasp_offset)

    def impacts(self, k: np.ndarray, flight_dt_s: float = FLIGHT_DT_S) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(impact (K, 3) with z = 0, flight time (K,), release pos (K, 3), release vel (K, 3))
        of payloads freed at steps ``k``, under the profile's flight effects (RK4 at
        ``flight_dt_s`` when there are any, else closed form)."""
        p0, v0 = self.payload_free(k)
        if self.payload.flight_accel is not None:
            _, _, _, t_hit, hit = integrate_flight(p0, v0, self.payload.flight_accel, dt_s=flight_dt_s)
            return hit, np.asarray(t_hit), p0, v0
        t_fall = ballistic_impact_time(np, p0.T, v0.T, PAYLOAD_RADIUS_M)
        hit = ballistic_position(np, p0, v0, t_fall[:, None])
        hit[:, 2] = 0.0
        return hit, t_fall, p0, v0


@dataclass(slots=True)
class _TwinState:
    """The fields of a runtime.protocol.messages.MachineState that the executor reads, for the
    twin seen as hardware (``simulated`` False, no payload tracking). A plain record: one is
    built per 10 ms step of every rollout, and pydantic's ``model_construct`` cost about a tenth
    of a rollout's CPU time (cProfile of preview_throw, 200 rollouts)."""

    stamp_s: float
    q: list[float]
    qd: list[float]
    gripper_open: bool
    payload_attached: bool
    machine_id: str = "preview"
    schema_version: int = 1
    payload_pos_m: list[float] | None = None
    payload_vel_mps: list[float] | None = None
    simulated: bool = False
    reset_count: int | None = None
    machine_fault: str | None = None
    watchdog_trips: int | None = None


def _run_swing(policy, req: PreviewRequest, profile: RealityProfile, q, qd, seed: int, kinematics: bool,
               check: ReleaseCheck | None):
    """Run the executor on a twin of ``profile`` from (q, qd) until DELAY_SIGMAS sigma after the
    mean opening. Returns (_Swing, extras) or (None, failure reason). ``kinematics``: also
    record clearance flags and reach per step (extras = (flags (N, 3), radii (N,))). ``check``:
    the release check of the preview's executors (one per preview, reused by its rollouts)."""
    payload = _Payload.of(profile)
    # the twin opens after the mean delay (a last release_delay effect overrides the others);
    # flight effects cannot change the swing and are left to _Swing.impacts
    at_mean = ReleaseDelay(mean_s=min(payload.delay_mean_s, ReleaseDelay.params[0].hi), jitter_s=0.0)
    effects = [e for e in profile.effects if e.stage != "flight"] + [at_mean]
    sim = SimulatedMachine(dataclasses.replace(profile, effects=effects), seed=seed)
    sim.set_state(q, qd)
    twin = TwinMachine(sim, "preview")
    # the release check as the runtime runs it (the request's radius: the server's setting)
    # no per-tick telemetry: the preview reads only how the throw ended
    executor = ThrowExecutor({req.mode: policy}, config=ExecutorConfig(
        prepare_timeout_s=10.0, release_check_radius_m=req.release_check_radius_m, record_ticks=False), release_check=check)
    request = ThrowRequest(throw_id="preview", machine_id="preview", mode=req.mode, target_m=list(req.target_m))

    def hardware_state() -> MachineState:
        # the executor sees the twin as hardware (no SimReset); no validation and no payload
        # fields (the executor checks finiteness itself, the payload is not needed)
        return cast(MachineState, _TwinState(stamp_s=twin.sim_time_s(), q=sim.q.tolist(), qd=sim.qd.tolist(),
                                             gripper_open=sim.gripper_open, payload_attached=sim.payload_attached))

    refusal = executor.start(request, hardware_state())
    if refusal is not None:
        return None, refusal
    rec: dict[str, list] = {k: [] for k in ("t", "qpos", "qvel", "mq", "mqd", "flags", "radii")}
    swing_t = release_t = None
    tail_s = payload.delay_mean_s + DELAY_SIGMAS * payload.delay_std_s + 2 * PHYSICS_PERIOD_S
    max_steps = int(round((10.0 + executor.config.prepare_timeout_s + 2.0) / PHYSICS_PERIOD_S))
    for _ in range(max_steps):
        out = executor.tick(hardware_state())
        if swing_t is None and any(ev.phase == "swinging" for ev in out.events):
            swing_t = sim.time_s
        if out.finished is not None:
            return None, out.finished.failure_reason or out.finished.status
        if out.gripper_open and release_t is None:
            release_t = sim.time_s
        sim.step(out.valve_u, out.gripper_open)
        if swing_t is not None:
            rec["t"].append(sim.time_s)
            rec["qpos"].append(sim.data.qpos.copy())
            rec["qvel"].append(sim.data.qvel.copy())
            mq, mqd = sim.q, sim.qd
            rec["mq"].append(mq)
            rec["mqd"].append(mqd)
            if kinematics:
                pts = forward_kinematics(np, mq, mqd)
                rec["flags"].append([bool(f) for f in clearance_violations(np, mq, pts)])
                rec["radii"].append(max(np.hypot(*pts.gripper_centre[:2]), np.hypot(*pts.hanger[:2])))
        if release_t is not None and sim.time_s >= release_t + tail_s:
            break
    else:
        return None, "the swing did not release within the twin's time budget"
    if release_t is None:
        return None, "no release"
    if swing_t is None:  # the executor swings before it releases
        raise RuntimeError("the twin released without a swinging phase")
    swing = _Swing(payload, swing_t, release_t, np.array(rec["t"]), np.array(rec["qpos"]), np.array(rec["qvel"]),
                   np.array(rec["mq"]), np.array(rec["mqd"]))
    return swing, (np.array(rec["flags"]).reshape(-1, 3), np.array(rec["radii"]))


class NominalCache:
    """The nominal rollouts of a worker's recent previews, by request (least recently used out).

    The console previews in two steps, the nominal rollout alone and then the ellipse, and asks
    for the ellipse from the nominal's start state (server.throws.previews.PreviewService.submit,
    ``extends``): the ellipse's preview then reuses the nominal's swing and summary instead of
    running the same rollout again (it is deterministic: same policy, profile, request and seed
    give the same swing). A hit needs the same policy (SHA-256), the same profile object (a
    worker caches profiles per source) and every request field but ``rollouts`` and
    ``param_rollouts`` equal. Thread-safe.

    Args:
        size: entries kept (each a recorded swing of ~200 steps and its summary, tens of kB).
    """

    def __init__(self, size: int = 8):
        self.size = size
        self._entries: OrderedDict[tuple, tuple[RealityProfile, _Swing | None, dict]] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = 0

    @staticmethod
    def key(policy, req: PreviewRequest) -> tuple:
        """What a nominal rollout depends on besides the profile: policy SHA-256 (or the runner's
        identity), mode, target, start state, seed, clearance and release-check radii."""
        return (getattr(policy, "sha256", None) or id(policy), req.mode, tuple(map(float, req.target_m)),
                tuple(map(float, req.q)), tuple(map(float, req.qd)), int(req.seed), float(req.clearance_radius_m),
                req.release_check_radius_m)

    def get(self, key: tuple, profile: RealityProfile) -> tuple[_Swing | None, dict] | None:
        """(swing or None when it failed, nominal summary) of ``key`` under ``profile``, or None."""
        with self._lock:
            entry = self._entries.get(key)
            if entry is None or entry[0] is not profile:
                return None
            self._entries.move_to_end(key)
            self.hits += 1
            return entry[1], entry[2]

    def put(self, key: tuple, profile: RealityProfile, swing: _Swing | None, summary: dict) -> None:
        """Keep the nominal rollout of ``key`` under ``profile`` (the entry holds the profile, so
        that its identity stays its own)."""
        with self._lock:
            self._entries[key] = (profile, swing, summary)
            self._entries.move_to_end(key)
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)


def _nominal(policy, req: PreviewRequest, profile: RealityProfile, q: np.ndarray, qd: np.ndarray,
             check: ReleaseCheck | None) -> tuple[_Swing | None, dict]:
    """The nominal rollout: (its swing, the preview's summary without ``mc`` and ``timing_s``),
    or (None, {"status": "failed", "reason"}) when the twin's swing failed."""
    swing, extra = _run_swing(policy, req, dataclasses.replace(profile, uncertainty={}), q, qd, req.seed, kinematics=True,
                              check=check)
    if swing is None:
        return None, {"status": "failed", "reason": extra}
    flags, radii = extra
    k0 = int(swing.open_index(swing.payload.delay_mean_s))
    hit, t_fall, p0, v0 = swing.impacts(np.array([k0]))
    impact, flight_s, p0, v0 = hit[0], float(t_fall[0]), p0[0], v0[0]
    down, cross = impact_errors(req.target_m, impact)
    if swing.payload.flight_accel is not None:
        ts, ps, _, _, _ = integrate_flight(p0, v0, swing.payload.flight_accel)
        payload_path = ps[np.unique(np.linspace(0, len(ts) - 1, 40).astype(int))]
    else:
        payload_path = np.array([ballistic_position(np, p0, v0, t) for t in np.linspace(0.0, flight_s, 40)])
    grip = np.array([forward_kinematics(np, a, b).gripper_centre for a, b in zip(swing.qpos[: k0 + 1], swing.qvel[: k0 + 1])])
    return swing, {
        "status": "ok", "reason": None, "mode": req.mode, "target_m": list(map(float, req.target_m)),
        "profile": profile.name,
        "impact_m": impact.tolist(), "downrange_error_m": down, "crossrange_error_m": cross,
        "release_pos_m": p0.tolist(), "release_vel_mps": v0.tolist(),
        "release_command_pos_m": forward_kinematics(np, *(a[int(swing.open_index(0.0))] for a in (swing.qpos, swing.qvel))).gripper_centre.tolist(),
        "release_after_s": float(swing.release_t - swing.swing_t), "flight_s": flight_s,
        "duration_s": float(swing.t[k0] - swing.swing_t + flight_s),
        "peak_joint_speeds": {name: float(np.max(np.abs(swing.meas_qd[: k0 + 1, i]))) for i, name in enumerate(ACTIVE_JOINTS)},
        "clearance": _clearance(swing.meas_q[: k0 + 1], flags[: k0 + 1], radii[: k0 + 1], req.clearance_radius_m),
        "gripper_path_m": _downsample(grip),
        "payload_path_m": np.round(payload_path, 4).tolist(),
        "mc": None,
    }


def preview_throw(policy, req: PreviewRequest, profile: RealityProfile | None = None,
                  pool: Executor | None = None, nominals: NominalCache | None = None) -> dict:
    """Preview one throw; returns a JSON-ready summary (see the keys below).

    Args:
        policy: a loaded runtime.policy.PolicyRunner of ``req.mode``.
        req: the request and the machine's current (measured) state.
        profile: the site's reality profile, with its uncertainty block if any (default nominal).
        pool: processes for the Monte Carlo's full rollouts (a long-lived pool of
            sim_twin.twin.pools.process_pool; each process loads the policy from ``policy.path`` once),
            or None to run them here one after the other. The impacts are the same either way.
        nominals: a worker's :class:`NominalCache`: the nominal rollout of the same request under
            the same profile is taken from it when there, and kept in it otherwise. The summary
            is the same either way (``timing_s.nominal`` is then the look-up's time).

    Returns:
        ``status`` ("ok" or "failed"), ``reason``; and when ok: ``impact_m``, ``downrange_error_m``,
        ``crossrange_error_m``, ``release_pos_m`` / ``release_vel_mps`` (payload free),
        ``release_command_pos_m``, ``duration_s`` (swing start to impact), ``release_after_s``,
        ``flight_s``, ``peak_joint_speeds`` {joint: rad/s or m/s}, ``clearance`` {inside,
        reasons, max_radius_m, cabin_sweep_rad [min, max]}, ``gripper_path_m``,
        ``payload_path_m``, ``mc`` (None for rollouts <= 1, else see :func:`_monte_carlo`),
        ``profile`` (name), ``timing_s`` {nominal, mc}.

    Raises:
        ValueError: the profile's uncertainty block is invalid.
    """
    t_start = time.perf_counter()
    profile = profile or RealityProfile()
    unc = parse(profile.uncertainty)
    q, qd = np.asarray(req.q, dtype=float), np.asarray(req.qd, dtype=float)
    check = ReleaseCheck.load() if req.release_check_radius_m is not None else None
    # the Monte Carlo's full rollouts go to the pool before the nominal runs here: they need
    # nothing of it (their release delays are drawn up front), so the two overlap
    plan = _mc_plan(req, profile, unc, q, qd) if req.rollouts > 1 else None
    futures = _submit_rollouts(policy, req, plan[2], pool) if plan is not None and plan[1] else None
    key = NominalCache.key(policy, req) if nominals is not None else None
    known = nominals.get(key, profile) if nominals is not None and key is not None else None
    if known is None:
        swing, nominal = _nominal(policy, req, profile, q, qd, check)
        if nominals is not None and key is not None:
            nominals.put(key, profile, swing, nominal)
    else:
        swing, nominal = known
    summary = dict(nominal)  # the cached one stays as it is
    if swing is None:
        for f in futures or []:
            f.cancel()
        return summary
    t_nominal = time.perf_counter() - t_start
    t1 = time.perf_counter()
    if req.rollouts > 1:
        summary["mc"] = _monte_carlo(policy, req, profile, unc, q, qd, swing, check, pool, plan, futures)
    summary["timing_s"] = {"nominal": t_nominal, "mc": time.perf_counter() - t1}
    return summary


def _draw_delays(payload: _Payload, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) release delays [s] of one full rollout: its payload's delay distribution, clipped at
    DELAY_SIGMAS sigma (the swing is recorded that far)."""
    mean_s, std_s = payload.delay_mean_s, payload.delay_std_s
    tail = DELAY_SIGMAS * std_s
    return np.clip(rng.normal(mean_s, std_s, n), max(0.0, mean_s - tail), mean_s + tail)


def _impacts_at(swing: _Swing, delays: np.ndarray) -> np.ndarray:
    """(n, 3) impacts [m, machine frame] of ``swing`` opened after each of ``delays`` [s]."""
    idx = swing.open_index(delays)
    uniq, inv = np.unique(idx, return_inverse=True)
    return swing.impacts(uniq, MC_FLIGHT_DT_S)[0][inv.ravel()]


def _rollout_impacts(policy, req: PreviewRequest, profile: RealityProfile, q, qd, seed: int, delays: np.ndarray,
                     check: ReleaseCheck | None) -> np.ndarray | None:
    """One full rollout of the Monte Carlo: (n, 3) impacts [m], or None when its swing failed."""
    swing, _ = _run_swing(policy, req, profile, q, qd, seed, kinematics=False, check=check)
    return None if swing is None else _impacts_at(swing, delays)


_PROCESS_CACHE: dict = {}
"""In a pool process: loaded policies by path and the release check (loaded once per process)."""


def _rollout_in_process(policy_path: str, req: PreviewRequest, profile: RealityProfile, q, qd, seed: int,
                        delays: np.ndarray) -> np.ndarray | None:
    """:func:`_rollout_impacts` in a pool process (the policy and release check cached there)."""
    policy, check = _process_policy(policy_path, req.release_check_radius_m is not None)
    return _rollout_impacts(policy, req, profile, q, qd, seed, delays, check)


def _process_policy(policy_path: str, release_check: bool):
    """(policy runner, release check or None) of this pool process, loaded once (_PROCESS_CACHE)."""
    from runtime.policy import PolicyRunner

    policy = _PROCESS_CACHE.get(policy_path)
    if policy is None:
        policy = _PROCESS_CACHE[policy_path] = PolicyRunner.load(policy_path)
    check = None
    if release_check:
        check = _PROCESS_CACHE.get("release_check")
        if check is None:
            check = _PROCESS_CACHE["release_check"] = ReleaseCheck.load()
    return policy, check


def warm_policy(pool: Executor, processes: int, policy_path: str | Path, release_check: bool = True) -> list[Future]:
    """Load the policy ``policy_path`` (and the release check) in the ``processes`` processes of
    ``pool`` and make their first calls (runtime.executor.ThrowExecutor.warm_up), so that the
    first Monte Carlo of a policy does not pay for them in its rollouts. Returns at once (the
    futures); a worker calls it when a preview brings a policy it has not loaded yet, so the
    processes load it while that preview's nominal rollout runs and the console asks for the
    ellipse. A process that takes two of these tasks loads once (the second is a cache hit)."""
    return [pool.submit(_warm_process, str(policy_path), release_check) for _ in range(processes)]


def _warm_process(policy_path: str, release_check: bool) -> None:
    policy, check = _process_policy(policy_path, release_check)
    config = ExecutorConfig(release_check_radius_m=DEFAULT_RADIUS_M if check is not None else None)
    ThrowExecutor({policy.mode: policy}, config=config, release_check=check).warm_up()


def warm_imports() -> None:
    """Import what a preview imports only when it first needs it: scipy.stats (the Monte Carlo's
    Sobol points, sim_twin.twin.uncertainty.unit_points), about 2 s of CPU on the 2-core
    development VM, which a worker's first ellipse paid otherwise (cProfile of a fresh process)."""
    from scipy.stats import qmc  # noqa: F401


def warm_up(pool: Executor, processes: int) -> None:
    """Import the twin in the ``processes`` processes of ``pool`` (a preview's first rollouts
    then start at once); returns when they are up."""
    for f in [pool.submit(_import_twin) for _ in range(processes)]:
        f.result()


def _import_twin() -> None:
    import runtime.policy  # noqa: F401
    import sim_twin.twin.simulated_machine  # noqa: F401


_Task = tuple[RealityProfile, np.ndarray, np.ndarray, int, np.ndarray]
"""One full rollout of the Monte Carlo: (profile, q (6,), qd (6,), seed, release delays (n,) s)."""


def _mc_plan(req: PreviewRequest, profile: RealityProfile, unc, q, qd) -> tuple[StartUncertainty, bool, list[_Task]]:
    """The Monte Carlo's full rollouts (module doc): (start-state model, whether anything is
    uncertain, one task per full rollout: (profile, q (6,), qd (6,), seed, release delays (n,) s)).
    Every release delay is drawn here, before any rollout runs."""
    start = unc.start if unc.start.active else NO_START_UNCERTAINTY
    uncertain = bool(unc.params) or start.active
    n_full = max(1, min(req.param_rollouts, req.rollouts // JITTER_PER_ROLLOUT)) if uncertain else 1
    dims = unc.param_dims + StartUncertainty.DIMS
    points = unit_points(n_full, dims, req.seed)
    rng = np.random.default_rng(req.seed)
    per = np.full(n_full, req.rollouts // n_full)
    per[: req.rollouts % n_full] += 1
    tasks: list[_Task] = []
    for i in range(n_full):
        prof_i = sample_profile(profile, unc, points[i, : unc.param_dims]) if uncertain else profile
        q_i, qd_i = start.perturb(q, qd, points[i, unc.param_dims:]) if uncertain else (q, qd)
        tasks.append((prof_i, q_i, qd_i, req.seed * 1000 + i, _draw_delays(_Payload.of(prof_i), per[i], rng)))
    return start, uncertain, tasks


def _submit_rollouts(policy, req: PreviewRequest, tasks: list[_Task], pool: Executor | None) -> list[Future] | None:
    """The full rollouts ``tasks`` (:func:`_mc_plan`) submitted to ``pool``; None without a pool
    or with fewer than 2 (they then run in this process)."""
    if pool is None or len(tasks) < 2:
        return None
    path = str(policy.path)
    return [pool.submit(_rollout_in_process, path, req, *t) for t in tasks]


def _monte_carlo(policy, req: PreviewRequest, profile: RealityProfile, unc, q, qd, nominal: _Swing,
                 check: ReleaseCheck | None, pool: Executor | None = None,
                 plan: tuple[StartUncertainty, bool, list[_Task]] | None = None,
                 futures: list[Future] | None = None) -> dict:
    """``req.rollouts`` impacts over the site's uncertainty (module doc); the full rollouts run in
    ``pool`` when one is given (:func:`preview_throw`), or were submitted there already
    (``futures``, of ``plan``: :func:`_mc_plan`, :func:`_submit_rollouts`). Every release delay is
    drawn before the rollouts run, so the impacts do not depend on where or in which order they ran.

    Returns:
        {rollouts, param_rollouts, failed_rollouts, effects (what was sampled), impacts_m (R, 2),
        mean_impact_m (3,), sigma_downrange_m, sigma_crossrange_m, ellipse} or, when every
        full rollout failed, the same with impacts_m [] and ellipse None.
    """
    start, uncertain, tasks = plan if plan is not None else _mc_plan(req, profile, unc, q, qd)
    n_full = len(tasks)
    results: list[np.ndarray | None]
    if not uncertain:
        results = [_impacts_at(nominal, tasks[0][4])]
    elif futures is not None or (futures := _submit_rollouts(policy, req, tasks, pool)) is not None:
        results = [f.result() for f in futures]
    else:
        results = [_rollout_impacts(policy, req, *t, check) for t in tasks]
    impacts = [r for r in results if r is not None]
    failed = len(results) - len(impacts)
    effects = (["release_delay"] + [p.path for p in unc.params]
               + (["start_state"] if start.active else []))
    out = {"rollouts": int(req.rollouts), "param_rollouts": n_full, "failed_rollouts": failed,
           "profile": profile.name, "effects": effects, "impacts_m": [], "mean_impact_m": None,
           "sigma_downrange_m": None, "sigma_crossrange_m": None, "ellipse": None}
    if not impacts:
        return out
    imp = np.concatenate(impacts)
    errs = np.array([impact_errors(req.target_m, p) for p in imp])
    out.update(impacts_m=np.round(imp[:, :2], 4).tolist(), mean_impact_m=imp.mean(axis=0).tolist(),
               sigma_downrange_m=float(errs[:, 0].std()), sigma_crossrange_m=float(errs[:, 1].std()),
               ellipse=_ellipse(imp[:, :2]))
    return out


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
