"""Whether a candidate policy throws worse than the deployed one on any site-matrix cell, beyond
sampling noise (the deploy rule of docs/training.md "Deploying a new version").

A site matrix (sim_twin.evaluation.matrix) throws 100 times per (profile, target) cell, throw ``k`` from a
seed that fixes its start pose and the profile's randomness, the same seeds for every policy. Two
policies' throws of one seed are therefore a matched pair, and each cell is compared on its pairs,
pooled over the start-pose seeds given (seed 0, 1 and 2 matrices: 300 pairs a cell):

* **success**: exact one-sided McNemar test on the discordant pairs (the candidate failed where the
  deployed policy landed, against the reverse; binomial with p = 1/2).
* **landing error**: the miss distance ``hypot(downrange, crossrange)`` [m] of the pairs where both
  landed; one-sided Wilcoxon signed-rank test on candidate minus deployed (``scipy.stats.wilcoxon``,
  ``alternative="greater"``). The miss distance is what an operator sees and grows with both bias and
  spread (E[miss^2] = bias^2 + sigma^2 per axis).

A failure spread thinly over many cells (one or two ground-clearance stops in each of a dozen near
cells, say) is in no cell enough for its McNemar test, so success is also compared **pooled over all
cells**: the same exact one-sided McNemar test on every pair of the comparison.

The p-values of every test of the comparison (cells x 2, and the pooled success test) are corrected
together by Holm's step-down procedure (Holm 1979) at a family-wise error rate ``alpha`` (default
0.05, CHOSEN): a cell is *worse* when one of its tests is rejected, and the candidate fails more
often overall when the pooled test is. The earlier rule (worse where success is lower
or |bias| or sigma is larger by more than 5 mm) called the deployed policy worse than itself on
25-49 of 66 cells between two start-pose seeds (reports/deploy_comparison_2d.md, _3d.md): its
differences were sampling noise.

``python -m sim_twin.evaluation.matrix_compare --deployed D0.json D1.json --candidate C0.json C1.json``
prints the table and exits 1 when the candidate is worse on any cell or fails more often over all cells.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

ALPHA = 0.05
"""Family-wise error rate of one comparison (CHOSEN)."""


@dataclass(frozen=True)
class CellComparison:
    """One (profile, target) cell: pairs pooled over seeds, success counts, mean miss distances [m]
    over the pairs where both landed, raw one-sided p-values and the Holm verdict."""

    profile: str
    target_m: float
    pairs: int
    landed_deployed: int
    landed_candidate: int
    both_landed: int
    mean_miss_deployed_m: float | None
    mean_miss_candidate_m: float | None
    p_success: float
    p_miss: float
    worse: bool = False
    worse_on: tuple[str, ...] = ()


@dataclass(frozen=True)
class Comparison:
    """All cells of a comparison; ``worse_cells`` counts those the candidate is worse on. The pooled
    success test over all pairs: ``pooled_lost`` pairs the candidate failed where the deployed policy
    landed, ``pooled_won`` the reverse, its raw one-sided p-value ``p_pooled_success`` and Holm
    verdict ``fails_more``."""

    alpha: float
    cells: list[CellComparison]
    pooled_lost: int = 0
    pooled_won: int = 0
    p_pooled_success: float = 1.0
    fails_more: bool = False

    @property
    def worse_cells(self) -> int:
        return sum(c.worse for c in self.cells)

    @property
    def worse(self) -> bool:
        """The deploy rule's verdict: worse on a cell, or failing more often over all cells."""
        return bool(self.worse_cells) or self.fails_more


