"""Sim-to-sim evaluation of an ONNX policy by the paper's protocol (Sec. IV-A).

Each throw runs the runtime's own ThrowExecutor (observation builder, ONNX policy, PID +
feed-forward controller, state machine) on the simulated machine (CPU MuJoCo twin with the
hydraulic valve model of its reality profile), exactly as on the machine but without Zenoh:
a different controller and actuation from the training environment, as the paper evaluated in
Gazebo rather than Isaac Gym. Every throw starts from a random collision-free pose at rest with
the gripper hanging still (3D: cabin anywhere); targets lie on the downrange axis (2D: in the
arm's plane).

``slinger evaluate --policy policies/throw2d.onnx --targets 7.5:10:0.5 --throws 200`` writes a
JSON report and the paper's figure (mean impact with 1 sigma bars against the target). Work is
spread over all cores; progress is logged.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from runtime.entrypoint import module_main
from runtime.throw_geometry import ARM_PLANE_OFFSET_M

log = logging.getLogger(__name__)


def target_on_axis(mode: str, distance_m: float) -> list[float]:
    """Ground target at ``distance_m`` from the turn axis on the evaluation axis (machine
    frame): in the arm's plane for 2D (cabin at 0), on the x axis for 3D."""
    if mode == "2d":
        return [math.sqrt(distance_m**2 - ARM_PLANE_OFFSET_M**2), ARM_PLANE_OFFSET_M, 0.0]
    return [distance_m, 0.0, 0.0]


def _throw_batch(policy_path: str, mode: str, distance_m: float, seeds: list[int], profile_path: str | None,
                 executor_config: dict | None = None) -> list[dict]:
    """Worker: throws at one target distance, one per seed. Returns one dict per throw (with
    ``held_releases``: release flags the release check held). ``executor_config``: keyword
    arguments of runtime.executor.ExecutorConfig (default its defaults)."""
    from runtime.executor import ExecutorConfig, ThrowExecutor
    from runtime.policy import PolicyRunner
    from runtime.protocol.messages import ThrowRequest
    from sim_twin.plant import TwinMachine, run_throw
    from sim_twin.profile import RealityProfile
    from sim_twin.simulated_machine import SimulatedMachine

    policy = PolicyRunner.load(policy_path)
    profile = RealityProfile.load(profile_path) if profile_path else RealityProfile()
    rows = []
    for seed in seeds:
        sim = SimulatedMachine(profile, seed=seed)
        sim.reset(cabin_turn=0.0 if mode == "2d" else None)
        twin = TwinMachine(sim, "eval")
        executor = ThrowExecutor({mode: policy}, config=ExecutorConfig(**(executor_config or {})))
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
        rows.append(row)
    return rows


def summarise(distance_m: float, rows: list[dict]) -> dict:
    """Per-target statistics: success rate (released, landed, no collision), mean impact
    distance, bias (mean downrange error), sigma downrange / crossrange, mean crossrange,
    mean throw duration (swing start to impact), the failure reasons and how many throws had a
    release held by the release check (runtime.executor)."""
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
    }


def evaluate(
    policy_path: Path,
    mode: str,
    distances_m: list[float],
    throws: int,
    profile_path: Path | None = None,
    seed: int = 0,
    workers: int | None = None,
    batch: int = 10,
) -> dict:
    """Run the protocol; returns the report dict (see summarise). Logs progress."""
    workers = workers or os.cpu_count() or 1
    jobs = []
    for i, d in enumerate(distances_m):
        seeds = [seed * 1_000_003 + i * 100_000 + k for k in range(throws)]
        jobs += [(d, seeds[j : j + batch]) for j in range(0, throws, batch)]
    results: dict[float, list[dict]] = {d: [] for d in distances_m}
    t0, done = time.time(), 0
    prof = str(profile_path) if profile_path else None
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futs = {pool.submit(_throw_batch, str(policy_path), mode, d, s, prof): d for d, s in jobs}
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
        "throws_per_target": throws,
        "seed": seed,
        "wall_s": time.time() - t0,
        "targets": [summarise(d, results[d]) for d in distances_m],
    }


