"""Site matrix: one policy over the nominal simulated machine and a committed set of site
profiles (``slinger evaluate --matrix``), by the paper's protocol (sim_twin.evaluation.evaluate: random
collision-free start poses at rest, targets on the evaluation axis, the runtime's own executor).

Bars (issue 9), per profile and target, 100 throws each:

* success >= 95 % in every profile;
* profiles that do not shift the mean (hydraulics, latency, noise, friction; ``shifts_mean``
  False below): 2D |bias| <= 0.15 m and sigma downrange <= 0.20 m, 3D sigma <= 0.30 m
  (downrange and crossrange);
* nominal: 2D |bias| <= 0.10 m, sigma <= 0.10 m, success >= 98 %; 3D sigma <= 0.20 m, success >= 95 %.

Writes ``<out>.json`` (every cell with its bar verdict), ``<out>.md`` (the table) and ``<out>.png``
(bias with 1 sigma bars per profile and target). All (profile, target, seed batch) jobs share one
process pool.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import as_completed
from pathlib import Path

import numpy as np

from sim_twin.evaluation.evaluate import summarise, throw_batch, throw_seeds
from sim_twin.provenance import compact_json
from sim_twin.twin.pools import process_pool

log = logging.getLogger(__name__)

PROFILE_DIR = Path(__file__).parent.parent / "profiles"

MATRIX_PROFILES: list[tuple[str, bool]] = [
    ("nominal", False),
    ("slow_hydraulics", False),
    ("fast_hydraulics", False),
    ("sensor_latency", False),
    ("sensor_noise", False),
    ("friction_x3", False),
    ("slow_latent_noisy", False),
    ("heavy_load", True),
    ("windy_site", True),
    ("worn_gripper", True),
    ("heavy_windy", True),
]
"""(profile name in sim_twin/profiles, shifts the mean). 'nominal' is the default profile."""


def success_bar(mode: str, profile: str = "nominal") -> float:
    """The site matrix's success bar of a cell (share of throws released, landed, no collision):
    0.98 for the nominal 2D machine, else 0.95 (the bars above)."""
    return 0.98 if (profile == "nominal" and mode == "2d") else 0.95


def cell_bars(mode: str, profile: str, shifts_mean: bool, t: dict) -> dict[str, bool]:
    """Bar verdicts of one (profile, target) cell from its summarise() statistics."""
    ok = {"success": t["success_rate"] >= success_bar(mode, profile)}
    if t["landed"] == 0:
        return {**ok, "accuracy": False}
    if profile == "nominal":
        if mode == "2d":
            ok["accuracy"] = abs(t["bias_m"]) <= 0.10 and t["sigma_downrange_m"] <= 0.10
        else:
            ok["accuracy"] = t["sigma_downrange_m"] <= 0.20 and t["sigma_crossrange_m"] <= 0.20
    elif not shifts_mean:
        if mode == "2d":
            ok["accuracy"] = abs(t["bias_m"]) <= 0.15 and t["sigma_downrange_m"] <= 0.20
        else:
            ok["accuracy"] = t["sigma_downrange_m"] <= 0.30 and t["sigma_crossrange_m"] <= 0.30
    return ok


def run_matrix(policy: Path, mode: str, targets: list[float], throws: int, profiles=None, seed: int = 0, workers: int | None = None, batch: int = 10,
               profile_dir: Path = PROFILE_DIR, release_sweep: bool = False) -> dict:
    """Evaluate ``policy`` on every profile of ``profiles`` (default MATRIX_PROFILES), read from
    ``profile_dir`` (default sim_twin/profiles).

    With ``release_sweep`` (the training gate's matrices) the policy validation's twin sweep over
    the policy's declared target range runs first (sim_twin.evaluation.evaluate.twin_sweep, its
    defaults): the matrix's targets are 7.5-10 m, a manifest's range 5-10.7 m, and a version that
    does not release at part of it fails validation before promotion; the report's ``pass``
    then needs the sweep too.

    Returns:
        {"policy", "mode", "throws_per_target", "seed", "wall_s", "profiles": [{"name",
        "shifts_mean", "targets": [summarise(per_throw=True) + "bars"], "pass"}], "pass"} and, with
        ``release_sweep``, "release_sweep": {"passed", "reason", "throws", "target_range_m"}.

    Raises:
        FileNotFoundError: a profile file is missing.
        runtime.policy.PolicyError: the policy does not load (before any throw).
    """
    from runtime.policy import PolicyRunner

    runner = PolicyRunner.load(policy)  # its version and declared range; the throws load their own
    sweep = None
    if release_sweep:
        from sim_twin.evaluation.evaluate import twin_sweep

        declared = runner.target_range_m
        why, made = twin_sweep(policy, mode, declared)
        sweep = {"passed": why is None, "reason": why, "throws": made, "target_range_m": list(declared)}
        log.info("release sweep over %g-%g m: %s", *declared, "passed" if why is None else why)
    profiles = profiles or MATRIX_PROFILES
    paths: dict[str, str | None] = {}
    for name, _ in profiles:
        path = paths[name] = None if name == "nominal" else str(Path(profile_dir) / f"{name}.json")
        if path and not Path(path).is_file():
            raise FileNotFoundError(path)
    jobs = []
    for name, _ in profiles:
        for i, d in enumerate(targets):
            seeds = throw_seeds(seed, i, throws)  # same start poses in every profile
            jobs += [(name, d, seeds[j : j + batch]) for j in range(0, throws, batch)]
    results: dict[tuple[str, float], list[dict]] = {(name, d): [] for name, _ in profiles for d in targets}
    t0 = time.time()
    with process_pool(workers) as pool:
        futs = {pool.submit(throw_batch, str(policy), mode, d, s, paths[name]): (name, d) for name, d, s in jobs}
        for k, fut in enumerate(as_completed(futs), 1):
            results[futs[fut]] += fut.result()
            if k % 20 == 0 or k == len(futs):
                log.info("matrix %s: %d/%d batches (%.0f s)", mode, k, len(futs), time.time() - t0)
    rows = []
    for name, shifts in profiles:
        cells = []
        for d in targets:
            t = summarise(d, results[(name, d)], per_throw=True)
            t["bars"] = cell_bars(mode, name, shifts, t)
            cells.append(t)
        rows.append({"name": name, "shifts_mean": shifts, "targets": cells, "pass": all(all(c["bars"].values()) for c in cells)})
    report = {
        "policy": str(policy),
        "policy_version": runner.version,
        "mode": mode,
        "throws_per_target": throws,
        "seed": seed,
        "wall_s": time.time() - t0,
        "profiles": rows,
        "pass": all(r["pass"] for r in rows) and (sweep is None or sweep["passed"]),
    }
    if sweep is not None:
        report["release_sweep"] = sweep
    return report


def markdown(report: dict) -> str:
    """One table: a row per profile and target (success, bias, sigmas, verdict)."""
    out = [f"**Site matrix {report['mode'].upper()} `{report['policy_version']}`**, {report['throws_per_target']} throws per "
           f"target and profile, {report['wall_s'] / 60:.1f} min; all bars met: **{'yes' if report['pass'] else 'no'}**\n",
           *([f"Release sweep over the declared range {report['release_sweep']['target_range_m'][0]:g}-"
              f"{report['release_sweep']['target_range_m'][1]:g} m: "
              + ("passed" if report["release_sweep"]["passed"] else f"**failed**: {report['release_sweep']['reason']}") + "\n"]
             if report.get("release_sweep") else []),
           "| profile | shifts mean | target [m] | success | bias [m] | σ down [m] | σ cross [m] | bars |",
           "|---|---|---|---|---|---|---|---|"]
    for p in report["profiles"]:
        for t in p["targets"]:
            def f(k, t=t):
                return "n/a" if t[k] is None else f"{t[k]:+.3f}"

            miss = [k for k, v in t["bars"].items() if not v]
            out.append(f"| {p['name']} | {'yes' if p['shifts_mean'] else 'no'} | {t['target_m']:.1f} | {100 * t['success_rate']:.0f} % | "
                       f"{f('bias_m')} | {f('sigma_downrange_m')} | {f('sigma_crossrange_m')} | {'ok' if not miss else 'MISS ' + ', '.join(miss)} |")
    return "\n".join(out) + "\n"


def plot(reports: list[dict], out: Path) -> None:
    """Bias ± 1 sigma downrange per target, one line per profile; one panel per report."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(reports), figsize=(7 * len(reports), 4.8), squeeze=False)
    for ax, rep in zip(axes[0], reports):
        n = len(rep["profiles"])
        for k, p in enumerate(rep["profiles"]):
            cells = [t for t in p["targets"] if t["landed"]]
            d = np.array([t["target_m"] for t in cells]) + (k - n / 2) * 0.03
            ok = p["pass"]
            ax.errorbar(d, [t["bias_m"] for t in cells], yerr=[t["sigma_downrange_m"] for t in cells], fmt="o-" if ok else "x--",
                        ms=3, lw=0.8, capsize=2, label=f"{p['name']}{'' if ok else ' (miss)'}")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_xlabel("target distance [m]")
        ax.set_ylabel("downrange bias ± 1σ [m]")
        ax.set_title(f"{rep['mode'].upper()} {rep['policy_version']}: site matrix, {rep['throws_per_target']} throws/cell", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def dumps(report: dict) -> str:
    """JSON of a report, indented, with every list of plain values (the per-throw data) on one
    line (sim_twin.provenance.compact_json)."""
    return compact_json(report)


def write(report: dict, out: Path) -> None:
    """``out``.json, .md and .png."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(dumps(report) + "\n")
    out.with_suffix(".md").write_text(markdown(report))
    plot([report], out.with_suffix(".png"))
