"""Sim-to-sim evaluation of an ONNX policy by the paper's protocol (Sec. IV-A).

Each throw runs the runtime's own ThrowExecutor (observation builder, ONNX policy, PID +
feed-forward controller, state machine) on the simulated machine (CPU MuJoCo twin with the
hydraulic valve model of its reality profile), exactly as on the machine but without Zenoh:
a different controller and actuation from the training environment, as the paper evaluated in
Gazebo rather than Isaac Gym. Every throw starts from a random collision-free pose at rest with
the gripper hanging still (3D: cabin anywhere); targets lie on the downrange axis (2D: in the
arm's plane).

:func:`throw_batch` runs throws at one target distance, one per seed (the evaluation, the site
matrix sim_twin.evaluation.matrix and the server's quick evaluations use it); :func:`twin_sweep`
throws over a policy's declared range (the policy validation's and the training gate's check); :func:`evaluate` spreads them
over all cores and summarises them per target (:func:`summarise`); progress is logged. The
command line (``slinger evaluate``: JSON report and the paper's figure) is sim_twin.evaluation.cli.
"""

from __future__ import annotations

import logging
import math
import os
import time
from concurrent.futures import as_completed
from pathlib import Path

import numpy as np

from runtime.throw_geometry import ARM_PLANE_OFFSET_M
from sim_twin.twin.pools import process_pool

log = logging.getLogger(__name__)


def target_on_axis(mode: str, distance_m: float) -> list[float]:
    """Ground target at ``distance_m`` from the turn axis on the evaluation axis (machine
    frame): in the arm's plane for 2D (cabin at 0), on the x axis for 3D."""
    if mode == "2d":
        return [math.sqrt(distance_m**2 - ARM_PLANE_OFFSET_M**2), ARM_PLANE_OFFSET_M, 0.0]
    return [distance_m, 0.0, 0.0]


def throw_batch(policy_path: str | Path, mode: str, distance_m: float, seeds: list[int],
                profile_path: str | Path | None = None, executor_config: dict | None = None, engine: str = "mujoco") -> list[dict]:
    """Throws at one target distance (:func:`target_on_axis`), one per seed, each from the seed's
    random start pose on a simulated machine of the profile, by the runtime's executor. Runs in
    the calling process (a process pool's worker: the arguments are plain, picklable values).

    Args:
        policy_path: ONNX policy of ``mode``.
        mode: "2d" or "3d".
        distance_m: target distance from the turn axis, m.
        seeds: one throw per seed (the start pose and the profile's randomness).
        profile_path: reality profile JSON, or None for the nominal twin.
        executor_config: keyword arguments of runtime.executor.ExecutorConfig (default its
            defaults: the release check on at its default radius).
        engine: physics engine of the simulated machine (sim_twin.twin.engines: "mujoco", "drake").

    Returns:
        One dict per throw: ``seed``, ``status`` ("landed", a failure, or "refused" with the
        executor's ``reason``), ``held_releases`` (release flags the release check held) and for
        landed throws ``impact_m``, ``downrange_error_m``, ``crossrange_error_m`` (m),
        ``duration_s`` (swing start to impact), ``release_after_s``, and the payload's release as
        the simulated machine flew it: ``release_pos_m`` (3,) m, ``release_vel_mps`` (3,) m/s
        (machine frame, at the opening) and ``flight_s`` (opening to impact).

    Raises:
        ValueError, OSError: the policy or profile cannot be loaded.
    """
    from runtime.executor import ExecutorConfig, ThrowExecutor
    from runtime.policy import PolicyRunner
    from runtime.protocol.messages import ThrowRequest
    from runtime.release_check import ReleaseCheck
    from sim_twin.twin.engines import make_machine
    from sim_twin.twin.profile import RealityProfile
    from sim_twin.twin.twin_machine import TwinMachine, run_throw

    policy = PolicyRunner.load(policy_path)
    profile = RealityProfile.load(profile_path) if profile_path else RealityProfile()
    config = ExecutorConfig(**(executor_config or {}))
    check = ReleaseCheck.load() if config.release_check_radius_m is not None else None  # one for the batch
    rows = []
    for seed in seeds:
        sim = make_machine(engine, profile, seed=seed)
        sim.reset(cabin_turn=0.0 if mode == "2d" else None)
        twin = TwinMachine(sim, "eval")
        executor = ThrowExecutor({mode: policy}, config=config, release_check=check)
        req = ThrowRequest(throw_id=f"eval-{seed}", machine_id="eval", mode=mode, target_m=target_on_axis(mode, distance_m))
        outcome, events = run_throw(twin, executor, req)
        if outcome is None:
            rows.append({"seed": seed, "status": "refused", "reason": events})
            continue
        swing = next((e.stamp_s for e in events if e.phase == "swinging"), None)
        held = sum(1 for e in events if (e.detail or "").startswith("release held"))
        row = {"seed": seed, "status": outcome.status, "reason": outcome.failure_reason, "held_releases": held}
        if outcome.status == "landed":
            row.update(
                impact_m=outcome.impact_m.tolist(),
                downrange_error_m=outcome.downrange_error_m,
                crossrange_error_m=outcome.crossrange_error_m,
                duration_s=(outcome.impact.impact_stamp_s - swing) if swing is not None else None,
                release_after_s=(outcome.release_stamp_s - swing) if swing is not None else None,
            )
            if sim.impact is not None:
                row.update(release_pos_m=sim.impact.release_pos_m.tolist(), release_vel_mps=sim.impact.release_vel_mps.tolist(),
                           flight_s=sim.impact.impact_time_s - sim.impact.opening_time_s)
        rows.append(row)
    return rows


