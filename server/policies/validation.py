"""Policy validation before promotion, in a child process with memory and time limits.

A policy version must pass two sweeps before it can be promoted (server.policies.versions):

1. **Observation sweep** (:func:`observation_sweep`): the policy is run on ``observations``
   observations built by runtime.observation.build_observation from joint positions anywhere
   within the joint limits (runtime.machine.JOINT_LOWER/UPPER; cabin turn and passive joints
   within +-pi and +-0.8 rad), joint velocities up to 1.5 times the active joints' speed limits
   (passive +-3 rad/s, so gripper speeds of several m/s), previous actions in [-1, 1], targets
   over the whole declared range (both ends included) and both gripper states. Every action must
   be finite and of the mode's size. A condition that only some states meet (e.g. a NaN only
   beyond 6 m while the gripper moves faster than 1 m/s) is met by a large share of the samples.
2. **Twin sweep** (sim_twin.evaluation.evaluate.twin_sweep): throws in the CPU twin (sim_twin.evaluation.evaluate's throw loop)
   at ``distances`` target distances spanning the declared range, ``throws_per_distance`` each,
   every throw from a random collision-free start pose (sim_twin.twin.initial_pose through the seed).
   No throw may fail because of the policy (a non-finite or misshaped action, a policy error), and
   at every distance the policy must release in at least one throw.

Both run in ``python -m server.policies.validation`` (a child process) so that a hostile file
cannot take the caller's memory or time: the parent (:func:`validate`) polls the child's resident
memory every 50 ms and kills it past ``memory_bytes`` (an address-space limit of
``memory_bytes`` + 4 GiB backs that up), kills it past ``time_s``, and kills it within one poll
of a cancel (``check_cancel`` raising). The verdict is a dict: ``passed``, ``reason`` (a sentence
when failed), ``observations``, ``throws``, ``elapsed_s``, ``peak_rss_bytes``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import resource
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from server.config import Settings

log = logging.getLogger(__name__)

POLL_S = 0.05
ADDRESS_SPACE_HEADROOM_BYTES = 4 << 30
"""Added to the memory limit for the child's address-space limit (the interpreter, numpy,
onnxruntime and MuJoCo map far more than they touch)."""


@dataclass(frozen=True)
class ValidationLimits:
    """What a validation checks and what it may spend.

    Attributes:
        observations: policy evaluations of the observation sweep.
        distances: target distances of the twin sweep (spanning the declared range; 0: no twin sweep).
        throws_per_distance: twin throws per distance, each from a random start pose.
        memory_bytes: resident memory the child may use, bytes.
        time_s: wall-clock time the child may use, s.
    """

    observations: int = 4096
    distances: int = 5
    throws_per_distance: int = 20  # sim_twin.evaluation.evaluate.SWEEP_THROWS_PER_DISTANCE (tests/test_release_sweep.py)
    memory_bytes: int = 1 << 30
    time_s: float = 600.0

    @classmethod
    def from_settings(cls, settings: Settings, upload: bool = False) -> ValidationLimits:
        """The limits of the server's settings; ``upload``: the quick check of an upload (64
        observations, no twin throws, at most 60 s)."""
        memory = settings.validation_memory_mb << 20
        if upload:
            return cls(observations=64, distances=0, throws_per_distance=0, memory_bytes=memory,
                       time_s=min(60.0, settings.validation_time_s))
        return cls(settings.validation_observations, settings.validation_distances,
                   settings.validation_throws_per_distance, memory, settings.validation_time_s)


def observation_sweep(runner, n: int, seed: int = 0) -> str | None:
    """Run ``runner`` (runtime.policy.PolicyRunner) on ``n`` observations spanning the bounds
    (module docstring); returns why it failed, or None."""
    from runtime.machine import ACTIVE_VELOCITY_LIMITS, JOINT_LOWER, JOINT_UPPER
    from runtime.observation import build_observation, num_actions
    from runtime.policy import PolicyError
    from runtime.throw_geometry import ARM_PLANE_OFFSET_M

    rng = np.random.default_rng(seed)
    mode = runner.mode
    lo_d, hi_d = runner.target_range_m
    q_lo = np.where(np.isfinite(JOINT_LOWER), JOINT_LOWER, [-math.pi, 0, 0, 0, -0.8, -0.8])
    q_hi = np.where(np.isfinite(JOINT_UPPER), JOINT_UPPER, [math.pi, 0, 0, 0, 0.8, 0.8])
    qd_max = np.concatenate([1.5 * ACTIVE_VELOCITY_LIMITS, [3.0, 3.0]])
    n_act, steps = num_actions(mode), runner.history_steps
    for i in range(n):
        q_hist = rng.uniform(q_lo, q_hi, size=(steps, 6))
        qd_hist = rng.uniform(-qd_max, qd_max, size=(steps, 6))
        if i % 8 == 0:  # corners: every velocity at its bound
            qd_hist = np.sign(qd_hist) * qd_max
        d = (lo_d, hi_d)[i % 2] if i < 4 else rng.uniform(lo_d, hi_d)
        # 2D: in the arm's plane at the current cabin angle; 3D: any bearing
        yaw = q_hist[0, 0] if mode == "2d" else rng.uniform(-math.pi, math.pi)
        off = ARM_PLANE_OFFSET_M if mode == "2d" else 0.0
        along = math.sqrt(max(d**2 - off**2, 0.0))
        c, s = math.cos(yaw), math.sin(yaw)
        target = np.array([c * along - s * off, s * along + c * off, 0.0])
        prev = rng.uniform(-1.0, 1.0, size=n_act)
        obs = build_observation(np, mode, q_hist, qd_hist, prev, target, float(i % 3 == 0))
        try:
            action = np.asarray(runner.act(obs))
        except PolicyError as e:
            return f"policy error on observation {i} (target {d:.2f} m): {e}"
        if action.shape != (n_act,) or not np.all(np.isfinite(action)):
            ee_speed = _gripper_speed(q_hist[0], qd_hist[0])
            return (f"non-finite or misshaped action on observation {i} of the sweep (target {d:.2f} m, "
                    f"gripper speed {ee_speed:.2f} m/s)")
    return None


def _gripper_speed(q, qd) -> float:
    from runtime.machine import forward_kinematics

    return float(np.linalg.norm(forward_kinematics(np, q, qd).gripper_centre_vel))


def _child(args: dict) -> dict:
    """The child's work: load, observation sweep, twin sweep."""
    from runtime.policy import PolicyError, PolicyRunner
    from sim_twin.evaluation.evaluate import twin_sweep  # the training gate's release check too

    t0 = time.monotonic()
    out: dict[str, Any] = {"passed": False, "reason": None, "observations": 0, "throws": 0}
    try:
        runner = PolicyRunner.load(args["onnx_path"], args.get("manifest_path"))
    except PolicyError as e:
        out["reason"] = f"the policy does not load: {e}"
        return out
    out["reason"] = observation_sweep(runner, args["observations"], args.get("seed", 0))
    out["observations"] = args["observations"]
    if out["reason"] is None and args["distances"] > 0 and args["throws_per_distance"] > 0:
        out["reason"], out["throws"] = twin_sweep(args["onnx_path"], runner.mode, runner.target_range_m,
                                                  args["distances"], args["throws_per_distance"], args.get("seed", 0))
    out["passed"] = out["reason"] is None
    out["child_s"] = time.monotonic() - t0
    return out


