"""Deploy comparison report: from-scratch candidates against the deployed policy (sim_twin.evaluation.matrix_compare),
with the check that the comparison does not call the deployed policy worse than itself.

``python tests/benchmarks/deploy_comparison.py --mode 2d --deployed reports/site_matrix_2d.json
reports/site_matrix_2d_seed1.json ... --candidate NAME=m0.json,m1.json ... --out reports/deploy_comparison_2d``
writes ``<out>.json`` and ``<out>.md``:

* **null check**: for every ordered pair of the deployed policy's seeds (a, b), seed b's throws are
  paired with seed a's by position (different start poses, the same policy, so no true difference)
  and compared; the count of cells called worse by the paired test (sim_twin.evaluation.matrix_compare) and
  by the earlier rule (lower success, or |bias| or sigma larger by more than 5 mm) side by side;
* **candidates**: each candidate's matrices against the deployed ones of the same seeds, pooled.
"""

from __future__ import annotations

import argparse
import copy
import json
from itertools import permutations
from pathlib import Path

from sim_twin.evaluation.matrix_compare import ALPHA, compare

OLD_TOL_M = 0.005  # the earlier rule's tolerance


def old_rule_worse(dep: dict, cand: dict) -> int:
    """Cells the earlier rule called worse (lower success, or |bias| or sigma larger by > 5 mm)."""
    n = 0
    for pd, pc in zip(dep["profiles"], cand["profiles"], strict=True):
        for d, c in zip(pd["targets"], pc["targets"], strict=True):
            n += (c["success_rate"] < d["success_rate"] or abs(c["bias_m"]) > abs(d["bias_m"]) + OLD_TOL_M
                  or c["sigma_downrange_m"] > d["sigma_downrange_m"] + OLD_TOL_M)
    return n


def relabelled(rep: dict, like: dict) -> dict:
    """``rep`` with each cell's seeds replaced by those of ``like``'s cell (pairs by position)."""
    out = copy.deepcopy(rep)
    for po, pl in zip(out["profiles"], like["profiles"], strict=True):
        for co, cl in zip(po["targets"], pl["targets"], strict=True):
            co["per_throw"]["seed"] = list(cl["per_throw"]["seed"])
    return out


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--mode", required=True)
    p.add_argument("--deployed", type=Path, nargs="+", required=True, help="deployed site matrices, seeds 0, 1, ...")
    p.add_argument("--candidate", nargs="*", default=[], help="NAME=seed0.json,seed1.json,...")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    dep = [json.loads(f.read_text()) for f in args.deployed]
    null = []
    for a, b in permutations(range(len(dep)), 2):
        comp = compare([dep[a]], [relabelled(dep[b], dep[a])])
        null.append({"seeds": [dep[a]["seed"], dep[b]["seed"]], "paired_test_worse": comp.worse_cells,
                     "old_rule_worse": old_rule_worse(dep[a], dep[b]), "cells": len(comp.cells)})
    cands = []
    for spec in args.candidate:
        name, files = spec.split("=", 1)
        reps = [json.loads(Path(f).read_text()) for f in files.split(",")]
        seeds = [r["seed"] for r in reps]
        mine = [r for r in dep if r["seed"] in seeds]
        comp = compare(mine, reps)
        cands.append({"name": name, "matrices": files.split(","), "seeds": seeds, "worse_cells": comp.worse_cells,
                      "cells": len(comp.cells), "old_rule_worse_per_seed": [old_rule_worse(d, c) for d, c in
                                                                            zip(sorted(mine, key=lambda r: r["seed"]), sorted(reps, key=lambda r: r["seed"]))],
                      "worse": [{"profile": c.profile, "target_m": c.target_m, "on": list(c.worse_on), "pairs": c.pairs,
                                 "mean_miss_deployed_m": c.mean_miss_deployed_m, "mean_miss_candidate_m": c.mean_miss_candidate_m,
                                 "p_success": c.p_success, "p_miss": c.p_miss} for c in comp.cells if c.worse],
                      "better_mean_miss_cells": sum(1 for c in comp.cells if c.mean_miss_candidate_m is not None
                                                    and c.mean_miss_candidate_m < c.mean_miss_deployed_m)})
    body = {"mode": args.mode, "deployed": [str(f) for f in args.deployed], "alpha": ALPHA, "null_check": null, "candidates": cands}
    args.out.with_suffix(".json").write_text(json.dumps(body, indent=1) + "\n")
    md = [f"# Deploy comparison, {args.mode}: from-scratch candidates against the deployed policy", "",
          "Paired tests per cell (sim_twin.evaluation.matrix_compare: exact McNemar on success, Wilcoxon signed-rank on the miss "
          f"distance), Holm-corrected over the comparison at a family-wise error rate of {ALPHA:g}.", "",
          "## Null check: the deployed policy against itself on another seed's throws", "",
          "| seeds | cells called worse, paired test | cells called worse, earlier 5 mm rule |", "|---|---|---|"]
    md += [f"| {n['seeds'][0]} vs {n['seeds'][1]} | {n['paired_test_worse']} of {n['cells']} | {n['old_rule_worse']} of {n['cells']} |" for n in null]
    md += ["", "## Candidates", "", "| candidate | seeds | cells worse (paired test) | cells with a lower mean miss | worse on |", "|---|---|---|---|---|"]
    for c in cands:
        on = "; ".join(f"{w['profile']} {w['target_m']:g} m ({w['mean_miss_deployed_m']:.3f} → {w['mean_miss_candidate_m']:.3f} m)"
                       for w in c["worse"]) or "-"
        md.append(f"| {c['name']} | {', '.join(map(str, c['seeds']))} | {c['worse_cells']} of {c['cells']} | "
                  f"{c['better_mean_miss_cells']} | {on} |")
    args.out.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