def plot_reports(reports: list[dict], out: Path) -> None:
    """The paper's figure: mean impact distance with 1 sigma bars against the target distance,
    one panel per report (2D and 3D side by side)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(reports), figsize=(5.2 * len(reports), 4.4), squeeze=False)
    for ax, rep in zip(axes[0], reports):
        rows = [t for t in rep["targets"] if t["landed"]]
        d = np.array([t["target_m"] for t in rows])
        ax.plot([d.min() - 0.5, d.max() + 0.5], [d.min() - 0.5, d.max() + 0.5], "k--", lw=0.8, label="target")
        ax.errorbar(d, [t["mean_impact_m"] for t in rows], yerr=[t["sigma_downrange_m"] for t in rows], fmt="o", capsize=4, label="mean impact ± 1σ downrange")
        ax.errorbar(d + 0.08, [t["target_m"] + t["mean_crossrange_m"] for t in rows], yerr=[t["sigma_crossrange_m"] for t in rows],
                    fmt="s", ms=3, capsize=3, alpha=0.7, label="target + mean crossrange ± 1σ")
        ax.set_xlabel("target distance [m]")
        ax.set_ylabel("impact distance [m]")
        name = rep.get("policy_version", rep["mode"])
        ax.set_title(f"{rep['mode'].upper()} policy {name}, {rep['throws_per_target']} throws/target ({rep['profile']} twin)", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def markdown_table(report: dict) -> str:
    """The per-target statistics of a report as a Markdown table (for docs and reports)."""
    head = (f"**{report['mode'].upper()} `{report.get('policy_version', report['policy'])}`**, "
            f"{report['throws_per_target']} throws per target, {report['profile']} profile\n\n"
            "| target [m] | success | mean impact [m] | bias [m] | σ downrange [m] | mean crossrange [m] | σ crossrange [m] | duration [s] |\n"
            "|---|---|---|---|---|---|---|---|\n")
    rows = []
    for t in report["targets"]:
        def f(key, fmt="{:+.3f}"):
            return "n/a" if t[key] is None else fmt.format(t[key])
        rows.append(f"| {t['target_m']:.1f} | {100 * t['success_rate']:.1f} % | {f('mean_impact_m', '{:.3f}')} | {f('bias_m')} | "
                    f"{f('sigma_downrange_m', '{:.3f}')} | {f('mean_crossrange_m')} | {f('sigma_crossrange_m', '{:.3f}')} | "
                    f"{f('mean_duration_s', '{:.2f}')} |")
    return head + "\n".join(rows) + "\n"


def parse_targets(spec: str) -> list[float]:
    """"8.5" or "7.5,8" or "7.5:10:0.5" (start:stop:step, stop included) -> distances in m.

    Raises:
        ValueError: malformed spec or a non-positive step.
    """
    if ":" in spec:
        a, b, s = (float(x) for x in spec.split(":"))
        if s <= 0:
            raise ValueError("target step must be > 0")
        return [round(a + k * s, 6) for k in range(int(math.floor((b - a) / s + 1e-9)) + 1)]
    return [float(x) for x in spec.split(",")]


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policy", type=Path, default=Path("policies/throw2d.onnx"))
    parser.add_argument("--targets", default=None, help="2D default 7.5:10:0.5, 3D default 7:9.5:0.5")
    parser.add_argument("--throws", type=int, default=200, help="throws per target")
    parser.add_argument("--profile", type=Path, default=None, help="reality profile JSON (default nominal)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--out", type=Path, default=None, help="JSON report (default reports/eval_<mode>.json)")
    parser.add_argument("--plot", type=Path, default=None, help="PNG figure (default beside the JSON)")
    parser.add_argument("--matrix", action="store_true",
                        help="run the site matrix (nominal + sim_twin/profiles site profiles, sim_twin.matrix) and write "
                             "reports/site_matrix_<mode>.json/.md/.png (or --out); default 100 throws per target")
    parser.add_argument("--combine", type=Path, nargs="+", default=None,
                        help="only draw the figure of these JSON reports side by side (e.g. 2D and 3D) to --plot")


def run(args: argparse.Namespace) -> int:
    from runtime.policy import PolicyRunner

    if args.combine:
        reports = [json.loads(p.read_text()) for p in args.combine]
        plot_reports(reports, args.plot or Path("reports/eval.png"))
        print("\n".join(markdown_table(r) for r in reports))
        return 0

    mode = PolicyRunner.load(args.policy).mode
    targets = parse_targets(args.targets or ("7.5:10:0.5" if mode == "2d" else "7:9.5:0.5"))
    if args.matrix:
        from sim_twin import matrix

        throws = 100 if args.throws == 200 else args.throws  # 200 is the single-profile default
        rep = matrix.run_matrix(args.policy, mode, targets, throws, seed=args.seed, workers=args.workers)
        out = args.out or Path("reports") / f"site_matrix_{mode}.json"
        matrix.write(rep, out)
        log.info("site matrix %s: all bars met: %s; %s", mode, rep["pass"], out.with_suffix(".md"))
        return 0
    report = evaluate(args.policy, mode, targets, args.throws, args.profile, args.seed, args.workers)
    out = args.out or Path("reports") / f"eval_{mode}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    plot_reports([report], args.plot or out.with_suffix(".png"))
    for t in report["targets"]:
        log.info(
            "target %.2f m: success %.0f%%, bias %s m, sigma down %s m, sigma cross %s m, mean |error| %s m",
            t["target_m"], 100 * t["success_rate"], _fmt(t["bias_m"]), _fmt(t["sigma_downrange_m"]),
            _fmt(t["sigma_crossrange_m"]), _fmt(t["mean_abs_error_m"]),
        )
    log.info("report: %s", out)
    return 0


def _fmt(x) -> str:
    return "n/a" if x is None else f"{x:+.3f}"


def main(argv: list[str] | None = None) -> int:
    return module_main('slinger evaluate', __doc__, build_parser, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
