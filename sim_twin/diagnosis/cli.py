"""Sim-to-real gap diagnosis: why real throws miss when the twin says they hit.

::

    slinger diagnose DATASET [--out DIR] [--policy P --accuracy-throws N]   diagnose logged throws
    slinger diagnose benchmark [--cases 33] [--outside 8] [--throws 30]    blind check
    slinger diagnose generate --profile PROFILE.json --throws 50 --out DIR  make a dataset with the
                                                                             simulated machine
    slinger diagnose effects                                                 list the effects library

DATASET is a directory in the sim_twin.diagnosis.dataset format (index.json + throws/*.mcap);
the console's diagnosis page exports a machine's stored throws to one.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from runtime.entrypoint import module_main

log = logging.getLogger(__name__)


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("what", help="a dataset directory, or one of: benchmark, generate, effects")
    parser.add_argument("--out", type=Path, default=None, help="output directory (diagnosis: default reports/diagnosis/<dataset name>; "
                        "benchmark: JSON file, default reports/diagnosis_benchmark.json; generate: dataset directory)")
    parser.add_argument("--seed", type=int, default=0, help="split / case / throw seed")
    parser.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    parser.add_argument("--test-fraction", type=float, default=0.3, help="held-out share of the throws (default 0.3)")
    parser.add_argument("--candidates", default=None, help="comma-separated candidate effects (default: the whole library)")
    parser.add_argument("--policy", type=Path, default=Path("policies/throw2d.onnx"), help="2D policy (generate, benchmark, closed-loop accuracy)")
    parser.add_argument("--accuracy-throws", type=int, default=0, help="closed-loop twin throws per target distance for the accuracy comparison (0: off)")
    parser.add_argument("--no-plots", action="store_true")
    parser.add_argument("--cases", type=int, default=33, help="benchmark: library cases (default 33, cycling over every library effect)")
    parser.add_argument("--outside", type=int, default=8, help="benchmark: cases with effects outside the library (default 8)")
    parser.add_argument("--throws", type=int, default=30, help="benchmark: throws per case; generate: throws")
    parser.add_argument("--profile", type=Path, default=None, help="generate: reality profile JSON (default nominal)")
    parser.add_argument("--keep-data", type=Path, default=None, help="benchmark: keep the generated datasets here")


def run(args: argparse.Namespace) -> int:
    from sim_twin.diagnosis.dataset import DatasetError

    try:
        if args.what == "effects":
            from sim_twin.effects import EFFECTS

            print(json.dumps({n: c.describe() for n, c in EFFECTS.items()}, indent=1))
            return 0
        if args.what == "generate":
            return _generate(args)
        if args.what == "benchmark":
            from sim_twin.diagnosis import benchmark

            out = args.out or Path("reports") / "diagnosis_benchmark.json"
            res = benchmark.run(args.cases, args.outside, args.throws, args.seed, args.policy, args.workers or _cores(), out, args.keep_data)
            log.info("benchmark results: %s and %s", out, out.with_suffix(".txt"))
            return 0 if res["cases"] else 1
        return _diagnose(args)
    except (DatasetError, ValueError, OSError) as e:
        print(f"slinger diagnose: {e}", file=sys.stderr)
        return 2


def _cores() -> int:
    import os

    return os.cpu_count() or 1


def _generate(args) -> int:
    from sim_twin.diagnosis import dataset
    from sim_twin.profile import RealityProfile

    if args.out is None:
        raise ValueError("generate needs --out DIR")
    prof = RealityProfile.load(args.profile).to_dict() if args.profile else {"name": "nominal"}
    path = dataset.generate(args.out, prof, args.throws, args.policy, seed=args.seed, workers=args.workers or _cores())
    log.info("dataset written: %s", path)
    return 0


def _diagnose(args) -> int:
    from sim_twin.diagnosis.diagnose import diagnose

    dataset_dir = Path(args.what)
    out = args.out or Path("reports") / "diagnosis" / dataset_dir.resolve().name
    cands = [c.strip() for c in args.candidates.split(",")] if args.candidates else None
    rep = diagnose(dataset_dir, out, args.test_fraction, args.seed, args.workers, cands, args.policy if args.accuracy_throws else None,
                   args.accuracy_throws, plots=not args.no_plots)
    carriers = rep["where"]["conditioned"]["carriers"]
    print(f"Where: the gap is carried by {', '.join(carriers['channels']) or '-'} in the {', '.join(carriers['phases']) or '-'} phase(s)")
    print(f"Verdict: {rep['verdict']['text']}")
    for r in rep["which"]:
        print(f"  {r['effect']:18s} score {r['score']:+.3f}  held-out J {r['j_test_nominal']:.3g} -> {r['j_test']:.3g}  "
              + ", ".join(f"{k}={v:.4g}" for k, v in r["params"].items()))
    print(f"Report: {out / 'report.json'} ({rep['wall_s']:.0f} s)")
    return 0


def main(argv: list[str] | None = None) -> int:
    return module_main('slinger diagnose', __doc__, build_parser, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
