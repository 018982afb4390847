"""Is twice a stated detectable size found? The "no gap" verdict's power statement checked on datasets.

Run: ``python tests/benchmarks/bench_power_twice.py [--seed 0 --seed 1 ...] [--effect hanging_mass ...]
[--throws 30] [--no-sensor-spec] [--report reports/diagnosis_power_twice.json]``.

Per seed: 30 logged throws of the nominal machine (the 2D policy in the loop, real-log noise,
:class:`sim_twin.diagnosis.reallog.RealLogSpec`) are diagnosed; where the verdict is "no gap" its
power statement (:mod:`sim_twin.diagnosis.power`) gives each main candidate's detectable size. Then
for each main candidate a dataset with the same seed is generated with that candidate at its
nominal value plus TWICE the stated size, and diagnosed blind (whole library). "Found": the
verdict is not "no gap" (the where stage saw it); "named": the candidate is among the named or
consistent effects. The statement claims at least 80 % found.

Sensor spec: by default the datasets declare their sensor noise (index.json "sensors", as a site
that knows its sensors); with ``--no-sensor-spec`` they do not (the noise is measured from the
log's residuals, :func:`sim_twin.diagnosis.scoring.estimate_noise`), both for the nominal log
whose statement is checked and for the logs made at twice its sizes. Every row records which
(``sensor_spec``: "declared" or "measured"). ``--merge A.json B.json --report R.json`` puts
the runs of the two conditions side by side in one report (its ``figures``: per condition the
rate found with its one-sided 95 % Clopper-Pearson lower bound against the 80 % claim, the rate
named, and the stated sizes; a row without ``sensor_spec``, from a run before the option,
counts as "declared", the script's default then). Prints each case with the host's
load average; the report (JSON + .txt) records date, commit, policy SHA-256, host and command.
No assertions.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, action="append", default=[], help="dataset seed (repeatable; default 0)")
    parser.add_argument("--effect", action="append", default=[], help="main candidate (repeatable; default all of power.MAIN)")
    parser.add_argument("--throws", type=int, default=30)
    parser.add_argument("--workers", type=int, default=2, help="processes for generation and the candidate sweeps")
    parser.add_argument("--no-sensor-spec", action="store_true", help="datasets without a declared sensor spec (noise measured from the log)")
    parser.add_argument("--report", type=Path, default=None)
    parser.add_argument("--merge", type=Path, nargs="+", default=None, help="reports of runs to put side by side in --report (no new run)")
    args = parser.parse_args()
    if args.merge:
        if not args.report:
            parser.error("--merge needs --report")
        merge(args.merge, args.report)
        return 0
    from sim_twin.diagnosis import dataset
    from sim_twin.diagnosis.diagnose import diagnose
    from sim_twin.diagnosis.power import MAIN
    from sim_twin.diagnosis.reallog import RealLogSpec
    from sim_twin.twin.effects import effect_class

    policy = REPO / "policies" / "throw2d.onnx"
    from sim_twin.provenance import short_commit

    commit = short_commit() or "unknown"
    main_rows = [m for m in MAIN if not args.effect or m[0] in args.effect]
    spec = RealLogSpec(declare=not args.no_sensor_spec)
    sensor_spec = "declared" if spec.declare else "measured"
    rows: list[dict] = []
    seeds_used: list[dict] = []

    def write() -> None:
        if not args.report:
            return
        found = [r["found"] for r in rows]
        res = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "commit": commit,
               "policy_sha256": hashlib.sha256(policy.read_bytes()).hexdigest(), "host": platform.node(), "cpu_count": os.cpu_count(),
               "command": " ".join(["python"] + sys.argv), "throws": args.throws, "sensor_spec": sensor_spec, "seeds": seeds_used, "cases": rows,
               "found_rate": sum(found) / len(found) if found else None, "named_rate": sum(r["named"] for r in rows) / len(rows) if rows else None}
        args.report.parent.mkdir(parents=True, exist_ok=True)
        args.report.write_text(json.dumps(res, indent=1) + "\n")
        lines = [f"Twice the stated detectable size, {res['date']}, commit {commit}, policy throw2d.onnx sha256 {res['policy_sha256']}, "
                 f"host {res['host']}, command: {res['command']}",
                 f"found (verdict not 'no gap'): {sum(found)} of {len(found)}; named or consistent: {sum(r['named'] for r in rows)} of {len(rows)}"]
        lines += [f"  sensor spec: {sensor_spec}"]
        lines += [f"  seed {s['seed']}: nominal log verdict {s['answer']}" for s in seeds_used]
        lines += [f"  seed {r['seed']} {r['effect']} {r['param']} {r['nominal']:g} + 2 x {r['stated']:.4g} = {r['value']:.4g}: "
                  f"{r['answer']} {r['effects']} (found {r['found']}, named {r['named']})" for r in rows]
        args.report.with_suffix(".txt").write_text("\n".join(lines) + "\n")

    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seed or [0]:
            nominal = Path(tmp) / f"nominal_seed{seed}"
            dataset.generate(nominal, {"name": "nominal", "effects": []}, args.throws, policy, seed=seed, workers=args.workers, real_log=spec)
            rep = diagnose(nominal, None, seed=seed, workers=args.workers, plots=False)
            v = rep["verdict"]
            seeds_used.append({"seed": seed, "answer": v["answer"], "sensor_spec": sensor_spec, "noise_source": rep["where"]["noise"].get("source"),
                               "power": (v.get("power") or {}).get("effects")})
            print(f"seed {seed}: nominal log: {v['answer']} (load {os.getloadavg()[0]:.1f})", flush=True)
            if v["answer"] != "no_gap" or not v.get("power"):
                write()
                continue
            for name, param, _step, _ref, _unit, k in main_rows:
                stated = v["power"]["effects"].get(name, {}).get("min_change")
                if stated is None:
                    continue
                cls = effect_class(name)
                p = next(q for q in cls.params if q.name == param or q.name.startswith(param + "_"))
                value = min(p.nominal + 2 * stated / k, p.hi)
                data = Path(tmp) / f"{name}_seed{seed}"
                t0 = time.time()
                dataset.generate(data, {"name": f"twice_{name}", "effects": [{"effect": name, "params": {param: value}}]}, args.throws, policy,
                                 seed=seed, workers=args.workers, real_log=spec)
                r = diagnose(data, None, seed=seed, workers=args.workers, plots=False)["verdict"]
                names = set(r.get("effects", [])) | {n.get("effect") for n in r.get("not_confirmed", [])} | set(r.get("between") or [])
                row = {"seed": seed, "sensor_spec": sensor_spec, "effect": name, "param": param, "nominal": p.nominal, "stated": stated / k, "value": value,
                       "answer": r["answer"], "effects": r.get("effects", []), "found": r["answer"] != "no_gap", "named": name in names,
                       "wall_s": time.time() - t0, "load_avg_1min": os.getloadavg()[0]}
                rows.append(row)
                print(f"  {name} {param} = {value:.4g} (nominal {p.nominal:g} + 2 x {stated / k:.4g}): {r['answer']} {row['effects']} "
                      f"found {row['found']} named {row['named']} ({row['wall_s']:.0f} s, load {row['load_avg_1min']:.1f})", flush=True)
                write()
            write()
    return 0


def lower_bound(k: int, n: int, level: float = 0.95) -> float:
    """One-sided Clopper-Pearson lower bound of a rate, k found of n (0 for k = 0)."""
    from scipy.stats import beta

    return float(beta.ppf(1.0 - level, k, n - k + 1)) if k > 0 else 0.0


def merge(paths: list[Path], out: Path) -> dict:
    """One report of runs under either sensor-spec condition, side by side (module doc).

    Raises:
        ValueError: a file without cases.
    """
    runs = []
    for path in paths:
        body = json.loads(Path(path).read_text())
        if "cases" not in body:
            raise ValueError(f"{path}: not a bench_power_twice report")
        spec = body.get("sensor_spec", "declared")
        runs.append({"file": str(path), "sensor_spec": spec, "date": body.get("date"), "commit": body.get("commit"), "command": body.get("command"),
                     "host": body.get("host"), "note_load": body.get("note_load"), "provenance": body.get("provenance"),
                     "seeds": [{**s, "sensor_spec": s.get("sensor_spec", spec)} for s in body.get("seeds", [])],
                     "cases": [{**r, "sensor_spec": r.get("sensor_spec", spec)} for r in body["cases"]]})
    rows = [r for run in runs for r in run["cases"]]
    figures = []
    for spec in ("declared", "measured"):
        rs = [r for r in rows if r["sensor_spec"] == spec]
        if not rs:
            continue
        k, n, named = sum(r["found"] for r in rs), len(rs), sum(r["named"] for r in rs)
        lb = lower_bound(k, n)
        seeds = sorted({r["seed"] for r in rs})
        what = {"declared": "with a declared sensor spec", "measured": "without a sensor spec (noise measured from the log)"}[spec]
        sizes = {}
        for r in rs:
            sizes.setdefault(r["effect"], []).append(r["stated"])
        commits = sorted({run["commit"] for run in runs if run["sensor_spec"] == spec})
        figures.append({"what": f"twice the stated detectable size found (verdict not 'no gap'), {what}", "value": f"{k} of {n}",
                        "bar": "80 %", "met": bool(lb >= 0.8),
                        "conditions": f"one-sided 95 % lower bound of the rate {100 * lb:.0f} %; the candidate named, held consistent or in "
                                      f"the ambiguous pair in {named} of {n}; 30-throw logs of the simulated machine, seeds {seeds[0]}-{seeds[-1]}, "
                                      f"2D policy, real-log noise; commit {', '.join(commits)}",
                        "named": f"{named} of {n}", "stated": {e: [min(v), max(v)] for e, v in sizes.items()}})
    res = {"date": max(str(run["date"]) for run in runs), "runs": [{k: v for k, v in run.items() if k != "cases"} for run in runs],
           "cases": rows, "figures": figures}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1) + "\n")
    lines = ["Twice the stated detectable size, with and without a declared sensor spec (simulated machine, 2D policy, 30-throw logs)"]
    for f in figures:
        lines.append(f"  {f['what']}: {f['value']} (bar {f['bar']}: {'met' if f['met'] else 'NOT met'}); {f['conditions']}")
        lines.append("    stated sizes: " + "; ".join(f"{e} {lo:.4g}-{hi:.4g}" for e, (lo, hi) in f["stated"].items())
                     + " (s, kg, 1/s, s, m: the parameter's unit)")
    for run in runs:
        lines.append(f"run ({run['sensor_spec']}): {run['date']}, commit {run['commit']}, command: {run['command']}")
        lines += [f"  seed {s['seed']}: nominal log verdict {s['answer']}" for s in run["seeds"]]
        lines += [f"  seed {r['seed']} {r['effect']} {r['param']} {r['nominal']:g} + 2 x {r['stated']:.4g} = {r['value']:.4g}: "
                  f"{r['answer']} {r['effects']} (found {r['found']}, named {r['named']})" for r in run["cases"]]
    out.with_suffix(".txt").write_text("\n".join(lines) + "\n")
    return res


if __name__ == "__main__":
    raise SystemExit(main())
