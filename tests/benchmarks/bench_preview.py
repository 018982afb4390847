"""Preview latency on this machine: the single-rollout preview (nominal swing in the twin) and
the 200-rollout Monte Carlo impact ellipse, both through the HTTP API (POST /api/previews, what
the console calls: a job run by a `slinger worker` process started here) and of
sim_twin.preview.preview.preview_throw alone.

Run: ``python tests/benchmarks/bench_preview.py [--repeats 10] [--profile P] [--processes N ...]
[--policy NAME=path.onnx ...] [--out report.json]``.
Prints median / max wall seconds per case and the bar (0.3 s single rollout, 1.5 s for 200
rollouts), the function alone with its Monte Carlo in 1 and in 2 processes, and for the
function alone also the CPU seconds of this process (what the wall time is on an idle core when
the machine is shared); no assertions. With ``--policy`` given more than once the function-alone
cases run for each 2D policy in turn in one run (a candidate's preview cost beside the deployed
policy's: a policy whose throws last longer previews longer); the HTTP part always uses the
deployed policy. ``--out`` writes the printed lines and each case's median and max as JSON. The default profile is the server's default site profile
(sim_twin.preview.preview.DEFAULT_SITE_PROFILE: parameter ranges, start-state model, release jitter).
The HTTP part uses the app with a loopback Zenoh peer and a fake runtime that reports the trained
2D policy from different start poses (tests.conftest.FakeRuntime).
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # tests.conftest (the fake runtime)
POLICY = REPO / "policies" / "throw2d.onnx"
TARGETS = [[d, -0.292, 0.0] for d in (7.5, 8.0, 8.5, 9.0, 9.5)]


def bench_function(repeats: int, profile_path: Path | None, processes: int = 0, policy_path: Path = POLICY) -> tuple[dict, dict]:
    """preview_throw alone with the 2D policy ``policy_path``; with ``processes`` >= 2 its Monte Carlo
    runs in a pool of that many processes (as a worker runs it, Settings.preview_processes). CPU is
    this process's only. Returns ({rollouts: [wall s]}, {rollouts: [CPU s]})."""
    from runtime.policy import PolicyRunner
    from sim_twin.preview.preview import PreviewRequest, preview_throw, site_profile, warm_up
    from sim_twin.twin.initial_pose import sample_pose
    from sim_twin.twin.pools import process_pool

    pool = None
    if processes >= 2:
        pool = process_pool(processes)
        warm_up(pool, processes)
    policy = PolicyRunner.load(policy_path)
    profile = site_profile(None, profile_path)
    rng = np.random.default_rng(0)
    preview_throw(policy, PreviewRequest("2d", TARGETS[0], sample_pose(rng, cabin_turn=0.0).tolist(), [0.0] * 6, rollouts=24), profile)  # imports
    out, cpu = {}, {}
    for rollouts in (1, 200):
        times, cpus = [], []
        for i in range(repeats):
            q = sample_pose(rng, cabin_turn=0.0)
            t, c = time.perf_counter(), time.process_time()
            s = preview_throw(policy, PreviewRequest("2d", TARGETS[i % len(TARGETS)], q.tolist(), [0.0] * 6, rollouts=rollouts), profile,
                              pool=pool)
            times.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
            assert s["status"] in ("ok", "failed")
        out[rollouts], cpu[rollouts] = times, cpus
    if pool is not None:
        pool.shutdown()
    return out, cpu


def bench_http(repeats: int) -> dict:
    from fastapi.testclient import TestClient

    from runtime.protocol.messages import PolicyInfo
    from server.app import create_app
    from server.config import Settings
    from tests.conftest import ADMIN, FakeRuntime, add_user, free_port, login, wait_for, wait_online
    from tests.fleet_site import Worker

    manifest = json.loads(POLICY.with_suffix(".json").read_text())
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), zenoh_listen=[endpoint], viser_enabled=False, auto_migrate=True)
        with TestClient(create_app(settings)) as client, Worker(settings, "--lanes", "fast") as worker:
            wait_for(lambda: "consuming" in worker.text(), 120, "preview worker up")  # previews are jobs
            add_user(client.app.state.sessions, *ADMIN, "admin")
            login(client, *ADMIN)
            client.app.state.store.register_policy(manifest, onnx_path=POLICY)
            rt = FakeRuntime(endpoint, policies=[PolicyInfo(mode="2d", version=manifest["name"], sha256=manifest["onnx_sha256"])])
            try:
                wait_online(client)
                out = {}
                for rollouts in (1, 200):
                    times = []
                    for i in range(repeats + 1):
                        t = time.perf_counter()
                        r = client.post("/api/previews", json={"machine_id": "m1", "mode": "2d",
                                                               "target": TARGETS[i % len(TARGETS)], "rollouts": rollouts})
                        dt = time.perf_counter() - t
                        assert r.status_code == 200, r.text
                        if i > 0 or rollouts == 200:  # the very first call loads the policy
                            times.append(dt)
                    out[rollouts] = times
            finally:
                rt.close()
    return out


