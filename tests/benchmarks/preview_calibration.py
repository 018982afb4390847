"""Calibration of the preview's 1 sigma impact ellipse against throws of the simulated machine.

For each of N throws (seeded): the simulated machine's TRUE parameters are drawn uniformly
within the site profile's uncertainty block (ranges; Gaussians for fitted sigmas), its start pose
is a random collision-free pose with the gripper hanging, a residual passive swing below the
executor's still threshold, and the preview is given the MEASURED pose (true pose plus encoder /
IMU error drawn from the profile's start-state model). The preview (sim_twin.preview.preview, the site
profile, ``--rollouts`` impacts from ``--param-rollouts`` full rollouts) predicts a mean and a
covariance; the true throw (the runtime's executor on the simulated machine with the drawn
parameters and release jitter) lands somewhere. Reported: the share of true impacts inside the
predicted 1 sigma ellipse (Mahalanobis distance <= 1; a 2-D Gaussian puts 39.3 % there; goal
30-50 %) and inside 2 sigma (86.5 %), for the honest preview and, every ``--compare-every``-th
throw, for the old one (release jitter only, nominal twin).

"True impact" is where the payload lands (the truth machine runs without impact-measurement
noise); the share for the MEASURED impact (true + the profile's impact noise, sigma per axis
``sensing.impact_noise_m``) against the ellipse widened by that noise is reported beside it
(``measured``), which is what a site check with a survey pole would see.

Rows carry the policy's name and ONNX SHA-256 and the profile's SHA-256: a resumed run keeps only
the rows made with the same policy, profile and Monte Carlo size (others are set aside, logged).

Run (about 5-15 min on 2 cores)::

    nice -n 10 python tests/benchmarks/preview_calibration.py --throws 200 \\
        --out reports/preview_calibration.json --plot reports/preview_calibration.png
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
log = logging.getLogger("preview_calibration")


def one_throw(policy_path: str, profile_path: str, mode: str, distance_m: float, seed: int, rollouts: int, param_rollouts: int,
              compare: bool = True) -> dict:
    """Worker: one true throw, its honest preview and (``compare``) the release-jitter-only one;
    returns the row (keys: seed, target_m, status, impact_m (true, m), impact_measured_m, honest,
    jitter_only, preview_s, cpu_s)."""
    from runtime.executor import ThrowExecutor
    from runtime.policy import PolicyRunner
    from runtime.protocol.messages import ThrowRequest
    from sim_twin.evaluation.evaluate import target_on_axis
    from sim_twin.twin.initial_pose import sample_pose
    from sim_twin.twin.twin_machine import TwinMachine, run_throw
    from sim_twin.preview.preview import PreviewRequest, preview_throw
    from sim_twin.twin.profile import RealityProfile
    from sim_twin.twin.simulated_machine import SimulatedMachine
    from sim_twin.twin.uncertainty import parse, sample_profile

    c0 = time.process_time()
    policy = _policy(policy_path, PolicyRunner)
    site = RealityProfile.load(profile_path)
    unc = parse(site.uncertainty)
    rng = np.random.default_rng([seed, 7])
    true_profile = sample_profile(site, unc, rng.random(unc.param_dims))
    q_true = sample_pose(rng, cabin_turn=0.0 if mode == "2d" else None)
    # truth: residual passive swing; measured: the pose plus sensor error, the gripper looks still
    _, qd_true = unc.start.perturb(q_true, np.zeros(6), np.r_[np.full(6, 0.5), rng.random(2)])
    q_meas, _ = unc.start.perturb(q_true, np.zeros(6), np.r_[rng.random(6), np.full(2, 0.5)])
    target = target_on_axis(mode, distance_m)
    meas_sigma = float(true_profile.sensing.impact_noise_m)
    true_profile.sensing = dataclasses.replace(true_profile.sensing, impact_noise_m=0.0)  # the true landing spot
    sim = SimulatedMachine(true_profile, seed=seed)
    sim.set_state(q_true, qd_true)
    outcome, _ = run_throw(TwinMachine(sim, "calib"), ThrowExecutor({mode: policy}),
                           ThrowRequest(throw_id=f"c{seed}", machine_id="calib", mode=mode, target_m=target))
    row = {"seed": seed, "target_m": distance_m, "status": outcome.status if outcome else "refused"}
    if outcome is None or outcome.status != "landed":
        row["reason"] = outcome.failure_reason if outcome else "refused"
        return row
    impact = np.asarray(outcome.impact_m, dtype=float)[:2]
    measured = impact + rng.normal(0.0, meas_sigma, 2)
    row["impact_m"] = impact.tolist()
    row["impact_measured_m"] = measured.tolist()
    old = RealityProfile(**{**{k: getattr(site, k) for k in ("release_delay_mean_s", "release_delay_std_s",
                                                              "passive_viscous_per_s", "passive_coulomb_rad_per_s2")},
                            "hydraulics": site.hydraulics, "effects": site.effects,
                            "uncertainty": {"start.encoder_sigma_rad": 0, "start.imu_sigma_rad": 0, "start.passive_rate_max_radps": 0}})
    t0 = time.perf_counter()
    kinds = (("honest", site, param_rollouts), ("jitter_only", old, 1))[: 2 if compare else 1]
    for key, prof, pr in kinds:
        s = preview_throw(policy, PreviewRequest(mode, target, q_meas.tolist(), [0.0] * 6, rollouts=rollouts, seed=seed, param_rollouts=pr), prof)
        ell = (s.get("mc") or {}).get("ellipse")
        if s["status"] != "ok" or ell is None:
            row[key] = {"status": s["status"], "reason": s.get("reason")}
            continue
        mean, cov = np.array(ell["center_m"]), np.array(ell["cov"])
        d = impact - mean
        d2 = float(d @ np.linalg.solve(cov + 1e-12 * np.eye(2), d))
        dm = measured - mean
        d2m = float(dm @ np.linalg.solve(cov + (meas_sigma**2 + 1e-12) * np.eye(2), dm))
        row[key] = {"status": "ok", "mahalanobis2": d2, "mahalanobis2_measured": d2m, "center_m": mean.tolist(), "semi_major_m": ell["semi_major_m"],
                    "semi_minor_m": ell["semi_minor_m"], "sigma_downrange_m": s["mc"]["sigma_downrange_m"],
                    "failed_rollouts": s["mc"]["failed_rollouts"], "nominal_impact_m": s["impact_m"][:2]}
        if key == "honest":
            row["preview_s"] = time.perf_counter() - t0
    row["cpu_s"] = time.process_time() - c0
    return row


_POLICIES: dict = {}


def _policy(path, runner_cls):
    if path not in _POLICIES:
        _POLICIES[path] = runner_cls.load(path)
    return _POLICIES[path]


def summarise(rows: list[dict]) -> dict:
    """Shares inside 1 and 2 sigma per preview kind, with binomial standard errors."""
    out = {}
    for key in ("honest", "jitter_only"):
        d2 = np.array([r[key]["mahalanobis2"] for r in rows if r.get(key, {}).get("status") == "ok"])
        n = len(d2)
        if not n:
            out[key] = {"n": 0}
            continue
        p1, p2 = float(np.mean(d2 <= 1.0)), float(np.mean(d2 <= 4.0))
        d2m = np.array([r[key]["mahalanobis2_measured"] for r in rows if "mahalanobis2_measured" in r.get(key, {})])
        pm = float(np.mean(d2m <= 1.0)) if len(d2m) else float("nan")
        out[key] = {"n": n, "inside_1sigma": p1, "inside_1sigma_se": math.sqrt(p1 * (1 - p1) / n),
                    "measured_inside_1sigma": pm, "measured_inside_1sigma_se": math.sqrt(pm * (1 - pm) / max(len(d2m), 1)),
                    "measured_inside_2sigma": float(np.mean(d2m <= 4.0)) if len(d2m) else float("nan"),
                    "inside_2sigma": p2, "median_semi_major_m": float(np.median([r[key]["semi_major_m"] for r in rows if r.get(key, {}).get("status") == "ok"])),
                    "median_mahalanobis": float(np.median(np.sqrt(d2)))}
    out["gaussian_reference"] = {"inside_1sigma": 1 - math.exp(-0.5), "inside_2sigma": 1 - math.exp(-2.0)}
    return out


def plot(report: dict, path: Path) -> None:
    """Coverage curve (share of true impacts inside the k sigma ellipse against k) for both
    previews and the 2-D Gaussian, and the histogram of Mahalanobis distances."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = report["rows"]
    k = np.linspace(0, 4, 161)
    fig, ax = plt.subplots(1, 2, figsize=(10.5, 4.2))
    ax[0].plot(k, 1 - np.exp(-k**2 / 2), "k--", label="2-D Gaussian")
    for key, label in (("honest", "honest preview"), ("jitter_only", "release jitter only (before)")):
        d = np.sqrt([r[key]["mahalanobis2"] for r in rows if r.get(key, {}).get("status") == "ok"])
        if len(d):
            ax[0].plot(k, [(d <= x).mean() for x in k], label=f"{label}: {100 * (d <= 1).mean():.0f} % in 1σ")
            ax[1].hist(np.clip(d, 0, 10), bins=np.linspace(0, 10, 41), alpha=0.6, label=label)
    ax[0].axvline(1.0, color="grey", lw=0.6)
    ax[0].set_xlabel("ellipse size k [σ]")
    ax[0].set_ylabel("share of true impacts inside")
    ax[0].set_title(f"{report['throws']} throws, {report['mode']}, profile {report['profile_name']}", fontsize=10)
    ax[0].legend(fontsize=8)
    ax[0].grid(alpha=0.3)
    ax[1].set_xlabel("Mahalanobis distance of the true impact (clipped at 10)")
    ax[1].set_ylabel("throws")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", type=Path, default=REPO / "policies" / "throw2d.onnx")
    ap.add_argument("--profile", type=Path, default=REPO / "sim_twin" / "profiles" / "nominal_uncertain.json")
    ap.add_argument("--throws", type=int, default=200)
    ap.add_argument("--targets", default=None, help="distances cycled over, default 2D 7.5:10:0.5, 3D 7:9.5:0.5")
    ap.add_argument("--rollouts", type=int, default=200)
    ap.add_argument("--param-rollouts", type=int, default=16)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "reports" / "preview_calibration.json")
    ap.add_argument("--plot", type=Path, default=None)
    ap.add_argument("--compare-every", type=int, default=10,
                    help="also run the release-jitter-only preview every this many throws (it is far off; 1 = every throw)")
    ap.add_argument("--report-only", action="store_true", help="write the report from the rows finished so far (<out>.rows.jsonl)")
    args = ap.parse_args()
    from runtime.policy import PolicyRunner
    from sim_twin.evaluation.cli import parse_targets
    from sim_twin.twin.profile import RealityProfile

    policy = PolicyRunner.load(args.policy)
    mode = policy.mode
    tag = {"policy_name": policy.manifest.get("name"), "policy_sha256": hashlib.sha256(args.policy.read_bytes()).hexdigest(),
           "profile_sha256": hashlib.sha256(args.profile.read_bytes()).hexdigest(), "rollouts": args.rollouts,
           "param_rollouts": args.param_rollouts}
    dists = parse_targets(args.targets or ("7.5:10:0.5" if mode == "2d" else "7:9.5:0.5"))
    t0 = time.time()
    partial = args.out.with_suffix(".rows.jsonl")  # rows as they finish: a stopped run resumes
    args.out.parent.mkdir(parents=True, exist_ok=True)
    rows = [json.loads(line) for line in partial.read_text().splitlines()] if partial.is_file() else []
    stale = [r for r in rows if r.get("tag") != tag]
    if stale:  # made with another policy, profile or Monte Carlo size: not this measurement
        log.warning("setting aside %d rows of %s made with another policy/profile/MC size", len(stale), partial)
        rows = [r for r in rows if r.get("tag") == tag]
        partial.with_suffix(".stale.jsonl").open("a").writelines(json.dumps(r) + "\n" for r in stale)
        partial.write_text("".join(json.dumps(r) + "\n" for r in rows))
    done = {r["seed"] for r in rows}
    seeds = [(args.seed * 100_000 + i, dists[i % len(dists)]) for i in range(args.throws)]
    if args.report_only:
        seeds = []
    with ProcessPoolExecutor(max_workers=args.workers) as pool, partial.open("a") as f:
        futs = [pool.submit(one_throw, str(args.policy), str(args.profile), mode, d, seed, args.rollouts, args.param_rollouts,
                            (seed - args.seed * 100_000) % max(args.compare_every, 1) == 0)
                for seed, d in seeds if seed not in done]
        for n, fut in enumerate(as_completed(futs), 1):
            rows.append({**fut.result(), "tag": tag})
            f.write(json.dumps(rows[-1]) + "\n")
            f.flush()
            el = time.time() - t0
            inside = [r["honest"]["mahalanobis2"] <= 1 for r in rows if r.get("honest", {}).get("status") == "ok"]
            log.info("%d/%d throws, %.0f s, ETA %.0f min; inside 1 sigma so far %.1f %% of %d; this throw %.1f s CPU",
                     len(rows), args.throws, el, el / n * (len(futs) - n) / 60, 100 * np.mean(inside) if inside else float("nan"),
                     len(inside), rows[-1].get("cpu_s", float("nan")))
    rows.sort(key=lambda r: r["seed"])
    report = {"complete": len(rows) >= args.throws, "mode": mode, "policy": str(args.policy.relative_to(REPO) if args.policy.is_relative_to(REPO) else args.policy),
              "profile": str(args.profile.relative_to(REPO) if args.profile.is_relative_to(REPO) else args.profile),
              "profile_name": RealityProfile.load(args.profile).name, "throws": len(rows), "throws_planned": args.throws, "rollouts": args.rollouts,
              "param_rollouts": args.param_rollouts, "seed": args.seed, "wall_s": time.time() - t0, **tag,
              "cpu_s_total": float(sum(r.get("cpu_s", 0.0) for r in rows)),
              "median_throw_cpu_s": float(np.median([r["cpu_s"] for r in rows if "cpu_s" in r] or [float("nan")])),
              "landed": sum(r["status"] == "landed" for r in rows),
              "median_preview_s": float(np.median([r["preview_s"] for r in rows if "preview_s" in r] or [float("nan")])),
              "summary": None, "rows": rows}
    report["summary"] = summarise(rows)
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    plot(report, args.plot or args.out.with_suffix(".png"))
    s = report["summary"]
    for key in ("honest", "jitter_only"):
        if s[key].get("n"):
            print(f"{key:12s}: {100 * s[key]['inside_1sigma']:.1f} % +- {100 * s[key]['inside_1sigma_se']:.1f} inside 1 sigma "
                  f"(measured impacts: {100 * s[key]['measured_inside_1sigma']:.1f} %), "
                  f"{100 * s[key]['inside_2sigma']:.1f} % inside 2 sigma over {s[key]['n']} throws "
                  f"(median semi-major {s[key]['median_semi_major_m']:.3f} m)")
    print(f"landed {report['landed']}/{args.throws}; Gaussian: 39.3 % / 86.5 %; wall {report['wall_s']:.0f} s; {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
