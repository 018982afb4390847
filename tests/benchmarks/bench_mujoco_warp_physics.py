"""Bare MuJoCo Warp physics of the training model, driven from Python without JAX.

Run on a GPU machine with warp-lang (docs/training.md, Throughput, says how to carry it)::

    python tests/benchmarks/bench_mujoco_warp_physics.py OUT.json

For 16384 and 65536 worlds, with and without the MJCF's joint-limit constraints (the training
model has none: ``sim_twin.training.mjx_env.ThrowEnvCore``'s ``joint_limits``), it times
``mjw.step`` (MuJoCo Warp as bundled with MJX) two ways: 8 steps (one control step's physics)
captured in one CUDA graph (``wp.ScopedCapture``) and replayed 25 times, and 200 steps launched
one by one. It prints and writes physics steps per second: the ceiling of an environment that
drives MuJoCo Warp from torch, to set beside MJX's rates in
``bench_training_throughput.py`` (``reports/training_throughput.json``, ``mujoco_warp_bare``).
"""

from __future__ import annotations

import json
import sys
import time

GRAPH_STEPS = 8  # physics steps of one control step (runtime.observation.SUBSTEPS)
GRAPH_REPLAYS = 25
LAUNCHED_STEPS = 200


def rates(n: int, joint_limits: bool) -> dict:
    """Physics steps per second of ``n`` worlds: ``graph`` (replayed CUDA graph) and ``launched``."""
    import mujoco.mjx.third_party.mujoco_warp as mjw
    import warp as wp

    from sim_twin.training.mjx_env import training_model

    m = training_model(joint_limits)
    mw, dw = mjw.put_model(m), mjw.make_data(m, nworld=n)
    dw.ctrl.fill_(0.1)
    mjw.step(mw, dw)
    wp.synchronize()
    with wp.ScopedCapture() as cap:
        for _ in range(GRAPH_STEPS):
            mjw.step(mw, dw)
    wp.capture_launch(cap.graph)
    wp.synchronize()
    t0 = time.perf_counter()
    for _ in range(GRAPH_REPLAYS):
        wp.capture_launch(cap.graph)
    wp.synchronize()
    graph = n * GRAPH_STEPS * GRAPH_REPLAYS / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    for _ in range(LAUNCHED_STEPS):
        mjw.step(mw, dw)
    wp.synchronize()
    launched = n * LAUNCHED_STEPS / (time.perf_counter() - t0)
    return {"graph_physics_steps_per_s": graph, "nograph_physics_steps_per_s": launched}


def main() -> None:
    import warp as wp

    wp.init()
    out = {}
    for limits in (False, True):
        for n in (16384, 65536):
            r = rates(n, limits)
            out[f"n{n}_limits_{'on' if limits else 'off'}"] = r
            print(n, "limits", "on" if limits else "off", {k: f"{v / 1e6:.2f} M/s" for k, v in r.items()}, flush=True)
    with open(sys.argv[1], "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
