"""Logged throws of the Drake machine as a diagnosis dataset: the gap between the engines, for
``slinger diagnose`` against the MuJoCo twin.

The Drake machine (sim_twin.twin.drake_machine) stands for a machine the twin was not built from, so
its logs are made like a real machine's (sim_twin.diagnosis.reallog.RealLogSpec, the defaults
of the diagnosis benchmark): white noise on every encoder and IMU channel in the loop (the
policy and controller see it), no payload channel, no payload-free flag, the impact measured
with 5 cm noise and ~7 % of impacts missing. The throws are those of the diagnosis datasets
(sim_twin.diagnosis.dataset.generate: targets cycling through DISTANCES_M, seed
``seed * 10007 + i`` for throw i, the runtime's executor and the ONNX policy in the loop), only
the engine differs. Written with the diagnosis' public writers (dataset.write, reallog).

Run: ``python -m sim_twin.diagnosis.drake_dataset --mode 2d --throws 60 --out var/drake_gap_2d``, then
``slinger diagnose var/drake_gap_2d``.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from runtime.entrypoint import module_main
from sim_twin import default_policy

log = logging.getLogger(__name__)


def _throw(args) -> tuple[dict, bytes] | None:
    """One logged Drake throw (a process pool's job): (index row, MCAP bytes), or None if refused."""
    policy_path, profile_dict, seed, distance_m, mode, spec = args
    from runtime.executor import ThrowExecutor
    from runtime.policy import PolicyRunner
    from runtime.protocol.messages import ThrowRequest
    from sim_twin.diagnosis import reallog
    from sim_twin.evaluation.evaluate import target_on_axis
    from sim_twin.twin.engines import make_machine
    from sim_twin.twin.profile import RealityProfile
    from sim_twin.twin.twin_machine import TwinMachine, run_throw

    policy = PolicyRunner.load(policy_path)
    sim = make_machine("drake", RealityProfile.from_dict(profile_dict), seed=seed)
    sim.reset(cabin_turn=0.0 if mode == "2d" else None)
    twin = TwinMachine(sim, "drake")
    req = ThrowRequest(throw_id=f"t{seed:06d}", machine_id="drake", mode=mode, target_m=target_on_axis(mode, distance_m))
    outcome, _ = run_throw(twin, ThrowExecutor({mode: policy}), req)
    if outcome is None:
        return None
    row = {"throw_id": req.throw_id, "mode": mode, "target_m": list(req.target_m), "status": outcome.status,
           "policy_version": outcome.policy_version, "seed": seed, "engine": "drake",
           "impact_m": None if outcome.impact_m is None else outcome.impact_m.tolist(),
           "impact_stamp_s": None if outcome.impact is None else outcome.impact.impact_stamp_s,
           "release_stamp_s": outcome.release_stamp_s}
    meta = {"throw_id": req.throw_id, "mode": mode, "status": outcome.status, "policy_version": outcome.policy_version,
            "target_m": json.dumps(list(req.target_m)), "engine": "drake"}
    row = reallog.degrade_row(row, spec, np.random.default_rng([seed, 7]))
    return row, reallog.write_log(outcome.telemetry.rows, outcome.telemetry.events, spec, meta)


def generate(directory: Path, throws: int, policy_path: Path, mode: str = "2d", seed: int = 0, workers: int = 1) -> Path:
    """Throw ``throws`` times with the nominal Drake machine and write a real-log-like dataset.

    Returns:
        the index path (sim_twin.diagnosis.dataset format).

    Raises:
        ValueError: unknown mode.
    """
    from sim_twin.diagnosis import dataset
    from sim_twin.diagnosis.reallog import RealLogSpec

    if mode not in dataset.DISTANCES_M:
        raise ValueError(f"mode must be one of {sorted(dataset.DISTANCES_M)}, got {mode!r}")
    spec = RealLogSpec()
    profile = {"name": "nominal", "effects": [spec.noise_effect()]}
    distances = dataset.DISTANCES_M[mode]
    jobs = [(str(policy_path), profile, seed * 10007 + i, float(distances[i % len(distances)]), mode, spec) for i in range(throws)]
    if workers > 1:
        from sim_twin.twin.pools import process_pool

        with process_pool(workers) as pool:
            results = list(pool.map(_throw, jobs, chunksize=max(1, throws // (4 * workers))))
    else:
        results = [_throw(j) for j in jobs]
    rows = [r for r in results if r is not None]
    log.info("generated %d Drake throws (%d landed)", len(rows), sum(r[0]["status"] == "landed" for r in rows))
    return dataset.write(directory, rows, machine_id="drake", sensors=spec.sensors(),
                         source={"generator": "sim_twin.diagnosis.drake_dataset.generate", "engine": "drake", "seed": seed, "policy": str(policy_path),
                                 "mode": mode, "real_log": {k: getattr(spec, k) for k in spec.__dataclass_fields__}})


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mode", choices=("2d", "3d"), default="2d")
    parser.add_argument("--policy", type=Path, default=None, help="ONNX policy (default the deployed policies/throw<mode>.onnx)")
    parser.add_argument("--throws", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--out", type=Path, required=True, help="dataset directory")


def run(args: argparse.Namespace) -> int:
    path = generate(args.out, args.throws, args.policy or default_policy(args.mode), args.mode, args.seed, args.workers)
    log.info("dataset written: %s", path)
    return 0


def main(argv: list[str] | None = None) -> int:
    return module_main("python -m sim_twin.diagnosis.drake_dataset", __doc__, build_parser, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
