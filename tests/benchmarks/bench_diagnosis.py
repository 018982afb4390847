"""Wall time of a 50-throw sim-to-real diagnosis on this machine (bar: under 10 minutes on 2 cores).

Run: ``python tests/benchmarks/bench_diagnosis.py [--throws 50] [--profile sim_twin/profiles/slow_hydraulics.json]
[--out reports/diagnosis_50]``. Generates the logged throws with the simulated machine under the
profile (the 2D policy in the loop), then times ``slinger diagnose`` on them (all cores) and prints
the phases' times, the verdict and the bar. The report and plots go to ``--out``. No assertions.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--throws", type=int, default=50)
    parser.add_argument("--profile", type=Path, default=None, help="hidden reality profile (default: passive viscous friction 0.6 1/s, under which every throw lands)")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    from sim_twin.diagnosis import dataset
    from sim_twin.diagnosis.diagnose import diagnose
    from sim_twin.profile import RealityProfile

    prof = RealityProfile.load(args.profile).to_dict() if args.profile else {"name": "worn_bearings", "effects": [{"effect": "passive_friction", "params": {"viscous_per_s": 0.6}}]}
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "throws"
        t0 = time.time()
        dataset.generate(data, prof, args.throws, REPO / "policies" / "throw2d.onnx", seed=args.seed, workers=os.cpu_count() or 1)
        t_gen = time.time() - t0
        out = args.out or Path(tmp) / "report"
        t0 = time.time()
        rep = diagnose(data, out, seed=args.seed)
        t_diag = time.time() - t0
    print(f"cores: {os.cpu_count()}; throws: {rep['throws']} ({len(rep['train'])} train, {len(rep['test'])} held out)")
    print(f"generate (policy in the loop): {t_gen:.1f} s")
    print(f"diagnose (where + which + how far + plots): {t_diag:.1f} s  -> bar 600 s: {'met' if t_diag < 600 else 'MISSED'}")
    print(f"verdict: {rep['verdict']['text']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