def throws_of(report: dict) -> dict[tuple[str, float, int], tuple[float, float] | None]:
    """(profile, target_m, seed) -> (downrange, crossrange) error [m] or None (not landed) of a site
    matrix report with per-throw data.

    Raises:
        ValueError: a cell has no ``per_throw`` data (a report written before site matrices kept
            it: run ``slinger evaluate --matrix`` again; the seeds make it the same throws).
    """
    out: dict[tuple[str, float, int], tuple[float, float] | None] = {}
    for p in report["profiles"]:
        for c in p["targets"]:
            pt = c.get("per_throw")
            if pt is None:
                raise ValueError(f"{p['name']} at {c['target_m']} m has no per-throw data: re-run this site matrix "
                                 "(slinger evaluate --matrix --seed S) to compare it")
            for s, dr, cr in zip(pt["seed"], pt["downrange_error_m"], pt["crossrange_error_m"], strict=True):
                out[(p["name"], float(c["target_m"]), int(s))] = None if dr is None else (float(dr), float(cr))
    return out


def _pool(reports: list[dict]) -> dict[tuple[str, float, int], tuple[float, float] | None]:
    pooled: dict[tuple[str, float, int], tuple[float, float] | None] = {}
    for rep in reports:
        pooled.update(throws_of(rep))
    return pooled


def _p_fails_more(lost: int, won: int) -> float:
    """One-sided exact McNemar p-value that the candidate fails more often: ``lost`` discordant pairs
    where it failed and the deployed policy landed, ``won`` the reverse (binomial, p = 1/2); 1 with
    no discordant pair."""
    from scipy import stats

    return float(stats.binomtest(lost, lost + won, 0.5, alternative="greater").pvalue) if lost + won else 1.0


def _holm(pvalues: list[float], alpha: float) -> list[bool]:
    """Holm's step-down rejections of ``pvalues`` at family-wise error rate ``alpha``."""
    order = sorted(range(len(pvalues)), key=lambda i: pvalues[i])
    reject = [False] * len(pvalues)
    for rank, i in enumerate(order):
        if pvalues[i] > alpha / (len(pvalues) - rank):
            break
        reject[i] = True
    return reject


def compare(deployed: list[dict], candidate: list[dict], alpha: float = ALPHA) -> Comparison:
    """Compare the candidate's site matrices with the deployed policy's, cell by cell (module doc).

    Args:
        deployed, candidate: site-matrix reports (sim_twin.evaluation.matrix.run_matrix) with per-throw data,
            one per start-pose seed, of one mode; both lists hold the same cells and seeds.
        alpha: family-wise error rate over all tests, in (0, 1).

    Raises:
        ValueError: empty lists, modes differ, alpha outside (0, 1), a report without per-throw
            data, or the two sides do not hold the same (profile, target, seed) throws.
    """
    from scipy import stats

    if not deployed or not candidate:
        raise ValueError("compare needs at least one site matrix on each side")
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    modes = {r.get("mode") for r in deployed + candidate}
    if len(modes) != 1:
        raise ValueError(f"site matrices of different modes: {sorted(map(str, modes))}")
    dep, cand = _pool(deployed), _pool(candidate)
    if set(dep) != set(cand):
        only = sorted(set(dep) ^ set(cand))[:3]
        raise ValueError(f"the two sides hold different throws (e.g. {only}): compare matrices of the same seeds, "
                         "targets, profiles and throws per cell")
    cells: dict[tuple[str, float], list[int]] = {}
    for key in dep:
        cells.setdefault(key[:2], []).append(key[2])
    raw: list[CellComparison] = []
    lost_all = won_all = 0
    for (profile, target), seeds in cells.items():
        d = [dep[(profile, target, s)] for s in seeds]
        c = [cand[(profile, target, s)] for s in seeds]
        lost = sum(1 for a, b in zip(d, c) if a is not None and b is None)  # candidate failed, deployed landed
        won = sum(1 for a, b in zip(d, c) if a is None and b is not None)
        lost_all, won_all = lost_all + lost, won_all + won
        p_success = _p_fails_more(lost, won)
        both = [(math.hypot(*a), math.hypot(*b)) for a, b in zip(d, c) if a is not None and b is not None]
        diffs = [b - a for a, b in both]
        p_miss = float(stats.wilcoxon(diffs, alternative="greater").pvalue) if any(diffs) else 1.0
        raw.append(CellComparison(
            profile, target, len(seeds), sum(a is not None for a in d), sum(b is not None for b in c), len(both),
            sum(a for a, _ in both) / len(both) if both else None, sum(b for _, b in both) / len(both) if both else None,
            p_success, p_miss))
    p_pooled = _p_fails_more(lost_all, won_all)
    reject = _holm([p for r in raw for p in (r.p_success, r.p_miss)] + [p_pooled], alpha)
    out = []
    for i, r in enumerate(raw):
        on = tuple(name for name, rej in zip(("success", "landing error"), reject[2 * i : 2 * i + 2]) if rej)
        out.append(CellComparison(**{**asdict(r), "worse": bool(on), "worse_on": on}))
    out.sort(key=lambda r: (r.profile, r.target_m))
    return Comparison(alpha, out, lost_all, won_all, p_pooled, reject[-1])