def _rss_bytes(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        pass
    return 0


def validate(onnx_path: str | Path, limits: ValidationLimits = ValidationLimits(), check_cancel=None,
             manifest_path: str | Path | None = None, seed: int = 0) -> dict:
    """Validate a policy file (with its manifest beside it) in a limited child process.

    Args:
        onnx_path: the ONNX file; its manifest is ``manifest_path`` or the same path with ``.json``.
        limits: what to check and what it may spend.
        check_cancel: called every poll; raise from it to cancel (the child is killed first).
        seed: seed of the sweeps (the same seed gives the same observations and start poses).

    Returns:
        The verdict (module docstring). Exceeding a limit fails it with the limit as the reason.
    """
    args = {"onnx_path": str(onnx_path), "manifest_path": str(manifest_path) if manifest_path else None,
            "observations": limits.observations, "distances": limits.distances,
            "throws_per_distance": limits.throws_per_distance, "seed": seed}
    address_space = limits.memory_bytes + ADDRESS_SPACE_HEADROOM_BYTES

    def _limit_memory() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (address_space, address_space))

    t0 = time.monotonic()
    child = subprocess.Popen([sys.executable, "-m", "server.policies.validation", json.dumps(args)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_limit_memory,
                             env={**os.environ, "OMP_NUM_THREADS": "1"})
    peak, reason = 0, None
    try:
        while child.poll() is None:
            if check_cancel is not None:
                check_cancel()
            peak = max(peak, _rss_bytes(child.pid))
            if peak > limits.memory_bytes:
                reason = (f"the evaluation exceeded its memory limit of {limits.memory_bytes / 2**20:.0f} MiB "
                          f"({peak / 2**20:.0f} MiB resident)")
            elif time.monotonic() - t0 > limits.time_s:
                reason = f"the evaluation exceeded its time limit of {limits.time_s:.0f} s"
            if reason is not None:
                child.kill()
                break
            time.sleep(POLL_S)
    finally:
        if child.poll() is None:
            child.kill()
        stdout, stderr = child.communicate()
    elapsed = time.monotonic() - t0
    common = {"elapsed_s": round(elapsed, 3), "peak_rss_bytes": peak, "limits": asdict(limits)}
    if reason is not None:
        return {"passed": False, "reason": reason, "observations": 0, "throws": 0, **common}
    line = next((ln for ln in reversed(stdout.splitlines()) if ln.startswith("{")), None)
    if child.returncode != 0 or line is None:
        tail = (stderr or "").strip().splitlines()[-1:] or [f"exit status {child.returncode}"]
        if child.returncode in (-9, 137) or "bad_alloc" in (stderr or "") or "allocate" in (stderr or "").lower():
            why = f"the evaluation ran out of memory (limit {limits.memory_bytes / 2**20:.0f} MiB): {tail[0][:300]}"
        else:
            why = f"the evaluation process failed: {tail[0][:300]}"
        return {"passed": False, "reason": why, "observations": 0, "throws": 0, **common}
    return {**json.loads(line), **common}


def main(argv: list[str]) -> int:
    logging.basicConfig(level=logging.WARNING)
    print(json.dumps(_child(json.loads(argv[0]))), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