def main() -> int:
    logging.basicConfig(level=logging.WARNING)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--profile", type=Path, default=None, help="site profile (default: the server's default)")
    ap.add_argument("--no-http", action="store_true")
    ap.add_argument("--processes", type=int, action="append", default=[],
                    help="Monte Carlo processes of the function runs (repeatable; default 1 and 2)")
    ap.add_argument("--policy", action="append", default=[],
                    help="NAME=path.onnx of a 2D policy for the function runs (repeatable; default the deployed one)")
    ap.add_argument("--out", type=Path, default=None, help="also write the lines and figures as JSON here")
    args = ap.parse_args()
    import os

    policies = []
    for spec in args.policy or [f"deployed={POLICY}"]:
        name, sep, path = spec.partition("=")
        if not sep or not Path(path).is_file():
            ap.error(f"--policy {spec!r}: give NAME=path.onnx of an existing file")
        policies.append((name, Path(path)))
    lines = [f"cores: {os.cpu_count()}, load average {os.getloadavg()[0]:.1f}"]
    print(lines[0])
    cases = []  # (printed name, {"policy", "processes", "clock"}, {rollouts: times})
    for name, path in policies:
        label = "" if len(policies) == 1 else f"{name} "
        for n in args.processes or [1, 2]:
            wall, cpu = bench_function(args.repeats, args.profile, n, path)
            case = {"policy": label.strip(), "processes": n}
            cases += [(f"{label}preview_throw() x{n}", {**case, "clock": "wall"}, wall),
                      (f"{label}preview_throw() x{n} CPU", {**case, "clock": "cpu"}, cpu)]
    if not args.no_http:
        cases.append(("POST /api/previews", {"policy": "", "processes": None, "clock": "wall"}, bench_http(args.repeats)))
    figures = []
    for name, case, res in cases:
        for rollouts, times in res.items():
            bar = 0.3 if rollouts == 1 else 1.5
            lines.append(f"{name:22s} rollouts={rollouts:3d}: median {statistics.median(times):.3f} s, "
                         f"max {max(times):.3f} s over {len(times)} (bar {bar} s)")
            print(lines[-1])
            figures.append({"case": name, **case, "rollouts": rollouts, "median_s": round(statistics.median(times), 4),
                            "max_s": round(max(times), 4), "n": len(times), "bar_s": bar})
    lines.append(f"load average after: {os.getloadavg()[0]:.1f}")
    print(lines[-1])
    if args.out:
        report = {"policies": {n: str(p) for n, p in policies}, "figures": report_figures(figures), "measures": figures,
                  "output": lines}
        args.out.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def report_figures(measures: list[dict]) -> list[dict]:
    """The report's figures (docs/results.md's layout: what, value, unit, bar, met, conditions) of
    the measures main prints (``[{"case", "policy", "processes", "clock", "rollouts", "median_s", "max_s",
    "n", "bar_s"}]``; ``processes`` None for the HTTP case): one per wall-clock case and rollout count,
    CPU-time cases left out; the bar applies to the median."""
    out = []
    for m in measures:
        if m["clock"] == "cpu":
            continue
        kind = "single-rollout preview" if m["rollouts"] == 1 else f"{m['rollouts']}-impact ellipse preview"
        if m["processes"] is None:
            what = f"{m['case']}, {kind}"
        else:
            where = "in one process" if m["processes"] == 1 else f"with {m['processes']} Monte Carlo processes"
            what = " ".join(s for s in (m["policy"], kind, where) if s)
        out.append({"what": f"{what}, median / max", "value": f"{m['median_s']:.3f} / {m['max_s']:.3f}", "unit": "s",
                    "bar": f"median <= {m['bar_s']} s", "met": m["median_s"] <= m["bar_s"], "conditions": f"{m['n']} previews"})
    return out

if __name__ == "__main__":
    raise SystemExit(main())
