"""Where a worn gripper's passive friction costs a 2D policy: the same throws (same start poses,
same seeds) on the nominal simulated machine and with the worn gripper's friction alone, each
throw's change of landing point against when the policy released it.

    python tests/benchmarks/friction_release_timing.py --policy deployed=policies/throw2d.onnx \
        --policy u=policies/training/throw2d-scratch-u/throw2d.onnx \
        --policy x=policies/training/throw2d-scratch-x/throw2d-it1451.onnx \
        --out reports/friction_release_timing_2d

(``throw2d-scratch-x`` is in the lab notebook: ``git checkout lab-notebook-2026-11-25 --
policies/training/throw2d-scratch-x`` first, policies/training/ARCHIVE.md.)

writes ``<out>.json`` (per policy and target: landed throws, first-swing throws, the mean miss
distance [m] nominal and with the friction, and the mean downrange shift the friction causes [m],
for first-swing and later releases; ``figures`` for docs/results.md) and ``<out>.png`` (one panel
per policy: shift against the release time, every target; and the mean miss per target).

Why: the deployed lineage `throw2d-robust-i` trained on the same friction range as the from-scratch
recipe (x0.5-3.5, policies/training/throw2d-robust-i/config.json) yet loses less to the worn
gripper's tenfold viscous friction (reports/site_coverage_diagnosis_2d.md). The gripper swings on
its passive joints until the release; a throw released in a later swing has spent longer under the
wrong friction. A throw is "first swing" when its release command comes within
``spread_sources.FIRST_SWING_S`` of the swing's start (the 2D policies release either at 0.9-1.6 s or
after 2.8 s; reports/spread_sources_2d_scratch.png in the lab notebook, reports/ARCHIVE.md).

Throws: ``spread_sources.throws`` (the runtime's executor with its release check on, start poses
``i * 100_000 + k`` as the site matrix's seed 0, i the target's index in 7.5:10:0.5 m). A throw is
paired when it landed in both conditions; the shift is worn minus nominal downrange error.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import as_completed
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from tests.benchmarks.site_coverage_diagnosis import effect_parts  # noqa: E402
from tests.benchmarks.spread_sources import FIRST_SWING_S, TARGETS_2D, throws  # noqa: E402

SITE_PROFILE = "worn_gripper"
EFFECT = "passive_friction"


def friction_profile() -> dict:
    """The worn gripper's passive-friction effect alone as a RealityProfile dict
    (sim_twin/profiles/worn_gripper.json split by site_coverage_diagnosis.effect_parts; its
    release-delay effect left out).

    Raises:
        ValueError: the committed profile has no passive-friction effect.
    """
    _, parts = effect_parts(SITE_PROFILE)
    for part in parts:
        if part["effects"][0]["effect"] == EFFECT:
            return part
    raise ValueError(f"sim_twin/profiles/{SITE_PROFILE}.json has no {EFFECT} effect")


def paired(nominal: list[dict], worn: list[dict]) -> list[dict]:
    """Throws of one cell that landed in both conditions, matched by seed: ``seed``,
    ``release_after_s`` (nominal, s), ``first_swing`` (bool), ``nominal_error_m``, ``worn_error_m``
    and ``shift_m`` (worn minus nominal downrange error, m)."""
    w = {r["seed"]: r for r in worn if r["status"] == "landed"}
    out = []
    for r in nominal:
        if r["status"] != "landed" or r["seed"] not in w:
            continue
        e0, e1 = r["downrange_error_m"], w[r["seed"]]["downrange_error_m"]
        out.append({"seed": r["seed"], "release_after_s": round(r["release_after_s"], 3),
                    "first_swing": bool(r["release_after_s"] <= FIRST_SWING_S),
                    "nominal_error_m": round(e0, 4), "worn_error_m": round(e1, 4), "shift_m": round(e1 - e0, 4)})
    return out


def _mean(xs) -> float | None:
    return round(float(np.mean(xs)), 4) if len(xs) else None


def summary(pairs: list[dict], n_nominal: int, n_worn: int, throws_per_cell: int) -> dict:
    """One cell's figures from :func:`paired` rows: landed counts, the number of first-swing throws,
    the mean miss distance (|downrange error|, m) in each condition and the mean shift (m) over all,
    first-swing and later throws (None where a group is empty)."""
    first = [p for p in pairs if p["first_swing"]]
    later = [p for p in pairs if not p["first_swing"]]
    return {"throws": throws_per_cell, "landed_nominal": n_nominal, "landed_worn": n_worn, "paired": len(pairs),
            "first_swing": len(first),
            "mean_miss_nominal_m": _mean([abs(p["nominal_error_m"]) for p in pairs]),
            "mean_miss_worn_m": _mean([abs(p["worn_error_m"]) for p in pairs]),
            "mean_shift_m": _mean([p["shift_m"] for p in pairs]),
            "mean_shift_first_swing_m": _mean([p["shift_m"] for p in first]),
            "mean_shift_later_m": _mean([p["shift_m"] for p in later]),
            "mean_miss_worn_first_swing_m": _mean([abs(p["worn_error_m"]) for p in first]),
            "mean_miss_worn_later_m": _mean([abs(p["worn_error_m"]) for p in later])}


MIN_GROUP = 10
"""Throws each of the first-swing and later groups of a cell needs for the within-target contrast."""


def figures(cells: list[dict]) -> list[dict]:
    """docs/results.md rows per policy: the share of first-swing releases, the mean downrange shift
    the friction causes over all paired throws (m), and the within-target contrast: later minus
    first-swing mean shift (m), averaged over the targets with at least MIN_GROUP throws in each
    group (pooling over targets would mix the release time with the distance)."""
    out = []
    for name in dict.fromkeys(c["policy"] for c in cells):
        mine = [c for c in cells if c["policy"] == name]
        rows = [p for c in mine for p in c["pairs"]]
        n_first = sum(p["first_swing"] for p in rows)
        cond = f"{len(rows)} paired throws over {len(mine)} targets, worn-gripper friction alone"
        out.append({"what": f"{name}: first-swing releases", "value": round(100 * n_first / max(len(rows), 1), 1), "unit": "%",
                    "conditions": cond})
        out.append({"what": f"{name}: mean downrange shift by the friction", "value": _mean([p["shift_m"] for p in rows]),
                    "unit": "m", "conditions": cond})
        both = [c for c in mine if MIN_GROUP <= c["first_swing"] <= c["paired"] - MIN_GROUP]
        if both:
            diff = [c["mean_shift_later_m"] - c["mean_shift_first_swing_m"] for c in both]
            out.append({"what": f"{name}: later minus first-swing shift, same target", "value": _mean(diff), "unit": "m",
                        "conditions": "targets " + ", ".join(f"{c['target_m']:g} m" for c in both)
                        + f" (each with >= {MIN_GROUP} throws per group)"})
    return out


def plot(report: dict, out: Path) -> None:
    """Top row: per policy, each paired throw's shift [m] against its release time [s], coloured by
    target; bottom: mean miss [m] per target, nominal (dashed) and with the friction (solid)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = report["cells"]
    names = list(dict.fromkeys(c["policy"] for c in cells))
    fig, axes = plt.subplots(2, len(names), figsize=(4.6 * len(names), 7.6), squeeze=False)
    cmap = plt.get_cmap("viridis")
    for j, name in enumerate(names):
        ax = axes[0][j]
        for c in (c for c in cells if c["policy"] == name):
            k = TARGETS_2D.index(c["target_m"]) / (len(TARGETS_2D) - 1)
            ax.scatter([p["release_after_s"] for p in c["pairs"]], [p["shift_m"] for p in c["pairs"]], s=8, color=cmap(k),
                       label=f"{c['target_m']:g} m")
        ax.axvline(FIRST_SWING_S, color="k", ls=":", lw=1)
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_title(f"{name}: shift by worn friction")
        ax.set_xlabel("release command after swing start [s]")
        ax.set_ylabel("downrange shift, worn - nominal [m]")
        if j == 0:
            ax.legend(fontsize=7, markerscale=2)
    top = max(max(c["mean_miss_nominal_m"] or 0.0, c["mean_miss_worn_m"] or 0.0) for c in cells)
    for j, name in enumerate(names):
        ax = axes[1][j]
        cs = sorted((c for c in cells if c["policy"] == name), key=lambda c: c["target_m"])
        t = [c["target_m"] for c in cs]
        ax.plot(t, [c["mean_miss_nominal_m"] for c in cs], "k--o", ms=3, label="nominal")
        ax.plot(t, [c["mean_miss_worn_m"] for c in cs], "-o", ms=3, color="tab:red", label="worn friction")
        ax.set_xlabel("target [m]")
        ax.set_ylabel("mean miss [m]")
        ax.set_title(f"{name}: mean miss")
        ax.set_ylim(0.0, 1.1 * top)
        ax.legend(fontsize=7)
    fig.suptitle(f"worn-gripper friction alone, {report['throws_per_cell']} throws per target (simulated machine)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def main() -> None:
    from runtime.policy import sha256_of
    from sim_twin.twin.pools import process_pool

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", action="append", required=True, help="NAME=path.onnx, a 2D policy (repeatable)")
    ap.add_argument("--targets", default=",".join(f"{d:g}" for d in TARGETS_2D), help="comma-separated, from 7.5:10:0.5 m")
    ap.add_argument("--throws", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True, help="report path without suffix (.json and .png are written)")
    ap.add_argument("--plot-only", action="store_true", help="only draw the plot of the existing report")
    args = ap.parse_args()
    if args.plot_only:
        plot(json.loads(args.out.with_suffix(".json").read_text()), args.out.with_suffix(".png"))
        return
    pols = {}
    for spec in args.policy:
        name, sep, path = spec.partition("=")
        if not sep or not name or not Path(path).is_file():
            ap.error(f"--policy wants NAME=path.onnx with an existing file, not {spec!r}")
        pols[name] = path
    sha = {name: sha256_of(path) for name, path in pols.items()}
    targets = [float(x) for x in args.targets.split(",")]
    if bad := [d for d in targets if d not in TARGETS_2D]:
        ap.error(f"unknown targets {bad} (the site matrix's 2D targets are {TARGETS_2D})")
    if args.throws < 2:
        ap.error("--throws must be at least 2")
    worn = friction_profile()
    t0 = time.time()
    jobs = {}
    with process_pool(args.workers) as pool:
        for name, path in pols.items():
            for d in targets:
                seeds = [TARGETS_2D.index(d) * 100_000 + k for k in range(args.throws)]
                for j in range(0, len(seeds), 10):
                    for cond, prof in (("nominal", None), ("worn", worn)):
                        jobs[pool.submit(throws, path, d, seeds[j:j + 10], prof)] = (name, d, cond)
        results: dict[tuple, list] = {key: [] for key in jobs.values()}
        for n, fut in enumerate(as_completed(jobs), 1):
            results[jobs[fut]] += fut.result()
            if n % 20 == 0 or n == len(jobs):
                print(f"  {n}/{len(jobs)} batches ({time.time() - t0:.0f} s)", flush=True)
    cells = []
    for name in pols:
        for d in targets:
            nom, wrn = results[(name, d, "nominal")], results[(name, d, "worn")]
            pairs = paired(nom, wrn)
            s = summary(pairs, sum(r["status"] == "landed" for r in nom), sum(r["status"] == "landed" for r in wrn), args.throws)
            cells.append({"policy": name, "policy_sha256": sha[name], "target_m": d, **s, "pairs": pairs})
            print(f"{name:10s} {d:4.1f} m  paired {s['paired']:3d}  first swing {s['first_swing']:3d}  miss nominal "
                  f"{s['mean_miss_nominal_m']} worn {s['mean_miss_worn_m']} m  shift first {s['mean_shift_first_swing_m']} "
                  f"later {s['mean_shift_later_m']} m", flush=True)
    report = {"profile": worn, "first_swing_s": FIRST_SWING_S, "throws_per_cell": args.throws, "wall_s": round(time.time() - t0, 1),
              "figures": figures(cells), "cells": cells}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(report, indent=1) + "\n")
    plot(report, args.out.with_suffix(".png"))
    print(f"wall {time.time() - t0:.0f} s -> {args.out.with_suffix('.json')}")


if __name__ == "__main__":
    main()
