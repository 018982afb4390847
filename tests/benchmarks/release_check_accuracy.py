"""Accuracy and cost of the release check's impact predictor (runtime.release_check).

    nice -n 10 python tests/benchmarks/release_check_accuracy.py --throws 100 --out reports/release_check_accuracy.json

Throws of the deployed policies on the twin by sim_twin.evaluation.evaluate's protocol (seeds of the site
matrix, ``i * 100_000 + k`` with i the target's index in 7.5:10:0.5 (2D) or 7:9.5:0.5 (3D)), with
a release check that never holds (radius 1e9 m) so that every release is the policy's own. For
each landed throw: the executor's own prediction at the release command (measured state and the
release step's references) against the measured impact (horizontal distance, m); for comparison
the prediction without the references (active joints keep their measured velocities) and the
naive one (drag-free flight of the gripper centre from the state AT the command). Prints median /
p99 / max per cell and the time per prediction.
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

CELLS = [  # (policy, mode, target m, index in the matrix's target list, profile or None)
    ("policies/throw2d.onnx", "2d", 7.5, 0, None),
    ("policies/throw2d.onnx", "2d", 10.0, 5, None),
    ("policies/throw3d.onnx", "3d", 7.0, 0, None),
    ("policies/throw3d.onnx", "3d", 9.5, 5, None),
    ("policies/throw2d.onnx", "2d", 7.5, 0, "sim_twin/profiles/slow_hydraulics.json"),
    ("policies/throw2d.onnx", "2d", 10.0, 5, "sim_twin/profiles/slow_hydraulics.json"),
    ("policies/throw3d.onnx", "3d", 7.0, 0, "sim_twin/profiles/slow_hydraulics.json"),
    ("policies/throw3d.onnx", "3d", 9.5, 5, "sim_twin/profiles/slow_hydraulics.json"),
]


def release_errors(policy_path: str, mode: str, distance_m: float, seeds: list[int], profile_path: str | None) -> list[dict]:
    """Worker: one throw per seed with the check off; per landed throw the predictor's and the
    naive prediction's horizontal error (m) and the prediction's wall time (s)."""
    from runtime.ballistics import ground_impact
    from runtime.executor import ExecutorConfig, ThrowExecutor
    from runtime.machine import forward_kinematics
    from runtime.policy import PolicyRunner
    from runtime.protocol.messages import ThrowRequest
    from runtime.release_check import ReleaseCheck
    from sim_twin.evaluation.evaluate import target_on_axis
    from sim_twin.twin.twin_machine import TwinMachine, run_throw
    from sim_twin.twin.profile import RealityProfile
    from sim_twin.twin.simulated_machine import SimulatedMachine

    check = ReleaseCheck.load()
    predictor = check.predictor
    assert predictor is not None, check.unavailable
    policy = PolicyRunner.load(policy_path)
    profile = RealityProfile.load(profile_path) if profile_path else RealityProfile()
    class Recording:  # the executor's predictor, keeping its last call
        def predict(self, q, qd, qd_ref=None):
            t0 = time.perf_counter()
            self.hit = predictor.predict(q, qd, qd_ref)
            self.dt = time.perf_counter() - t0
            return self.hit

    rows = []
    for seed in seeds:
        sim = SimulatedMachine(profile, seed=seed)
        sim.reset(cabin_turn=0.0 if mode == "2d" else None)
        rec = Recording()
        ex = ThrowExecutor({mode: policy}, config=ExecutorConfig(release_check_radius_m=1e9), release_check=ReleaseCheck(rec))
        req = ThrowRequest(throw_id=f"acc-{seed}", machine_id="eval", mode=mode, target_m=target_on_axis(mode, distance_m))
        outcome, _ = run_throw(TwinMachine(sim, "eval"), ex, req)
        if outcome is None or outcome.status != "landed":
            continue
        tick = next(r for r in outcome.telemetry.rows if r["t_s"] == outcome.release_stamp_s)
        q, qd = np.array(tick["q"]), np.array(tick["qd"])
        hit, dt, const = rec.hit, rec.dt, predictor.predict(q, qd)
        pts = forward_kinematics(np, q, qd)
        p0, v0 = np.asarray(pts.gripper_centre), np.asarray(pts.gripper_centre_vel)
        naive, _ = ground_impact(p0, v0)
        actual, target = np.asarray(outcome.impact_m), np.asarray(req.target_m)
        rows.append({"seed": seed, "error_m": float(np.hypot(*(hit - actual)[:2])), "const_error_m": float(np.hypot(*(const - actual)[:2])),
                     "naive_error_m": float(np.hypot(*(naive - actual)[:2])), "predict_s": dt,
                     "miss_m": float(np.hypot(*(actual - target)[:2])), "predicted_miss_m": float(np.hypot(*(hit - target)[:2]))})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--throws", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    t0 = time.time()
    with ProcessPoolExecutor(args.workers) as pool:
        futs = []
        for pol, mode, d, i, prof in CELLS:
            seeds = [i * 100_000 + k for k in range(args.throws)]
            futs.append([pool.submit(release_errors, pol, mode, d, seeds[j:j + 25], prof) for j in range(0, len(seeds), 25)])
        report = []
        for (pol, mode, d, _, prof), fs in zip(CELLS, futs):
            rows = [r for f in fs for r in f.result()]
            e, v, n, c = (np.array([r[k] for r in rows]) for k in ("error_m", "const_error_m", "naive_error_m", "predict_s"))
            cell = {"mode": mode, "target_m": d, "profile": Path(prof).stem if prof else "nominal", "landed": len(rows),
                    "median_m": float(np.median(e)), "p99_m": float(np.quantile(e, 0.99)), "max_m": float(e.max()),
                    "const_median_m": float(np.median(v)), "const_p99_m": float(np.quantile(v, 0.99)), "const_max_m": float(v.max()),
                    "naive_median_m": float(np.median(n)), "naive_p99_m": float(np.quantile(n, 0.99)), "naive_max_m": float(n.max()),
                    "largest_predicted_miss_m": max(r["predicted_miss_m"] for r in rows), "largest_miss_m": max(r["miss_m"] for r in rows),
                    "worst": sorted(rows, key=lambda r: -r["error_m"])[:3],
                    "predict_ms_median": 1e3 * float(np.median(c)), "predict_ms_max": 1e3 * float(c.max())}
            report.append(cell)
            print(f"{mode} {d:4.1f} m {cell['profile']:16s} n={len(rows):3d}  predictor median {cell['median_m']:.2f} p99 {cell['p99_m']:.2f} "
                  f"max {cell['max_m']:.2f} | const-vel {cell['const_median_m']:.2f} / {cell['const_p99_m']:.2f} / {cell['const_max_m']:.2f} | naive {cell['naive_median_m']:.2f} / {cell['naive_p99_m']:.2f} / {cell['naive_max_m']:.2f} m | "
                  f"{cell['predict_ms_median']:.2f} ms (max {cell['predict_ms_max']:.2f}) | largest predicted miss {cell['largest_predicted_miss_m']:.2f}, "
                  f"actual {cell['largest_miss_m']:.2f} m", flush=True)
    print(f"wall {time.time() - t0:.0f} s")
    if args.out:
        args.out.write_text(json.dumps({"throws_per_cell": args.throws, "cells": report}, indent=1) + "\n")


if __name__ == "__main__":
    main()
