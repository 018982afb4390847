"""The fine-tuning path of ``slinger adapt`` on the CPU with a tiny config (the real runs belong on
a GPU): resumes the committed 2D checkpoint for one PPO iteration with 8 environments under a
profile's effects as fixed randomisation, exports, then seals a 1-distance aim correction on top.
Checks that the result loads in the runtime with the profile's values in its fine-tuning config.
Not in the default run (JAX compilation takes a minute or more on 2 cores).

Run: ``nice -n 10 python tests/benchmarks/adapt_finetune_cpu.py [--profile sim_twin/profiles/worn_gripper.json]``
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", type=Path, default=REPO / "sim_twin" / "profiles" / "worn_gripper.json")
    ap.add_argument("--run", type=Path, default=REPO / "policies" / "training" / "throw2d-v2")
    args = ap.parse_args()
    from runtime.policy import PolicyRunner
    from sim_twin.adaptation import adapt as ad
    from sim_twin.twin.profile import RealityProfile

    prof = RealityProfile.load(args.profile)
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        onnx, info = ad.finetune(prof, args.run / "checkpoint.pt", args.run / "config.json", Path(tmp) / "ft.onnx", "ft-tiny",
                                 iterations=1, num_envs=8, max_minutes=None)
        runner = PolicyRunner.load(onnx)
        cfg = json.loads((Path(info["log_dir"]) / "finetune_config.json").read_text())
        table = ad._table([8.0], [0.1], [0.0])
        sealed = ad.seal_version(onnx, Path(tmp) / "ft-aim.onnx", "ft-aim", table, prof.to_dict(), {"finetune": info})
        aimed = PolicyRunner.load(sealed).aim_target([8.0, 0.0, 0.0])
    rand = cfg["env"]["randomization"]
    print(f"fine-tuned on {info['device']} in {time.time() - t0:.0f} s: version {runner.version}, fixed {info['fixed']}, "
          f"not representable in MJX: {info['unsupported']}; release delay in config {rand.get('release_delay_mean_s')}; aim at 8 m -> {aimed[0]:.2f} m")
    ok = runner.version == "ft-tiny" and abs(aimed[0] - 8.1) < 1e-9 and all(
        (rand[k] == [v, v] if isinstance(rand[k], list) else rand[k] == v) for k, v in info["fixed"].items())
    print("OK" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
