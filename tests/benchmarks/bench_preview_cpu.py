"""CPU seconds of one preview ellipse, the code of a base revision against this checkout, side by
side in one run.

What is timed is what a worker's ellipse job computes after the console's nominal preview: the
Monte Carlo of sim_twin.preview.preview.preview_throw (``rollouts`` impacts from the profile's full
rollouts, PARAM_ROLLOUTS = 16 by default) with the nominal rollout taken from the worker's
NominalCache (filled by one untimed call first), all in one process (no pool: every rollout's CPU is
counted by ``time.process_time``). The base revision's tree is exported with ``git archive`` into
a temporary directory; each side runs in its own Python process (the same interpreter), and the
runs alternate old, new, new, old, ... so that a shared host's load falls on both alike. Both sides
preview the same requests (policies/throw2d.onnx and throw3d.onnx of THIS checkout, the server's
default site profile, fixed seeds), and the script checks that their summaries are equal (the
ellipse, every impact, the nominal's fields).

Run: ``python tests/benchmarks/bench_preview_cpu.py [--base REV] [--rounds 4] [--repeats 3]``.
Prints the host's cores and 1-min load average before and after, each run's median CPU seconds
per ellipse and per nominal preview (the console's first request: one rollout, not cached), and
per mode the medians of both sides and their ratio (new / old). No assertions
beyond the equality check (exit status 1 when the summaries differ).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
BASE = "e91987a"
"""The code before the preview's CPU cuts (issue 45, item 8): runtime's controller, clearance
check, executor history, sensing effects, valves and model copies as they were."""
TARGETS = {"2d": [[7.5, -0.292, 0.0], [8.5, -0.292, 0.0], [9.5, -0.292, 0.0]],
           "3d": [[7.5, 1.0, 0.0], [8.5, 1.0, 0.0], [9.5, 1.0, 0.0]]}


def child(root: str, mode: str, repeats: int, rollouts: int) -> dict:
    """In a fresh process: import the code under ``root`` and time ``repeats`` ellipses per target
    of ``mode``. Returns {"root": where runtime was imported from, "cpu_s": [...], "summaries": {...}}."""
    sys.path.insert(0, root)
    import numpy as np

    import runtime
    from runtime.policy import PolicyRunner
    from sim_twin.preview.preview import NominalCache, PreviewRequest, preview_throw, site_profile, warm_imports
    from sim_twin.twin.initial_pose import sample_pose

    warm_imports()
    policy = PolicyRunner.load(REPO / "policies" / f"throw{mode}.onnx")
    profile = site_profile(None, Path(root) / "sim_twin" / "profiles" / "nominal_uncertain.json")
    rng = np.random.default_rng(1)
    cpu, cpu_nominal, summaries = [], [], {}
    for i, target in enumerate(TARGETS[mode]):
        q = sample_pose(rng, cabin_turn=0.0)
        req = PreviewRequest(mode, target, q.tolist(), [0.0] * 6, rollouts=rollouts, seed=i)
        nominals = NominalCache()
        preview_throw(policy, req, profile, nominals=nominals)  # the nominal, cached (and warm-up)
        for _ in range(repeats):
            c = time.process_time()
            s = preview_throw(policy, req, profile, nominals=nominals)
            cpu.append(time.process_time() - c)
        s.pop("timing_s", None)
        summaries[str(i)] = s
        for _ in range(repeats):  # the console's first request: the nominal rollout alone, not cached
            c = time.process_time()
            preview_throw(policy, dataclasses.replace(req, rollouts=1), profile)
            cpu_nominal.append(time.process_time() - c)
    return {"root": str(Path(runtime.__file__).resolve().parent.parent), "cpu_s": cpu, "cpu_nominal_s": cpu_nominal,
            "summaries": summaries}


def _run_child(root: Path, mode: str, repeats: int, rollouts: int) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", str(root), "--mode", mode, "--repeats", str(repeats),
                          "--rollouts", str(rollouts)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default=BASE, help=f"base revision (default {BASE})")
    ap.add_argument("--rounds", type=int, default=4, help="old/new pairs of runs per mode")
    ap.add_argument("--repeats", type=int, default=3, help="ellipses per target per run (3 targets)")
    ap.add_argument("--rollouts", type=int, default=200)
    ap.add_argument("--modes", default="2d,3d")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--mode", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.mode, args.repeats, args.rollouts)))
        return 0

    rev = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", args.base], capture_output=True, text=True,
                         check=True).stdout.strip()
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                          check=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True).stdout.strip())
    print(f"cores: {os.cpu_count()}, 1-min load average {os.getloadavg()[0]:.1f} at the start")
    print(f"old: {rev} (git archive), new: this checkout ({head}{', with uncommitted changes' if dirty else ''})")
    print(f"each run: {len(TARGETS['2d'])} targets x {args.repeats} ellipses of {args.rollouts} impacts, nominal cached, "
          "no pool; CPU = time.process_time of the run's process")
    same = True
    with tempfile.TemporaryDirectory() as tmp:
        old_root = Path(tmp) / "old"
        old_root.mkdir()
        archive = subprocess.run(["git", "-C", str(REPO), "archive", rev, "runtime", "sim_twin"], capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", str(old_root)], input=archive.stdout, check=True)
        results = {}
        for mode in args.modes.split(","):
            cpu = {"old": [], "new": []}
            nominal = {"old": [], "new": []}
            for r in range(args.rounds):
                order = ("old", "new") if r % 2 == 0 else ("new", "old")
                for side in order:
                    res = _run_child(old_root if side == "old" else REPO, mode, args.repeats, args.rollouts)
                    want = str(old_root if side == "old" else REPO)
                    if res["root"] != want:
                        raise RuntimeError(f"{side} run imported runtime from {res['root']}, not {want}")
                    cpu[side] += res["cpu_s"]
                    nominal[side] += res["cpu_nominal_s"]
                    print(f"  {mode} round {r + 1} {side}: median {statistics.median(res['cpu_s']):.3f} CPU s per ellipse, "
                          f"{statistics.median(res['cpu_nominal_s']):.3f} per nominal (load {os.getloadavg()[0]:.1f})", flush=True)
                    if side == "old":
                        old_summaries = res["summaries"]
                    else:
                        new_summaries = res["summaries"]
                if old_summaries != new_summaries:
                    same = False
                    print(f"  {mode} round {r + 1}: the summaries DIFFER")
            results[mode] = (cpu, nominal)
    print(f"1-min load average {os.getloadavg()[0]:.1f} at the end")
    print(f"medians over {args.rounds * len(TARGETS['2d']) * args.repeats} previews of each kind and side:")
    print(f"{'mode':5s} {'preview':8s} {'old CPU s':>10s} {'new CPU s':>10s} {'new/old':>8s}")
    for mode, (cpu, nominal) in results.items():
        for kind, vals in (("ellipse", cpu), ("nominal", nominal)):
            o, n = statistics.median(vals["old"]), statistics.median(vals["new"])
            print(f"{mode:5s} {kind:8s} {o:10.3f} {n:10.3f} {n / o:8.2f}")
    print("summaries (ellipse, impacts, nominal): " + ("identical" if same else "DIFFERENT"))
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
