"""Wall and CPU time of a sim-to-real diagnosis (goals: 30 throws within 30 s, 300 within 3 min, on 2 cores).

Run: ``python tests/benchmarks/bench_diagnosis.py [--throws 30] [--profile P.json | --dataset DIR ...]
[--workers 2] [--report reports/diagnosis_speed.json]``. Generates the logged throws with the
simulated machine under the profile (the 2D policy in the loop, logs like a real machine's), or
takes existing dataset directories, then times ``diagnose`` on each (``workers`` processes for
the candidate sweeps) and prints wall time, CPU time (this process and its sweep processes) and
the load average, which says how much of the machine the run had. The report (JSON + .txt)
records date, commit, policy SHA-256, host and the command. No assertions.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--throws", type=int, default=30)
    parser.add_argument("--profile", type=Path, default=None, help="hidden reality profile (default: passive viscous friction 0.6 1/s)")
    parser.add_argument("--dataset", type=Path, action="append", default=[], help="existing dataset directory (repeatable); no generation")
    parser.add_argument("--workers", type=int, action="append", default=[], help="sweep processes (repeatable; default 2)")
    parser.add_argument("--report", type=Path, default=None)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    from sim_twin.diagnosis import dataset
    from sim_twin.diagnosis.diagnose import diagnose
    from sim_twin.diagnosis.reallog import RealLogSpec
    from sim_twin.profile import RealityProfile

    policy = REPO / "policies" / "throw2d.onnx"
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO, check=False).stdout.strip()  # the code that runs
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        sets = list(args.dataset)
        if not sets:
            prof = RealityProfile.load(args.profile).to_dict() if args.profile else {"name": "worn_bearings", "effects": [{"effect": "passive_friction", "params": {"viscous_per_s": 0.6}}]}
            data = Path(tmp) / "throws"
            t0 = time.time()
            dataset.generate(data, prof, args.throws, policy, seed=args.seed, workers=os.cpu_count() or 1, real_log=RealLogSpec())
            print(f"generate {args.throws} throws (policy in the loop): {time.time() - t0:.1f} s")
            sets = [data]
        for d in sets:
            for w in args.workers or [2]:
                load0 = os.getloadavg()
                rep = diagnose(d, None, seed=args.seed, workers=w, plots=False)
                row = {"dataset": str(d), "throws": rep["throws"], "workers": rep["workers"], "wall_s": rep["wall_s"], "cpu_s": rep["cpu_s"],
                       "load_avg_1min_before": load0[0], "load_avg_1min_after": os.getloadavg()[0], "verdict": rep["verdict"]["answer"],
                       "effects": rep["verdict"].get("effects", [])}
                rows.append(row)
                print(f"{d}: {row['throws']} throws, workers {w}: wall {row['wall_s']:.1f} s, CPU {row['cpu_s']:.1f} s, "
                      f"load average {load0[0]:.1f} -> {row['load_avg_1min_after']:.1f}; verdict {row['verdict']} {row['effects']}")
    if args.report:
        res = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "commit": commit,
               "policy_sha256": hashlib.sha256(policy.read_bytes()).hexdigest(), "host": platform.node(), "cpu_count": os.cpu_count(),
               "command": " ".join(["python"] + sys.argv), "runs": rows}
        args.report.parent.mkdir(parents=True, exist_ok=True)
        args.report.write_text(json.dumps(res, indent=1) + "\n")
        lines = [f"Diagnosis speed, {res['date']}, commit {commit}, policy throw2d.onnx sha256 {res['policy_sha256']}, host {res['host']} "
                 f"({res['cpu_count']} cores, SHARED with other work: see the load averages), command: {res['command']}"]
        lines += [f"  {r['dataset']}: {r['throws']} throws, workers {r['workers']}: wall {r['wall_s']:.1f} s, CPU {r['cpu_s']:.1f} s, "
                  f"1-min load average {r['load_avg_1min_before']:.1f} -> {r['load_avg_1min_after']:.1f}; {r['verdict']} {' + '.join(r['effects'])}" for r in rows]
        args.report.with_suffix(".txt").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