def table(comp: Comparison) -> str:
    """Plain-text table of a comparison, one line per cell, and the verdict."""

    def f(x: float | None) -> str:
        return "   -  " if x is None else f"{x:6.3f}"

    lines = [f"{'profile':>18} {'target':>6}  pairs  landed dep/cand  mean miss dep/cand [m]  p success  p miss",]
    for r in comp.cells:
        lines.append(f"{r.profile:>18} {r.target_m:5.1f} m {r.pairs:5d}  {r.landed_deployed:6d}/{r.landed_candidate:<6d}  "
                     f"{f(r.mean_miss_deployed_m)}/{f(r.mean_miss_candidate_m)}         {r.p_success:9.2g}  {r.p_miss:6.2g}"
                     + (f"  WORSE ({', '.join(r.worse_on)})" if r.worse else ""))
    lines.append(f"pooled over all cells: the candidate failed on {comp.pooled_lost} pairs the deployed policy landed, "
                 f"the reverse on {comp.pooled_won}; p success {comp.p_pooled_success:.2g}"
                 + ("  FAILS MORE OFTEN" if comp.fails_more else ""))
    lines.append(f"candidate worse on {comp.worse_cells} of {len(comp.cells)} cells"
                 + (" and fails more often over all cells" if comp.fails_more else "")
                 + f" (Holm, family-wise error rate {comp.alpha:g})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m sim_twin.evaluation.matrix_compare``: exit 0 when the candidate is worse on no cell and
    does not fail more often over all cells, 1 when it is or does, 2 on bad input (with the reason)."""
    p = argparse.ArgumentParser(prog="python -m sim_twin.evaluation.matrix_compare", description=__doc__.split("\n\n")[0])
    p.add_argument("--deployed", type=Path, nargs="+", required=True, help="site matrices of the deployed policy")
    p.add_argument("--candidate", type=Path, nargs="+", required=True, help="site matrices of the candidate (same seeds)")
    p.add_argument("--alpha", type=float, default=ALPHA)
    p.add_argument("--out", type=Path, default=None, help="also write the comparison as JSON")
    args = p.parse_args(argv)
    try:
        comp = compare([json.loads(f.read_text()) for f in args.deployed], [json.loads(f.read_text()) for f in args.candidate],
                       args.alpha)
    except (OSError, ValueError, KeyError) as e:
        print(f"matrix_compare: {e}", file=sys.stderr)
        return 2
    print(table(comp))
    if args.out:
        args.out.write_text(json.dumps({"alpha": comp.alpha, "worse_cells": comp.worse_cells, "fails_more": comp.fails_more,
                                        "pooled_lost": comp.pooled_lost, "pooled_won": comp.pooled_won,
                                        "p_pooled_success": comp.p_pooled_success,
                                        "deployed": [str(f) for f in args.deployed], "candidate": [str(f) for f in args.candidate],
                                        "cells": [asdict(c) for c in comp.cells]}, indent=1) + "\n")
    return 1 if comp.worse else 0


if __name__ == "__main__":
    raise SystemExit(main())
