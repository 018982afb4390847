"""Site-matrix wall time by the policy session's onnxruntime threads, side by side in one run.

    python tests/benchmarks/bench_policy_threads.py --policy policies/throw2d.onnx --threads 1,0,8 --workers 2

Runs the same part of the site matrix (``slinger evaluate --matrix``: every profile, ``--targets``,
``--throws`` per cell, seed 0) once per ``$SLINGER_POLICY_THREADS`` setting (runtime.policy.session_options:
1 is the default, 0 onnxruntime's own default of a spinning thread per physical core, N a pool of N),
each in its own process with ``--workers`` pool processes, and prints the wall times, their ratio to the
first setting and the host's 1-minute load beside each. The matrix workers each hold a policy session,
so a pool per session multiplies: on a 64-core GPU host onnxruntime's default gave each of the
gate's 14 workers a pool of 32 threads. ``N`` larger than the cores here shows the oversubscription
a many-core host's default causes. Writes JSON with ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def run_once(policy: Path, threads: str, workers: int, targets: str, throws: int) -> dict:
    """One site-matrix part with ``$SLINGER_POLICY_THREADS=threads``: wall seconds and the load."""
    env = {**os.environ, "SLINGER_POLICY_THREADS": threads, "OMP_NUM_THREADS": "1",
           "CUDA_VISIBLE_DEVICES": "", "JAX_PLATFORMS": "cpu"}
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "sim_twin.evaluation.cli", "--policy", str(policy), "--matrix",
                        "--seed", "0", "--throws", str(throws), "--targets", targets, "--workers", str(workers),
                        "--out", str(Path(tmp) / "m.json")], cwd=ROOT, env=env, check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
    return {"threads": threads, "wall_s": round(wall, 2), "load_1min_before": round(load, 2)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", type=Path, default=ROOT / "policies" / "throw2d.onnx")
    p.add_argument("--threads", default="1,0", help="comma-separated $SLINGER_POLICY_THREADS settings")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    p.add_argument("--targets", default="9.5,10")
    p.add_argument("--throws", type=int, default=20, help="throws per cell")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    rows = [run_once(args.policy, t, args.workers, args.targets, args.throws) for t in args.threads.split(",")]
    base = rows[0]["wall_s"]
    print(f"{'threads':>8} {'wall s':>8} {'ratio':>6} {'load':>5}")
    for r in rows:
        r["ratio_to_first"] = round(r["wall_s"] / base, 3)
        print(f"{r['threads']:>8} {r['wall_s']:>8.1f} {r['ratio_to_first']:>6.2f} {r['load_1min_before']:>5.1f}")
    out = {"host": platform.node(), "cpus": os.cpu_count(), "workers": args.workers, "targets": args.targets,
           "throws_per_cell": args.throws, "policy": str(args.policy), "rows": rows}
    if args.out:
        args.out.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