def throw_seeds(seed: int, target_index: int, throws: int) -> list[int]:
    """The start-pose seeds of ``throws`` throws at the ``target_index``-th target of an evaluation
    or site matrix made with ``seed``: the same start poses at that target in every profile."""
    return [seed * 1_000_003 + target_index * 100_000 + k for k in range(throws)]


SWEEP_DISTANCES = 5
"""Target distances of :func:`twin_sweep` by default, spanning the declared range (the policy
validation's default too, server.config.Settings.validation_distances)."""
SWEEP_THROWS_PER_DISTANCE = 20
"""Throws per distance of :func:`twin_sweep` by default (server.config.Settings.validation_throws_per_distance).
CHOSEN: 20 lets the nominal success bar judge each distance (2D: every throw released; 3D: all but
one) and costs a few seconds on one core; with 2 a version that releases in some of its throws
at a distance and holds the rest passed (throw2d-scratch-aw at 6.4 m, tests/test_release_sweep.py)."""


def twin_sweep(onnx_path: str | Path, mode: str, target_range_m, distances: int = SWEEP_DISTANCES,
               throws_per_distance: int = SWEEP_THROWS_PER_DISTANCE, seed: int = 0) -> tuple[str | None, int]:
    """Twin throws over a policy's declared target range, the policy validation's sweep
    (server.policies.validation) and the training gate's release check (sim_twin.evaluation.matrix):
    ``distances`` distances spanning ``target_range_m`` (its middle for one), ``throws_per_distance``
    throws each (:func:`throw_batch`, nominal twin, start-pose seeds from ``seed``).

    Only failures caused by the policy count: a policy error or non-finite action, and a distance at
    which the policy asked to release in fewer of its throws than the site matrix's nominal success
    bar asks of a cell (sim_twin.evaluation.matrix.success_bar: 98 % in 2D, 95 % in 3D). The
    runtime ends a throw without a release after its release timeout, the load still in the
    gripper: a version that does not throw at part of the range it declares, e.g. one trained with
    γ 1.0 to wait there for training's forced release (docs/training.md), fails. A throw that
    misses, or whose every release the release check held, is the evaluation's business.

    Returns:
        (why it failed, or None; throws made).

    Raises:
        ValueError, OSError: the policy cannot be loaded (:func:`throw_batch`).
    """
    from sim_twin.evaluation.matrix import success_bar  # the matrix imports this module

    bar = success_bar(mode)
    lo, hi = target_range_m
    made = 0
    for k, d in enumerate(np.linspace(lo, hi, distances) if distances > 1 else [0.5 * (lo + hi)] * distances):
        seeds = [seed + 1000 * k + j for j in range(throws_per_distance)]
        unreleased = 0
        reason = ""
        for row in throw_batch(onnx_path, mode, float(d), seeds, None):
            made += 1
            why = str(row.get("reason") or "")
            if row["status"] == "failed" and ("policy" in why or "non-finite" in why):
                return f"twin throw at {d:.2f} m (start pose seed {row['seed']}) failed: {why}", made
            if row["status"] == "failed" and why.startswith("no release") and not row.get("held_releases"):
                unreleased, reason = unreleased + 1, why
        asked = len(seeds) - unreleased
        if seeds and asked < bar * len(seeds):
            told = "none" if asked == 0 else f"only {asked}"
            return (f"the policy asked to release in {told} of its {len(seeds)} twin throws at {d:.2f} m, inside its "
                    f"declared range {lo:g}-{hi:g} m (the nominal success bar is {bar:.0%}; {reason})"), made
    return None, made


