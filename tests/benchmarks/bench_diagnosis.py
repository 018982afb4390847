"""Wall and CPU time of a sim-to-real diagnosis (goals: 30 throws within 30 s, 300 within 3 min, on 2 cores).

Run: ``python tests/benchmarks/bench_diagnosis.py [--throws 30] [--case bias|asym3|friction ... |
--profile P.json | --dataset DIR ...] [--data-dir DIR] [--workers 2] [--report reports/diagnosis_speed.json]``.
Generates the logged throws with the simulated machine under each case's profile (the 2D policy
in the loop, logs like a real machine's; ``--data-dir`` keeps them and reuses them on the next
run with the same case, throws and seed), or takes existing dataset directories, then times
``diagnose`` on each (``workers`` processes for the candidate sweeps) and prints wall time, CPU
time (this process and its sweep processes) and the load average, which says how much of the
machine the run had. The cases: ``bias`` (impact measurement bias +0.25 m downrange: impact
only, the cheap kind), ``asym3`` (valve asymmetry on boom, dipper and telescope: per-joint
MuJoCo replays, the slowest kind), ``friction`` (passive viscous friction 0.6 1/s, the default).
The goals' command on 2 cores:
``taskset -c 0,1 python tests/benchmarks/bench_diagnosis.py --case bias --case asym3 --throws 30 --throws 300 --workers 2``.
The report (JSON + .txt) records date, commit, policy SHA-256, host and the command. No assertions.
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


CASES = {
    "friction": {"name": "worn_bearings", "effects": [{"effect": "passive_friction", "params": {"viscous_per_s": 0.6}}]},
    "bias": {"name": "impact_bias", "effects": [{"effect": "impact_bias", "params": {"bias_x_m": 0.25}}]},
    "asym3": {"name": "valve_asymmetry_3", "effects": [{"effect": "valve_asymmetry", "params": {
        "asymmetry_boom": 0.22, "asymmetry_dipper": -0.2, "asymmetry_telescope": 0.25}}]},
}
"""Hidden reality profiles of the timed datasets (``--case``)."""


def write_report(path: Path, rows: list[dict], commit: str, policy: Path) -> None:
    """The report (JSON + .txt) of the runs so far: written after every run, so that a run cut
    short keeps what finished."""
    res = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "commit": commit,
           "policy_sha256": hashlib.sha256(policy.read_bytes()).hexdigest(), "host": platform.node(), "cpu_count": os.cpu_count(),
           "cores_allowed": len(os.sched_getaffinity(0)), "command": " ".join(["python"] + sys.argv), "runs": rows}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(res, indent=1) + "\n")
    lines = [f"Diagnosis speed, {res['date']}, commit {commit}, policy throw2d.onnx sha256 {res['policy_sha256']}, host {res['host']} "
             f"({res['cpu_count']} cores, {res['cores_allowed']} allowed; SHARED with other work: see the load averages), command: {res['command']}"]
    lines += [f"  {r['dataset']}: {r['throws']} throws, workers {r['workers']}: wall {r['wall_s']:.1f} s, CPU {r['cpu_s']:.1f} s, "
              f"1-min load average {r['load_avg_1min_before']:.1f} -> {r['load_avg_1min_after']:.1f}; {r['verdict']} {' + '.join(r['effects'])}" for r in rows]
    path.with_suffix(".txt").write_text("\n".join(lines) + "\n")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--throws", type=int, action="append", default=[], help="throws per generated dataset (repeatable; default 30)")
    parser.add_argument("--case", choices=sorted(CASES), action="append", default=[], help="built-in hidden profile (repeatable)")
    parser.add_argument("--data-dir", type=Path, default=None, help="keep generated datasets here and reuse them")
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
    from sim_twin.twin.profile import RealityProfile

    policy = REPO / "policies" / "throw2d.onnx"
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO, check=False).stdout.strip()  # the code that runs
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        sets = list(args.dataset)
        if not sets:
            profiles = {c: CASES[c] for c in args.case}
            if args.profile:
                profiles[args.profile.stem] = RealityProfile.load(args.profile).to_dict()
            profiles = profiles or {"friction": CASES["friction"]}
            root = args.data_dir or Path(tmp)
            for name, prof in profiles.items():
                for throws in args.throws or [30]:
                    data = root / f"{name}_{throws}_seed{args.seed}"
                    if not (data / "index.json").is_file():
                        t0 = time.time()
                        dataset.generate(data, prof, throws, policy, seed=args.seed, workers=len(os.sched_getaffinity(0)), real_log=RealLogSpec())
                        print(f"generate {throws} throws under {name} (policy in the loop): {time.time() - t0:.1f} s")
                    sets.append(data)
        for d in sets:
            for w in args.workers or [2]:
                load0 = os.getloadavg()
                rep = diagnose(d, None, seed=args.seed, workers=w, plots=False)
                row = {"dataset": str(d), "throws": rep["throws"], "workers": rep["workers"], "wall_s": rep["wall_s"], "cpu_s": rep["cpu_s"],
                       "load_avg_1min_before": load0[0], "load_avg_1min_after": os.getloadavg()[0], "verdict": rep["verdict"]["answer"],
                       "effects": rep["verdict"].get("effects", [])}
                rows.append(row)
                print(f"{d}: {row['throws']} throws, workers {w}, cores allowed {len(os.sched_getaffinity(0))}: wall {row['wall_s']:.1f} s, CPU {row['cpu_s']:.1f} s, "
                      f"load average {load0[0]:.1f} -> {row['load_avg_1min_after']:.1f}; verdict {row['verdict']} {row['effects']}", flush=True)
                if args.report:
                    write_report(args.report, rows, commit, policy)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
