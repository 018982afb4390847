"""Which effect is the gap between the engines? The step-size study.

The diagnosis of the Drake machine's logs against the MuJoCo twin (reports/drake_gap_2d) finds a
gap in the active joints' speeds and the gripper swing that no library effect explains. The two
engines differ in their integrator and step (MuJoCo implicitfast at 10 ms, Drake's SAP at 1 ms)
and in how the cylinder servo is applied (a velocity actuator whose setpoint holds for 10 ms,
Drake's implicit PD every step). This script replays the logged valve commands of the Drake
dataset's throws open loop, from the same start state, in three machines: the MuJoCo twin, the
Drake machine at its default 1 ms step, and the Drake machine at the twin's 10 ms step, and
reports per joint the RMS difference of speeds and positions between each pair over the swing.
If Drake at 10 ms sits close to MuJoCo, the gap is the step (the twin's 10 ms discretisation),
not the model.

Run: ``nice -n 10 python tests/benchmarks/drake_gap_step.py --dataset var/drake_gap_2d --throws 20 --report reports/drake_gap_step.json``
(the dataset from ``python -m sim_twin.diagnosis.drake_dataset --mode 2d --throws 60 --out var/drake_gap_2d``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def replay(machine, q0: np.ndarray, qd0: np.ndarray, valve_u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 6) true positions and speeds of ``machine`` driven by ``valve_u`` (T, 4) from (q0, qd0)."""
    machine.set_state(q0, qd0)
    qs, qds = [], []
    for u in valve_u:
        machine.step(u, False)
        qs.append(machine.data.qpos.copy())
        qds.append(machine.data.qvel.copy())
    return np.array(qs), np.array(qds)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", type=Path, default=Path("var/drake_gap_2d"))
    parser.add_argument("--throws", type=int, default=20)
    parser.add_argument("--report", type=Path, default=None)
    args = parser.parse_args()
    from runtime.machine import JOINT_NAMES
    from sim_twin.diagnosis import dataset
    from sim_twin.twin.drake_machine import DrakeMachine
    from sim_twin.twin.simulated_machine import SimulatedMachine

    throws, _ = dataset.load(args.dataset)
    throws = throws[: args.throws]
    machines = {"mujoco_10ms": SimulatedMachine(seed=0), "drake_1ms": DrakeMachine(seed=0), "drake_10ms": DrakeMachine(seed=0, time_step_s=0.01)}
    pairs = (("drake_1ms", "mujoco_10ms"), ("drake_10ms", "mujoco_10ms"), ("drake_1ms", "drake_10ms"))
    sq = {p: {"q": np.zeros(6), "qd": np.zeros(6)} for p in pairs}
    n, t0 = 0, time.time()
    for th in throws:
        q0 = th.q[0].copy()
        q0[4], q0[5] = -(q0[1] + q0[2]), 0.0  # start at rest, gripper plumb (the logged start is noisy)
        runs = {name: replay(m, q0, np.zeros(6), th.valve_u) for name, m in machines.items()}
        for a, b in pairs:
            sq[(a, b)]["q"] += ((runs[a][0] - runs[b][0]) ** 2).sum(axis=0)
            sq[(a, b)]["qd"] += ((runs[a][1] - runs[b][1]) ** 2).sum(axis=0)
        n += len(th.valve_u)
    rows = {}
    for (a, b), s in sq.items():
        key = f"{a} - {b}"
        rows[key] = {"rms_q": dict(zip(JOINT_NAMES, np.sqrt(s["q"] / n).round(6).tolist())),
                     "rms_qd": dict(zip(JOINT_NAMES, np.sqrt(s["qd"] / n).round(6).tolist()))}
        print(f"{key:26s} RMS speed difference [rad/s, m/s]: " + ", ".join(f"{j} {v:.4f}" for j, v in rows[key]["rms_qd"].items()))
        print(f"{'':26s} RMS position difference [rad, m]:  " + ", ".join(f"{j} {v:.4f}" for j, v in rows[key]["rms_q"].items()))
    print(f"{len(throws)} throws, {n} periods, {time.time() - t0:.0f} s; load average {os.getloadavg()}")
    if args.report:
        active = ("boom", "dipper", "telescope")
        fig = []
        for key in rows:
            fig.append({"what": f"{key}: RMS speed difference, boom / dipper / telescope / gripper_pitch",
                        "value": " / ".join(f"{rows[key]['rms_qd'][j]:.4f}" for j in (*active, "gripper_pitch")), "unit": "rad/s, m/s"})
        report = {"figures": fig, "pairs": rows, "throws": len(throws), "periods": n, "dataset": str(args.dataset),
                  "start": "the logged first row's active joints, at rest, gripper plumb", "load_average": list(os.getloadavg())}
        args.report.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
