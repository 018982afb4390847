"""Effect of the release check on site-matrix cells (sim_twin.evaluation.matrix seeds and protocol).

    nice -n 10 python tests/benchmarks/release_check_matrix.py --out reports/release_check_matrix.json
    nice -n 10 python tests/benchmarks/release_check_matrix.py --only 3d:nominal --out reports/release_check_matrix_3d_nominal.json

Each cell runs its 100 throws twice, release check off (``release_check_radius_m=None``) and on
(runtime.executor.ExecutorConfig's default), on the same seeds (``i * 100_000 + k``, i the
target's index in 7:9.5:0.5 (3D) or 7.5:10:0.5 (2D), as ``slinger evaluate --matrix``). Per cell:
success, sigma downrange / crossrange, wild throws (landed > 5 m from the target), throws with a
held release, and throws that landed within 3 m with the check off but not with it on.
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from sim_twin.evaluation.evaluate import summarise, throw_batch

PROFILES = Path(__file__).resolve().parents[2] / "sim_twin" / "profiles"
CELLS = (  # (policy, mode, profile or None, [(target m, index)])
    [("policies/throw3d.onnx", "3d", p, [(8.0, 2), (8.5, 3), (9.0, 4), (9.5, 5)]) for p in ("slow_hydraulics", "slow_latent_noisy")]
    + [("policies/throw2d.onnx", "2d", None, [(7.5 + 0.5 * i, i) for i in range(6)])]
    + [("policies/throw3d.onnx", "3d", None, [(7.0 + 0.5 * i, i) for i in range(6)])]
)
WILD_M = 5.0


def _miss(r: dict) -> float:
    return float(np.hypot(r["downrange_error_m"], r["crossrange_error_m"])) if r["status"] == "landed" else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--throws", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--only", default=None, help="MODE:PROFILE, e.g. 3d:nominal (default every cell)")
    args = ap.parse_args()
    t0, jobs = time.time(), []
    with ProcessPoolExecutor(args.workers) as pool:
        for pol, mode, prof, targets in CELLS:
            if args.only and args.only != f"{mode}:{prof or 'nominal'}":
                continue
            path = str(PROFILES / f"{prof}.json") if prof else None
            for d, i in targets:
                seeds = [i * 100_000 + k for k in range(args.throws)]
                for cfg in ({"release_check_radius_m": None}, None):
                    futs = [pool.submit(throw_batch, pol, mode, d, seeds[j:j + 25], path, cfg) for j in range(0, len(seeds), 25)]
                    jobs.append((mode, prof or "nominal", d, cfg is None, futs))
        cells: dict = {}
        for mode, prof, d, on, futs in jobs:
            cells.setdefault((mode, prof, d), {})["on" if on else "off"] = [r for f in futs for r in f.result()]
    report = []
    for (mode, prof, d), runs in cells.items():
        off, on = runs["off"], runs["on"]
        row = {"mode": mode, "profile": prof, "target_m": d}
        for key, rows in (("off", off), ("on", on)):
            s = summarise(d, rows)
            row[key] = {"success": s["success_rate"], "sigma_down_m": s["sigma_downrange_m"], "sigma_cross_m": s["sigma_crossrange_m"],
                        "wild": sum(1 for r in rows if _miss(r) > WILD_M), "held_throws": s["held_throws"], "failures": s["failures"],
                        "largest_miss_m": float(np.nanmax([_miss(r) for r in rows]))}
        row["normal_lost"] = [a["seed"] for a, b in zip(off, on) if _miss(a) <= 3.0 and not _miss(b) <= 3.0]
        row["changed"] = sum(1 for a, b in zip(off, on) if a.get("impact_m") != b.get("impact_m"))
        row["held"] = [{"seed": b["seed"], "holds": b["held_releases"], "off": [a["status"], round(_miss(a), 2)],
                        "on": [b["status"], round(_miss(b), 2), b["reason"]]} for a, b in zip(off, on) if b.get("held_releases")]
        report.append(row)
        f, n = row["off"], row["on"]
        print(f"{mode} {prof:17s} {d:4.1f} | off: success {100 * f['success']:3.0f} % sigma {f['sigma_down_m']:.3f}/{f['sigma_cross_m']:.3f} wild {f['wild']} "
              f"max {f['largest_miss_m']:.1f} | on: success {100 * n['success']:3.0f} % sigma {n['sigma_down_m']:.3f}/{n['sigma_cross_m']:.3f} "
              f"wild {n['wild']} max {n['largest_miss_m']:.1f} held {n['held_throws']} | changed {row['changed']} normal lost {row['normal_lost']}", flush=True)
        for h in row["held"]:
            print(f"    held: seed {h['seed']} x{h['holds']}: off {h['off']} -> on {h['on']}")
    print(f"wall {time.time() - t0:.0f} s")
    if args.out:
        args.out.write_text(json.dumps({"throws_per_cell": args.throws, "cells": report}, indent=1) + "\n")


if __name__ == "__main__":
    main()
