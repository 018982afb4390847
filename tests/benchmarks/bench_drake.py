"""Speed of one throw on the Drake machine (sim_twin.twin.drake_machine) against real time, on one core.

A throw is what evaluation runs per seed: a fresh machine at the seed's random start pose, then
the runtime's executor (policy, controller, release check) driving it through
sim_twin.twin.twin_machine.run_throw until the impact. Its wall time over the simulated time it
covers is the "x real time" figure (goal: <= 5, so the paper's protocol fits a CI budget at
reduced throws); the MuJoCo twin's is measured beside it, and the Drake physics alone per 10 ms
period (DrakeMachine.step with valves moving). The process is pinned to one core (``--core``);
the host's load average is printed and recorded before and after, because on a shared host the
wall time includes waiting for the core. No assertions.

Run: ``nice -n 10 python tests/benchmarks/bench_drake.py [--throws 5] [--core 0] [--report reports/drake_speed.json]``
then ``slinger results --stamp reports/drake_speed.json --title ... --command ... --policy ...``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
POLICIES = {"2d": REPO / "policies" / "throw2d.onnx", "3d": REPO / "policies" / "throw3d.onnx"}


def one_throw(engine: str, mode: str, seed: int, policy, check) -> dict:
    """One evaluation throw at 8.5 m on ``engine``: wall and CPU seconds of the machine's
    construction and of the throw, and the simulated seconds the throw covered."""
    from runtime.executor import ThrowExecutor
    from runtime.protocol.messages import ThrowRequest
    from sim_twin.twin.engines import make_machine
    from sim_twin.evaluation.evaluate import target_on_axis
    from sim_twin.twin.twin_machine import TwinMachine, run_throw

    t0, c0 = time.perf_counter(), time.process_time()
    sim = make_machine(engine, None, seed=seed)
    sim.reset(cabin_turn=0.0 if mode == "2d" else None)
    twin = TwinMachine(sim, "bench")
    build_s = time.perf_counter() - t0
    req = ThrowRequest(throw_id=f"b{seed}", machine_id="bench", mode=mode, target_m=target_on_axis(mode, 8.5))
    t1, c1, s1 = time.perf_counter(), time.process_time(), twin.sim_time_s()
    outcome, _ = run_throw(twin, ThrowExecutor({mode: policy}, release_check=check), req)
    wall, cpu, simulated = time.perf_counter() - t1, time.process_time() - c1, twin.sim_time_s() - s1
    return {"engine": engine, "mode": mode, "seed": seed, "status": None if outcome is None else outcome.status,
            "build_s": round(build_s, 4), "wall_s": round(wall, 4), "cpu_s": round(cpu, 4), "simulated_s": round(simulated, 3),
            "x_real_time": round(wall / simulated, 4), "cpu_x_real_time": round(cpu / simulated, 4), "setup_cpu_s": round(c1 - c0, 4)}


def physics_only(periods: int = 500) -> dict:
    """Drake physics alone: seconds per 10 ms period with the valves moving."""
    from sim_twin.twin.drake_machine import DrakeMachine

    m = DrakeMachine(seed=0)
    m.reset(q_active=[0.0, -0.6, 1.5, 0.9])
    u = np.array([0.4, -0.6, 0.5, 0.6])
    t, c = time.perf_counter(), time.process_time()
    for k in range(periods):
        m.step(u if (k // 100) % 2 == 0 else -u, False)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    return {"periods": periods, "wall_s_per_period": wall / periods, "cpu_s_per_period": cpu / periods,
            "x_real_time": wall / (periods * 0.01)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--throws", type=int, default=5, help="throws per engine and mode")
    parser.add_argument("--core", type=int, default=0, help="pin to this core (-1: no pinning)")
    parser.add_argument("--report", type=Path, default=None, help="JSON report to write")
    args = parser.parse_args()
    if args.core >= 0:
        os.sched_setaffinity(0, {args.core})
    from runtime.policy import PolicyRunner
    from runtime.release_check import ReleaseCheck

    load_before = os.getloadavg()
    check = ReleaseCheck.load()
    policies = {mode: PolicyRunner.load(p) for mode, p in POLICIES.items()}
    one_throw("drake", "2d", 10_000, policies["2d"], check)  # imports, URDF export, first build
    one_throw("mujoco", "2d", 10_000, policies["2d"], check)
    rows = [one_throw(engine, mode, seed, policies[mode], check)
            for mode in ("2d", "3d") for engine in ("drake", "mujoco") for seed in range(args.throws)]
    phys = physics_only()
    load_after = os.getloadavg()
    summary = {}
    for engine in ("drake", "mujoco"):
        r = [x for x in rows if x["engine"] == engine]
        summary[engine] = {"median_x_real_time": statistics.median(x["x_real_time"] for x in r),
                           "max_x_real_time": max(x["x_real_time"] for x in r),
                           "median_cpu_x_real_time": statistics.median(x["cpu_x_real_time"] for x in r),
                           "median_simulated_s": statistics.median(x["simulated_s"] for x in r),
                           "median_build_s": statistics.median(x["build_s"] for x in r)}
    host = {"cores_visible": os.cpu_count(), "pinned_core": args.core, "load_average_before": [round(v, 2) for v in load_before],
            "load_average_after": [round(v, 2) for v in load_after], "nice": os.nice(0)}
    for engine, s in summary.items():
        print(f"{engine:7s}: one throw {s['median_x_real_time']:.3f}x real time (median; max {s['max_x_real_time']:.3f}x, "
              f"CPU {s['median_cpu_x_real_time']:.3f}x), {s['median_simulated_s']:.1f} simulated s, machine built in {s['median_build_s']:.3f} s")
    print(f"drake physics alone: {phys['wall_s_per_period'] * 1e3:.2f} ms per 10 ms period ({phys['x_real_time']:.3f}x real time)")
    print(f"host: load average {host['load_average_before']} before, {host['load_average_after']} after; "
          f"{host['cores_visible']} cores, pinned to core {args.core}, nice {host['nice']}")
    if args.report:
        d = summary["drake"]
        report = {"figures": [
            {"what": "one Drake throw (evaluation throw at 8.5 m, 2D and 3D), wall / simulated time, median", "value": round(d["median_x_real_time"], 3),
             "unit": "x real time", "bar": "<= 5", "met": d["max_x_real_time"] <= 5.0},
            {"what": "one Drake throw, wall / simulated time, max", "value": round(d["max_x_real_time"], 3), "unit": "x real time"},
            {"what": "one MuJoCo twin throw, wall / simulated time, median", "value": round(summary["mujoco"]["median_x_real_time"], 3),
             "unit": "x real time"},
            {"what": "Drake physics alone per 10 ms period", "value": round(phys["wall_s_per_period"] * 1e3, 3), "unit": "ms"},
        ], "summary": summary, "physics_only": phys, "host_load": host, "throws": rows}
        args.report.write_text(json.dumps(report, indent=1) + "\n")
        print(f"report: {args.report}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
