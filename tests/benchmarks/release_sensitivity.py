"""How fast a 2D policy's landing point moves around the release, on the CPU twin.

``python tests/benchmarks/release_sensitivity.py NAME=SPEC ... --out reports/training_release_sensitivity_2d.json``

For each policy, ``--throws`` throws at ``--target-m`` (nominal twin, the runtime's executor, the
release check on, start-pose seeds 0..N-1) and, from the simulated machine's payload state at every
10 ms physics step, the drag-free landing point (x, y) of the held payload if it were freed then
(runtime.ballistics, as the training environment's ``held_impact``). Two speeds of that landing
point, m/s, per throw:

* ``at_opening``: over the physics step before the gripper physically opened (what the training
  environment's ``release_slope`` reward term measures, sim_twin.training.mjx_env);
* ``at_command``: at the control step the policy commanded the release, the release delay
  (about 0.26 s) before the opening.

A landing that an opening-time error of dt moves by about speed x dt: the speed is the throw's
sensitivity to release-timing errors (release-delay jitter, sensor latency). Also per throw: the
release command and the opening after the throw's start (s) and the downrange error (m).

SPEC is an ONNX policy (``policies/training/throw2d-scratch-u/throw2d.onnx``) or a run, a directory or
``REV:RUN_DIR`` kept in git (``903fcd5:policies/training/throw2d-scratch-ab``; training_throw_style.RunSource),
whose ``checkpoint.pt`` is exported with its ``config.json`` (sim_twin.training.export). Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from tests.benchmarks.training_throw_style import RunSource  # noqa: E402

PHYSICS_PERIOD_S = 0.01


def policy_file(spec: str, tmp: Path) -> Path:
    """The ONNX file of ``spec`` (see the module docstring); a run is exported into ``tmp``.

    Raises:
        FileNotFoundError: the run has no checkpoint.pt or config.json.
    """
    if spec.endswith(".onnx"):
        return Path(spec)
    from sim_twin.training.export import export_checkpoint

    run = RunSource(spec, REPO)
    ckpt = tmp / f"{run.name}.pt"
    ckpt.write_bytes(run.read_bytes("checkpoint.pt"))
    return export_checkpoint(ckpt, json.loads(run.read("config.json")), tmp / f"{run.name}.onnx", run.name)


class _Recorder:
    """A twin seen through sim_twin.twin.twin_machine.run_throw: keeps every state it hands out
    (``states``, 10 ms apart after the first two, which the executor's start and first tick both
    read) and the index of the state at which the release was first commanded (``command_at``)."""

    def __init__(self, twin):
        self.twin, self.states, self.command_at = twin, [], None

    def __getattr__(self, name):
        return getattr(self.twin, name)

    def state(self):
        st = self.twin.state()
        self.states.append(st)
        return st

    def step(self, valve_u, gripper_open):
        if gripper_open and self.command_at is None:
            self.command_at = len(self.states) - 1
        return self.twin.step(valve_u, gripper_open)


def one_throw(policy, check, seed: int, target_m: float) -> dict:
    """One nominal 2D throw at ``target_m``; the landing-point speeds and timings of the module docstring."""
    from runtime.ballistics import ground_impact
    from runtime.executor import ExecutorConfig, ThrowExecutor
    from runtime.protocol.messages import ThrowRequest
    from sim_twin.evaluation.evaluate import target_on_axis
    from sim_twin.twin.engines import make_machine
    from sim_twin.twin.profile import RealityProfile
    from sim_twin.twin.twin_machine import TwinMachine, run_throw

    sim = make_machine("mujoco", RealityProfile(), seed=seed)
    sim.reset(cabin_turn=0.0)
    twin = _Recorder(TwinMachine(sim, "eval"))
    ex = ThrowExecutor({"2d": policy}, config=ExecutorConfig(), release_check=check)
    req = ThrowRequest(throw_id=f"s{seed}", machine_id="eval", mode="2d", target_m=target_on_axis("2d", target_m))
    outcome, _ = run_throw(twin, ex, req)
    open_at = next((i for i, st in enumerate(twin.states) if st.gripper_open), None)
    if outcome is None or outcome.status != "landed" or twin.command_at is None or open_at is None:
        return {"seed": seed, "landed": False}
    held = twin.states[:open_at]
    points = [ground_impact(np.asarray(st.payload_pos_m), np.asarray(st.payload_vel_mps))[0][:2] for st in held]
    speed = lambda i, j: float(np.linalg.norm(points[j] - points[i]) / ((j - i) * PHYSICS_PERIOD_S))  # noqa: E731
    return {"seed": seed, "landed": True, "downrange_error_m": outcome.downrange_error_m,
            "command_after_s": (twin.command_at - 1) * PHYSICS_PERIOD_S, "opening_after_s": (open_at - 1) * PHYSICS_PERIOD_S,
            "at_opening_mps": speed(open_at - 2, open_at - 1), "at_command_mps": speed(twin.command_at - 1, twin.command_at + 1)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("policies", nargs="+", help="NAME=SPEC (an ONNX file, or a run: a directory or REV:RUN_DIR in git)")
    ap.add_argument("--target-m", type=float, default=10.0)
    ap.add_argument("--throws", type=int, default=12)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)

    from runtime.policy import PolicyRunner, sha256_of
    from runtime.release_check import ReleaseCheck

    check = ReleaseCheck.load()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for item in args.policies:
            name, _, spec = item.partition("=")
            path = policy_file(spec, Path(tmp))
            policy = PolicyRunner.load(path)
            throws = [one_throw(policy, check, seed, args.target_m) for seed in range(args.throws)]
            ok = [t for t in throws if t["landed"]]
            summary = {key: float(np.mean([t[key] for t in ok])) for key in
                       ("at_opening_mps", "at_command_mps", "command_after_s", "opening_after_s")}
            summary["downrange_sigma_m"] = float(np.std([t["downrange_error_m"] for t in ok]))
            rows.append({"name": name, "spec": spec, "policy_sha256": sha256_of(path), "landed": len(ok),
                         **summary, "throws": throws})
            print(f"{name:24s} landed {len(ok):3d}/{len(throws)}  speed at opening {summary['at_opening_mps']:5.2f} m/s"
                  f"  at command {summary['at_command_mps']:5.2f} m/s  command {summary['command_after_s']:.2f} s"
                  f"  opening {summary['opening_after_s']:.2f} s  sigma {summary['downrange_sigma_m']:.3f} m", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"target_m": args.target_m, "profile": "nominal", "throws_per_policy": args.throws,
                                    "policies": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
