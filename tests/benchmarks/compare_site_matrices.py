"""Cell-by-cell comparison of two site matrices (a candidate policy against the deployed one).

``python tests/benchmarks/compare_site_matrices.py DEPLOYED.json CANDIDATE.json [...pairs]`` prints,
for every (profile, target) cell, success, |bias| and downrange sigma of both and whether the
candidate is worse (lower success, or larger |bias| or sigma by more than 0.005 m), and the count of
worse cells. docs/training.md "Deploying a new version": a from-scratch policy replaces the
deployed one only where it is worse on no cell.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

TOL_M = 0.005  # differences below 5 mm are within a 100-throw cell's sampling noise for sigma ~0.05-0.1 m (CHOSEN)


def cells(path: Path) -> dict[tuple[str, float], dict]:
    """(profile, target_m) -> cell of a site-matrix report (sim_twin.matrix)."""
    rep = json.loads(path.read_text())
    return {(p["name"], c["target_m"]): c for p in rep["profiles"] for c in p["targets"]}


def worse(dep: dict, cand: dict) -> bool:
    """Whether the candidate's cell is worse than the deployed one's."""
    return (cand["success_rate"] < dep["success_rate"] or abs(cand["bias_m"]) > abs(dep["bias_m"]) + TOL_M
            or cand["sigma_downrange_m"] > dep["sigma_downrange_m"] + TOL_M)


def main(argv: list[str]) -> int:
    total = 0
    for dep_path, cand_path in zip(argv[::2], argv[1::2]):
        dep, cand = cells(Path(dep_path)), cells(Path(cand_path))
        n = 0
        print(f"{dep_path} (deployed) vs {cand_path} (candidate): |bias| / sigma down [m]")
        for key in sorted(dep):
            d, c = dep[key], cand[key]
            w = worse(d, c)
            n += w
            print(f"  {key[0]:>18} {key[1]:5.1f} m  {abs(d['bias_m']):.3f}/{d['sigma_downrange_m']:.3f}  "
                  f"{abs(c['bias_m']):.3f}/{c['sigma_downrange_m']:.3f}{'  WORSE' if w else ''}")
        print(f"  candidate worse on {n} of {len(dep)} cells")
        total += n
    return 0 if total == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