def summarise(distance_m: float, rows: list[dict], per_throw: bool = False) -> dict:
    """Per-target statistics: success rate (released, landed, no collision), mean impact
    distance, bias (mean downrange error), sigma downrange / crossrange, mean crossrange,
    mean throw duration (swing start to impact), the failure reasons and how many throws had a
    release held by the release check (runtime.executor).

    With ``per_throw`` also ``"per_throw"``: ``{"seed": [n], "downrange_error_m": [n],
    "crossrange_error_m": [n]}`` ordered by seed, errors in m (0.1 mm resolution) and None for a
    throw that did not land. A throw's seed fixes its start pose and the profile's randomness, so
    two policies' throws of one seed are a matched pair (sim_twin.evaluation.matrix_compare pairs them)."""
    landed = [r for r in rows if r["status"] == "landed"]
    dr = np.array([r["downrange_error_m"] for r in landed])
    cr = np.array([r["crossrange_error_m"] for r in landed])
    dur = np.array([r["duration_s"] for r in landed if r.get("duration_s") is not None])
    reasons: dict[str, int] = {}
    for r in rows:
        if r["status"] != "landed":
            reasons[str(r.get("reason"))] = reasons.get(str(r.get("reason")), 0) + 1

    def stat(fn, a):
        return float(fn(a)) if a.size else None

    return {
        "target_m": distance_m,
        "throws": len(rows),
        "landed": len(landed),
        "success_rate": len(landed) / max(len(rows), 1),
        "mean_impact_m": stat(np.mean, dr + distance_m) if dr.size else None,
        "bias_m": stat(np.mean, dr),
        "sigma_downrange_m": stat(np.std, dr),
        "mean_crossrange_m": stat(np.mean, cr),
        "sigma_crossrange_m": stat(np.std, cr),
        "mean_abs_error_m": stat(np.mean, np.hypot(dr, cr)) if dr.size else None,
        "mean_duration_s": stat(np.mean, dur),
        "failures": reasons,
        "held_throws": sum(1 for r in rows if r.get("held_releases")),
    } | ({"per_throw": _per_throw(rows)} if per_throw else {})


def _per_throw(rows: list[dict]) -> dict[str, list]:
    """Seeds and landing errors of ``rows`` ordered by seed (see :func:`summarise`)."""
    rows = sorted(rows, key=lambda r: r["seed"])

    def err(r: dict, key: str) -> float | None:
        return round(float(r[key]), 4) if r["status"] == "landed" else None

    return {"seed": [int(r["seed"]) for r in rows], "downrange_error_m": [err(r, "downrange_error_m") for r in rows],
            "crossrange_error_m": [err(r, "crossrange_error_m") for r in rows]}


def evaluate(
    policy_path: Path,
    mode: str,
    distances_m: list[float],
    throws: int,
    profile_path: Path | None = None,
    seed: int = 0,
    workers: int | None = None,
    batch: int = 10,
    engine: str = "mujoco",
    per_throw: bool = False,
) -> dict:
    """Run the protocol; returns the report dict (see summarise; ``engine`` names the physics
    engine of the simulated machine, sim_twin.twin.engines; ``per_throw`` keeps each throw's errors by
    seed in every target). Logs progress."""
    workers = workers or os.cpu_count() or 1
    jobs = []
    for i, d in enumerate(distances_m):
        seeds = throw_seeds(seed, i, throws)
        jobs += [(d, seeds[j : j + batch]) for j in range(0, throws, batch)]
    results: dict[float, list[dict]] = {d: [] for d in distances_m}
    t0, done = time.time(), 0
    prof = str(profile_path) if profile_path else None
    with process_pool(workers) as pool:
        futs = {pool.submit(throw_batch, str(policy_path), mode, d, s, prof, None, engine): d for d, s in jobs}
        for fut in as_completed(futs):
            results[futs[fut]] += fut.result()
            done += 1
            n = sum(len(v) for v in results.values())
            log.info("evaluate: %d/%d throws (%.0f s)", n, throws * len(distances_m), time.time() - t0)
    from runtime.policy import PolicyRunner

    return {
        "policy": str(policy_path),
        "policy_version": PolicyRunner.load(policy_path).version,
        "mode": mode,
        "profile": prof or "nominal",
        "engine": engine,
        "throws_per_target": throws,
        "seed": seed,
        "wall_s": time.time() - t0,
        "targets": [summarise(d, results[d], per_throw=per_throw) for d in distances_m],
    }
