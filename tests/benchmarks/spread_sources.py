"""Where a policy's downrange spread comes from: the site matrix's nominal cell with one source of
randomness removed at a time, and how sensitive the landing point is to the release instant.

    nice -n 10 python tests/benchmarks/spread_sources.py --policy policies/throw2d.onnx \
        --checkpoint policies/training/throw2d-scratch-j/checkpoint.pt --throws 100 \
        --out reports/spread_sources_2d.json

(``--checkpoint`` exports an rsl_rl checkpoint of the 2D recipe to ONNX first; needs the training
extra. ``throw2d-scratch-j`` is in the lab notebook: ``git checkout lab-notebook-2026-11-25 --
policies/training/throw2d-scratch-j`` first, policies/training/ARCHIVE.md.)

A nominal throw of the simulated machine has four sources of scatter: the random start pose, the
gripper's opening delay (258 ms, sigma 15 ms: ``RealityProfile.release_delay_std_s``), the sensor
noise (``SensorParams``) and the noise of the measured impact. Each variant below switches some of
them off (profile ``release_delay_std_s`` 0, ``SensorParams.ideal()``); what is left with all of
them off is the spread the policy makes from the start pose alone. The start poses are the site
matrix's for seed 0 (``i * 100_000 + k``, i the target's index in 7.5:10:0.5 m), so the nominal
variant reproduces the matrix's nominal cells.

For each landed throw it also records the **release sensitivity**: the rate at which the drag-free
landing point of the gripper centre moves along the ground with the release instant, m/s, from
the telemetry rows (100 Hz) one tick before and after the gripper opened (central difference).
Multiplied by the release-delay sigma it is the spread that the gripper's own timing alone puts on
the landing point.

Prints one line per (policy, variant, target) and writes a JSON report (``--out``).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from concurrent.futures import as_completed
from pathlib import Path

import numpy as np

TARGETS_2D = [7.5, 8.0, 8.5, 9.0, 9.5, 10.0]  # the site matrix's 2D targets (index = seed block)
VARIANTS = {  # name -> profile dict (None = the nominal twin)
    "nominal": None,
    "no_release_jitter": {"name": "no_release_jitter", "release_delay_std_s": 0.0},
    "ideal_sensing": {"name": "ideal_sensing", "sensing": {k: 0.0 for k in (
        "encoder_noise_rad", "encoder_rate_noise_radps", "imu_latency_s", "imu_angle_noise_rad", "imu_rate_noise_radps", "impact_noise_m")}},
    "start_pose_only": {"name": "start_pose_only", "release_delay_std_s": 0.0, "sensing": {k: 0.0 for k in (
        "encoder_noise_rad", "encoder_rate_noise_radps", "imu_latency_s", "imu_angle_noise_rad", "imu_rate_noise_radps", "impact_noise_m")}},
}


def _ground_range(q: np.ndarray, qd: np.ndarray) -> float:
    """Horizontal distance from the turn axis (m) at which the gripper centre, released in state
    (q, qd) (rad, m; machine frame), lands in drag-free flight (runtime.ballistics)."""
    from runtime.ballistics import ground_impact
    from runtime.machine import forward_kinematics

    pts = forward_kinematics(np, q, qd)
    hit, _ = ground_impact(np.asarray(pts.gripper_centre, dtype=float), np.asarray(pts.gripper_centre_vel, dtype=float))
    return float(np.hypot(hit[0], hit[1]))


def throws(policy_path: str, distance_m: float, seeds: list[int], profile: dict | None) -> list[dict]:
    """Worker: one 2D throw per seed on the simulated machine of ``profile`` (a RealityProfile
    dict, None = nominal) by the runtime's executor with its release check on (as the site
    matrix). Returns per landed throw: ``seed``, ``downrange_error_m``, ``release_after_s`` and
    ``release_sensitivity_mps`` (see the module docstring); failures as ``{"seed", "status"}``."""
    from runtime.executor import ExecutorConfig, ThrowExecutor
    from runtime.policy import PolicyRunner
    from runtime.protocol.messages import ThrowRequest
    from runtime.release_check import ReleaseCheck
    from sim_twin.evaluation.evaluate import target_on_axis
    from sim_twin.twin.twin_machine import TwinMachine, run_throw
    from sim_twin.twin.profile import RealityProfile
    from sim_twin.twin.simulated_machine import SimulatedMachine

    policy = PolicyRunner.load(policy_path)
    prof = RealityProfile.from_dict(profile) if profile else RealityProfile()
    check = ReleaseCheck.load()
    rows = []
    for seed in seeds:
        sim = SimulatedMachine(prof, seed=seed)
        sim.reset(cabin_turn=0.0)
        ex = ThrowExecutor({"2d": policy}, config=ExecutorConfig(), release_check=check)
        req = ThrowRequest(throw_id=f"spread-{seed}", machine_id="eval", mode="2d", target_m=target_on_axis("2d", distance_m))
        outcome, _ = run_throw(TwinMachine(sim, "eval"), ex, req)
        if outcome is None or outcome.status != "landed":
            rows.append({"seed": seed, "status": "refused" if outcome is None else outcome.status})
            continue
        ticks = outcome.telemetry.rows
        k = min(range(len(ticks)), key=lambda i: abs(ticks[i]["t_s"] - outcome.opening_stamp_s))
        a, b = ticks[max(k - 1, 0)], ticks[min(k + 1, len(ticks) - 1)]
        rate = (_ground_range(np.array(b["q"]), np.array(b["qd"])) - _ground_range(np.array(a["q"]), np.array(a["qd"]))) / (b["t_s"] - a["t_s"])
        rows.append({"seed": seed, "status": "landed", "downrange_error_m": outcome.downrange_error_m,
                     "release_after_s": outcome.release_stamp_s - ticks[0]["t_s"], "opening_delay_s": outcome.opening_stamp_s - outcome.release_stamp_s,
                     "start_q": list(map(float, ticks[0]["q"])),
                     "release_sensitivity_mps": rate})
    return rows


FIRST_SWING_S = 2.0
"""Release commands up to this long after the swing starts are first-swing throws (s): the 2D
policies release either at 0.9-1.6 s or after 2.8 s (reports/spread_sources_2d_scratch.png, in the lab notebook: reports/ARCHIVE.md)."""


def _sigma(e: np.ndarray) -> float | None:
    return float(e.std(ddof=1)) if len(e) > 1 else None


ACTIVE_2D = slice(1, 4)
"""The start pose's boom, dipper (rad) and telescope (m) in runtime.machine.JOINT_NAMES order: what the start
pose draws in 2D (the turn is 0 and the gripper hangs at rest below them)."""


def start_pose_offset(start_q: list[list[float]], first: np.ndarray) -> dict:
    """How far the first-swing and the later-swing throws' start poses lie from the cell's typical one:
    the mean over each group of the Euclidean norm of the start pose's boom, dipper and telescope, each
    standardised over the cell's landed throws (its mean and standard deviation), {"start_pose_offset_first",
    "start_pose_offset_later"} (dimensionless; None for an empty group). ``start_q``: (N, 6) start poses,
    ``first``: (N,) bool."""
    if not start_q:
        return {"start_pose_offset_first": None, "start_pose_offset_later": None}
    q = np.asarray(start_q, dtype=float)[:, ACTIVE_2D]
    z = np.linalg.norm((q - q.mean(axis=0)) / np.where(q.std(axis=0) > 0, q.std(axis=0), 1.0), axis=1)
    return {"start_pose_offset_first": _mean(z[first]), "start_pose_offset_later": _mean(z[~first])}


def _mean(e: np.ndarray) -> float | None:
    return float(e.mean()) if len(e) else None


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def cell(rows: list[dict]) -> dict:
    """Summary of one cell: landed count, bias and sigma of the downrange error (m), the median
    time from the swing's start to the release command (s) and the sigma of the throws released
    up to it and after it (m), the number of first-swing throws (released within FIRST_SWING_S),
    the sigma of those and of the later ones (m; None for fewer than two) and their mean errors
    (m; None for none: two release swings whose means differ add to the cell's sigma), the median absolute
    release sensitivity (m/s), the spread it implies with the nominal 15 ms release-delay sigma (m)
    and every row of :func:`throws`."""
    landed = [r for r in rows if r["status"] == "landed"]
    e = np.array([r["downrange_error_m"] for r in landed])
    s = np.abs(np.array([r["release_sensitivity_mps"] for r in landed]))
    t = np.array([r["release_after_s"] for r in landed])
    early = t <= np.median(t)
    first = np.round(t, 3) <= FIRST_SWING_S  # on the report's rounding: a release at 2.0000000001 s is one at 2.0 s
    return {"throws": len(rows), "landed": len(landed), "bias_m": float(e.mean()), "sigma_downrange_m": float(e.std(ddof=1)),
            "release_after_s_median": float(np.median(t)),
            "sigma_early_half_m": float(e[early].std(ddof=1)), "sigma_late_half_m": float(e[~early].std(ddof=1)),
            "first_swing_throws": int(first.sum()), "sigma_first_swing_m": _sigma(e[first]), "sigma_later_m": _sigma(e[~first]),
            "bias_first_swing_m": _mean(e[first]), "bias_later_m": _mean(e[~first]),
            **start_pose_offset([r["start_q"] for r in landed], first),
            "release_sensitivity_mps_median": float(np.median(s)), "jitter_spread_m": float(np.median(s) * 0.015),
            "rows": [_rounded(r) for r in rows]}


def _rounded(row: dict) -> dict:
    """``row`` with its floats to 4 decimals (0.1 mm, 0.1 ms), the report's resolution."""
    return {k: [round(x, 4) for x in v] if isinstance(v, list) else round(v, 4) if isinstance(v, float) else v for k, v in row.items()}


def plot(report: dict, out: Path) -> None:
    """Two panels: downrange sigma per variant, policy and target (m; bars), and each nominal
    throw's downrange error (m) against the time from swing start to the release command (s) at
    the farthest target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = report["cells"]
    policies = list(dict.fromkeys(c["policy"] for c in cells))
    variants = list(dict.fromkeys(c["variant"] for c in cells))
    targets = sorted({c["target_m"] for c in cells})
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(13, 4.8))
    groups = [(p, d) for p in policies for d in targets]
    width = 0.8 / len(variants)
    for j, v in enumerate(variants):
        ys = [next(c["sigma_downrange_m"] for c in cells if (c["policy"], c["target_m"], c["variant"]) == (p, d, v)) for p, d in groups]
        ax1.bar([i + (j - (len(variants) - 1) / 2) * width for i in range(len(groups))], ys, width, label=v.replace("_", " "))
    ax1.axhline(0.10, color="k", ls="--", lw=1, label="nominal bar 0.10 m")
    ax1.set_xticks(range(len(groups)), [f"{p}\n{d:g} m" for p, d in groups], fontsize=7, rotation=20)
    ax1.set_ylabel("downrange sigma [m]")
    ax1.set_title("spread with sources of scatter removed")
    ax1.legend(fontsize=7)
    far = targets[-1]
    for p in policies:
        rows = [r for c in cells if (c["policy"], c["variant"], c["target_m"]) == (p, "nominal", far) for r in c["rows"] if r["status"] == "landed"]
        ax2.scatter([r["release_after_s"] for r in rows], [r["downrange_error_m"] for r in rows], s=12, label=p)
    ax2.axhline(0, color="k", lw=0.8)
    ax2.set_xlabel("release command after swing start [s]")
    ax2.set_ylabel("downrange error [m]")
    ax2.set_title(f"nominal, {far:g} m: error against release time")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    from runtime.policy import PolicyRunner, sha256_of
    from sim_twin.twin.pools import process_pool

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policy", action="append", default=[],
                    help="2D ONNX policy, or NAME=PATH to label it NAME in the report (repeat to compare)")
    ap.add_argument("--checkpoint", action="append", default=[], type=Path,
                    help="rsl_rl checkpoint of the 2D recipe, exported to ONNX first (repeatable)")
    ap.add_argument("--config", type=Path, default=Path("sim_twin/configs/throw_2d.json"), help="the checkpoints' training config")
    ap.add_argument("--targets", default="9.5,10.0", help="comma-separated, from the matrix's 7.5:10:0.5 m")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--throws", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="JSON report (and its plot beside it, .png)")
    ap.add_argument("--plot-only", action="store_true", help="only draw the plot of the existing --out report")
    ap.add_argument("--resummarise", action="store_true",
                    help="summarise the existing --out report's cells again from their stored throws (cell()), and plot")
    args = ap.parse_args()
    if args.resummarise:
        if not args.out:
            ap.error("--resummarise needs --out")
        data = json.loads(args.out.read_text())
        keep = ("policy", "policy_file", "policy_sha256", "variant", "target_m")
        data["cells"] = [{**{k: c[k] for k in keep}, **cell(c["rows"])} for c in data["cells"]]
        args.out.write_text(json.dumps(data, indent=1) + "\n")
        plot(data, args.out.with_suffix(".png"))
        return
    if args.plot_only:
        if not args.out:
            ap.error("--plot-only needs --out")
        plot(json.loads(args.out.read_text()), args.out.with_suffix(".png"))
        return
    if not args.policy and not args.checkpoint:
        ap.error("give at least one --policy or --checkpoint")
    tmp = tempfile.TemporaryDirectory()
    for ckpt in args.checkpoint:  # named after the run's folder
        from sim_twin.training.export import export_checkpoint

        name = ckpt.parent.name
        args.policy.append(str(export_checkpoint(ckpt, json.loads(args.config.read_text()), Path(tmp.name) / f"{name}.onnx", name)))
    labels = {}  # path -> the report's name for it (NAME=PATH), else the manifest's version
    for i, spec in enumerate(args.policy):
        name, sep, path = spec.partition("=")
        if sep and not Path(spec).exists():
            args.policy[i], labels[path] = path, name
    targets = [float(x) for x in args.targets.split(",")]
    variants = args.variants.split(",")
    bad = [d for d in targets if d not in TARGETS_2D] + [v for v in variants if v not in VARIANTS]
    if bad:
        ap.error(f"unknown targets or variants: {bad} (targets {TARGETS_2D}, variants {list(VARIANTS)})")
    t0 = time.time()
    jobs = {}
    with process_pool(args.workers) as pool:
        for pol in args.policy:
            for v in variants:
                for d in targets:
                    seeds = [TARGETS_2D.index(d) * 100_000 + k for k in range(args.throws)]
                    for j in range(0, len(seeds), 10):
                        jobs[pool.submit(throws, pol, d, seeds[j:j + 10], VARIANTS[v])] = (pol, v, d)
        results: dict[tuple, list] = {key: [] for key in jobs.values()}
        for n, fut in enumerate(as_completed(jobs), 1):
            results[jobs[fut]] += fut.result()
            if n % 20 == 0:
                print(f"  {n}/{len(jobs)} batches ({time.time() - t0:.0f} s)", flush=True)
    report = []
    for pol in args.policy:
        for v in variants:
            for d in targets:
                name = labels.get(pol) or PolicyRunner.load(pol).version
                c = {"policy": name, "policy_file": Path(pol).name, "policy_sha256": sha256_of(pol), "variant": v, "target_m": d, **cell(results[(pol, v, d)])}
                report.append(c)
                print(f"{c['policy']:24s} {v:18s} {d:4.1f} m  landed {c['landed']:3d}/{c['throws']}  bias {c['bias_m']:+.3f}  "
                      f"sigma {c['sigma_downrange_m']:.3f} m  release at {c['release_after_s_median']:.2f} s (median; sigma before "
                      f"{c['sigma_early_half_m']:.3f}, after {c['sigma_late_half_m']:.3f} m)  release sensitivity {c['release_sensitivity_mps_median']:.2f} m/s "
                      f"(x 15 ms = {c['jitter_spread_m']:.3f} m)  first swing {c['first_swing_throws']} throws, sigma "
                      f"{_fmt(c['sigma_first_swing_m'])}, later {_fmt(c['sigma_later_m'])} m (bias {_fmt(c['bias_first_swing_m'])}, "
                      f"{_fmt(c['bias_later_m'])})", flush=True)
    print(f"wall {time.time() - t0:.0f} s")
    tmp.cleanup()
    if args.out:
        data = {"throws_per_cell": args.throws, "wall_s": time.time() - t0, "cells": report}
        args.out.write_text(json.dumps(data, indent=1) + "\n")
        plot(data, args.out.with_suffix(".png"))


if __name__ == "__main__":
    main()
