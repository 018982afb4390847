"""Which part of a site profile makes a policy land worse: each profile split into its effects.

``python tests/benchmarks/site_coverage_diagnosis.py --mode 2d --profiles worn_gripper heavy_load
--policy deployed=policies/throw2d.onnx --policy u=policies/training/throw2d-scratch-u/throw2d.onnx
--out reports/site_coverage_diagnosis_2d`` throws every policy at the profile as committed
(sim_twin/profiles) and at one profile per effect of it, that effect alone, on the site matrix's
targets and start poses (sim_twin.evaluation.matrix.run_matrix, seed 0), and writes ``<out>.json``,
``<out>.md`` (mean miss distance [m], sim_twin.evaluation.evaluate.summarise's ``mean_abs_error_m`` over the landed
throws, and success per cell, the policies side by side) and
``<out>.png`` (mean miss against target, one panel per profile part).

Why: a from-scratch policy that loses to the deployed one on a site profile may lose on a part that
lies outside its training randomisation (sim_twin/configs/*.json ``env.randomization``), which a
wider range can cover, or on a part that training does not model at all.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
from pathlib import Path

import numpy as np

from sim_twin.evaluation.matrix import PROFILE_DIR, run_matrix

TARGETS = {"2d": [7.5, 8.0, 8.5, 9.0, 9.5, 10.0], "3d": [7.0, 7.5, 8.0, 8.5, 9.0, 9.5]}
"""The site matrix's targets [m] per mode (sim_twin.evaluation.cli defaults)."""


def effect_parts(name: str) -> tuple[dict, list[dict]]:
    """The committed profile sim_twin/profiles/<name>.json and one profile dict per effect of it,
    that effect alone, named ``<name>__<effect>`` (a plugin effect by its class name).

    Raises:
        FileNotFoundError: no such committed profile.
        ValueError: the profile has fewer than two effects (nothing to split).
    """
    spec = json.loads((PROFILE_DIR / f"{name}.json").read_text())
    effects = spec.get("effects", [])
    if len(effects) < 2:
        raise ValueError(f"profile {name!r} has {len(effects)} effect(s): nothing to split")
    return spec, [{**spec, "name": f"{name}__{e['effect'].split(':')[-1]}", "effects": [e]} for e in effects]


def split_profile(name: str, out_dir: Path) -> list[str]:
    """Write ``<name>__<effect>.json`` (the profile with only that effect, :func:`effect_parts`) into
    ``out_dir`` for each effect of sim_twin/profiles/<name>.json, and a copy of the profile itself;
    returns the profile names, the whole profile first.

    Raises:
        FileNotFoundError: no such committed profile.
        ValueError: the profile has fewer than two effects (nothing to split).
    """
    spec, parts = effect_parts(name)
    (out_dir / f"{name}.json").write_text(json.dumps(spec))
    for part in parts:
        (out_dir / f"{part['name']}.json").write_text(json.dumps(part))
    return [name, *(part["name"] for part in parts)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mode", choices=sorted(TARGETS), required=True)
    p.add_argument("--profiles", nargs="+", required=True, help="committed site profiles to split")
    p.add_argument("--policy", action="append", required=True, help="NAME=path.onnx (repeatable)")
    p.add_argument("--throws", type=int, default=100)
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    policies = dict(s.split("=", 1) for s in args.policy)
    targets = TARGETS[args.mode]
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        parts = [n for prof in args.profiles for n in split_profile(prof, Path(tmp))]
        for pname, path in policies.items():
            rep = run_matrix(Path(path), args.mode, targets, args.throws, profiles=[(n, True) for n in parts],
                             workers=args.workers, profile_dir=Path(tmp))
            for prof in rep["profiles"]:
                for t in prof["targets"]:
                    rows.append({"policy": pname, "profile": prof["name"], "target_m": t["target_m"],
                                 "mean_miss_m": t["mean_abs_error_m"], "success_rate": t["success_rate"], "bias_m": t["bias_m"]})
                logging.info("%s %s done", pname, prof["name"])
    body = {"mode": args.mode, "throws_per_target": args.throws, "seed": 0, "policies": policies, "parts": parts, "cells": rows}
    args.out.with_suffix(".json").write_text(json.dumps(body, indent=1) + "\n")
    names = list(policies)
    md = [f"# Site profiles split into their effects, {args.mode.upper()}", "",
          f"Mean miss distance [m] (success) per cell, {args.throws} throws, start-pose seed 0; "
          "`<profile>__<effect>` is the profile with that effect alone.", "",
          "| profile part | target [m] | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for part in parts:
        for d in targets:
            cells = {r["policy"]: r for r in rows if r["profile"] == part and r["target_m"] == d}
            md.append(f"| {part} | {d:.1f} | " + " | ".join(
                f"{cells[n]['mean_miss_m']:.3f} ({100 * cells[n]['success_rate']:.0f} %)" if cells[n]["mean_miss_m"] is not None
                else "none landed" for n in names) + " |")
    args.out.with_suffix(".md").write_text("\n".join(md) + "\n")
    plot(rows, parts, names, targets, args.out.with_suffix(".png"), args.mode)


def plot(rows: list[dict], parts: list[str], names: list[str], targets: list[float], out: Path, mode: str) -> None:
    """Mean miss against target, one panel per profile part, one line per policy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(len(parts), 4)
    nrows = -(-len(parts) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.6 * cols, 2.8 * nrows), sharey=True, squeeze=False)
    for ax, part in zip(axes.flat, parts):
        for n in names:
            y = [next((r["mean_miss_m"] for r in rows if r["policy"] == n and r["profile"] == part and r["target_m"] == d), None)
                 for d in targets]
            ax.plot(targets, [np.nan if v is None else v for v in y], marker="o", label=n)
        ax.set_title(part, fontsize=8)
        ax.set_xlabel("target [m]")
        ax.grid(alpha=0.3)
    for ax in axes[:, 0]:
        ax.set_ylabel("mean miss [m]")
    for ax in list(axes.flat)[len(parts):]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"Site profiles split into their effects, {mode.upper()}")
    fig.tight_layout()
    fig.savefig(out, dpi=80)


if __name__ == "__main__":
    main()
