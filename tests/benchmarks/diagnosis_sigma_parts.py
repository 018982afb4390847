"""Which part of the diagnosis' 1 sigma makes the benchmark's intervals wide: coverage per part.

Run: ``python tests/benchmarks/diagnosis_sigma_parts.py [--benchmark reports/diagnosis_benchmark.json ...]
[--report reports/diagnosis_sigma_parts.json]``. Reads committed benchmark reports (no replay,
no diagnosis; several: their parameters pooled, each case named by its seed) and, over their compared parameters (right answers only, as the benchmark's
coverage), gives for each part of the reported 1 sigma (``sigma_parts``: bootstrap spread,
Birge-scaled likelihood profile, between-throw scatter, back-fit shift; the diagnosis reports
their largest, :func:`sim_twin.diagnosis.forward.evaluate_candidate`) and for the reported sigma:
the share of parameters whose truth lies within 1 sigma, the median |fit - truth| / sigma
(0.67 for calibrated Gaussian errors) and how often that part is the largest. Also the binomial
standard error of a coverage on that many parameters. The report (JSON + .txt) is stamped
afterwards with ``slinger results --stamp``. No assertions.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

PARTS = ("bootstrap", "profile", "scatter", "backfit_shift")


def analyse(bench: dict | list[dict]) -> dict:
    """Coverage and median |z| per sigma part over the compared parameters of one benchmark
    report or of several pooled (cases then named ``seed:case``)."""
    benches = bench if isinstance(bench, list) else [bench]
    params = [(c["case"] if len(benches) == 1 else f"{b['seed']}:{c['case']}", p)
              for b in benches for c in b["cases"] if c.get("correct") for p in c.get("params", [])]
    info = [{k: b.get(k) for k in ("seed", "throws_per_case", "commit", "date", "complete")} for b in benches]
    pooled = {**{k: ", ".join(str(i[k]) for i in info) for k in info[0]}, "complete": all(i["complete"] for i in info)}
    out = {"benchmark": info[0] if len(benches) == 1 else pooled,
           "benchmarks": info, "parameters": len(params), "parts": {}}
    rows = []
    for case, p in params:
        err = abs(p["fit"] - p["truth"])
        parts = {k: v for k, v in (p.get("sigma_parts") or {}).items() if v}
        top = max(parts, key=parts.get) if parts else None
        rows.append({"case": case, "param": p["param"], "abs_error": err, "sigma": p["sigma"], "largest_part": top,
                     **{k: parts.get(k) for k in PARTS}})
    for k in PARTS + ("reported",):
        z = [r["abs_error"] / (r["sigma"] if k == "reported" else r[k]) for r in rows if (r["sigma"] if k == "reported" else r[k])]
        out["parts"][k] = {"n": len(z), "coverage": float(np.mean([x <= 1 for x in z])) if z else None,
                           "median_abs_z": float(np.median(z)) if z else None,
                           "largest_in": sum(r["largest_part"] == k for r in rows)}
    n = max(len(rows), 1)
    out["coverage_binomial_se_at_68pct"] = float(np.sqrt(0.68 * 0.32 / n))
    out["rows"] = rows
    return out


def format_report(r: dict) -> str:
    """The .txt summary of :func:`analyse`'s result."""
    b = r["benchmark"]
    lines = [f"1 sigma parts on the diagnosis benchmark (seed {b['seed']}, {b['throws_per_case']} throws per case, run commit {b['commit']}, "
             f"{'complete' if b['complete'] else 'PARTIAL'}): {r['parameters']} compared parameters; the binomial standard error of a "
             f"68 % coverage on them is {100 * r['coverage_binomial_se_at_68pct']:.0f} %",
             "  part            n   coverage  median |z|  largest in"]
    for k, v in r["parts"].items():
        cov = "n/a" if v["coverage"] is None else f"{100 * v['coverage']:.0f}%"
        mz = "n/a" if v["median_abs_z"] is None else f"{v['median_abs_z']:.2f}"
        lines.append(f"  {k:14s} {v['n']:3d}   {cov:>7s}   {mz:>8s}   {v['largest_in'] if k != 'reported' else '-'}")
    lines.append("  case param |fit - truth| reported sigma (largest part): bootstrap / profile / scatter / backfit_shift")
    for x in r["rows"]:
        lines.append(f"    {x['case']!s:>5s} {x['param']:22s} {x['abs_error']:.3g} {x['sigma']:.3g} ({x['largest_part']}): "
                     + " / ".join("-" if x[k] is None else f"{x[k]:.3g}" for k in PARTS))
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--benchmark", type=Path, action="append", default=[], help="benchmark report (repeatable: pooled; default reports/diagnosis_benchmark.json)")
    parser.add_argument("--report", type=Path, default=None)
    args = parser.parse_args()
    r = analyse([json.loads(b.read_text()) for b in args.benchmark or [Path("reports/diagnosis_benchmark.json")]])
    text = format_report(r)
    print(text)
    if args.report:
        args.report.write_text(json.dumps(r, indent=1) + "\n")
        args.report.with_suffix(".txt").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
