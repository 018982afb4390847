"""Sim-to-real gap diagnosis: why real throws miss when the twin says they hit.

::

    slinger diagnose DATASET [--out DIR] [--candidates a,b,pkg.mod:Class]   diagnose logged throws
    slinger diagnose benchmark [--small] [--throws 30] [--workers 2] [--cases 0,5] [--resume]
                               [--shard I/N] [--deadline-s S]                blind benchmark (or shard I of N)
    slinger diagnose merge --out reports/diagnosis_benchmark.json SHARD.json...
                                                                             one report from the shards' reports
    slinger diagnose generate --mode 2d|3d --throws 50 --out DIR [--profile P.json] [--real-log]
                                                                             make a dataset with the
                                                                             simulated machine
    slinger diagnose convert --mapping M.json --impacts I.csv --out DIR LOG...
                                                                             another machine's CSV/MCAP
    slinger diagnose convert --mapping bridge.toml --impacts I.csv --out DIR BAG...
                                                                             a ROS 2 machine's rosbag2
                                                                             bags (sim_twin.diagnosis.rosbag)
    slinger diagnose effects                                                 list the effects library

DATASET is a directory in the sim_twin.diagnosis.dataset format (index.json + throws/*.mcap,
optional impacts.csv; logformat documents the topics); the console's diagnosis page exports a
machine's stored throws to one.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from runtime.entrypoint import module_main
from sim_twin import default_policy

log = logging.getLogger(__name__)


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("what", help="a dataset directory, or one of: benchmark, merge, generate, convert, effects")
    parser.add_argument("inputs", nargs="*", type=Path, help="convert: the throw logs (CSV or MCAP, or rosbag2 bags: one per throw); "
                        "merge: the benchmark reports of the shards")
    parser.add_argument("--out", type=Path, default=None, help="output directory (diagnosis: default reports/diagnosis/<dataset name>; "
                        "benchmark: JSON file, default reports/diagnosis_benchmark.json; generate/convert: dataset directory)")
    parser.add_argument("--seed", type=int, default=0, help="split / case / throw seed")
    parser.add_argument("--workers", type=int, default=None, help="processes (diagnosis sweeps, generate, benchmark; default: all cores)")
    parser.add_argument("--test-fraction", type=float, default=0.3, help="held-out share of the throws (default 0.3)")
    parser.add_argument("--candidates", default=None, help="comma-separated candidates: library names or package.module:Class (default: the library)")
    parser.add_argument("--mode", choices=("2d", "3d"), default="2d", help="generate: throw mode")
    parser.add_argument("--policy", type=Path, default=None, help="generate: ONNX policy (default policies/throw<mode>.onnx)")
    parser.add_argument("--no-plots", action="store_true")
    parser.add_argument("--small", action="store_true", help="benchmark: the small CI version (one case of every kind but held-out, two singles; 16 throws)")
    parser.add_argument("--cases", default=None, help="benchmark: only these case numbers (comma-separated)")
    parser.add_argument("--shard", default=None, metavar="I/N", help="benchmark: only shard I of N (the cases dealt round-robin by kind); "
                        "`merge` combines the N reports")
    parser.add_argument("--deadline-s", type=float, default=None, help="benchmark: start no case after this many wall seconds and stop "
                        "the cases still running then; the report keeps the finished ones (--resume runs the rest)")
    parser.add_argument("--resume", action="store_true", help="benchmark: keep the finished cases already in --out (same seed/throws) and run the rest")
    parser.add_argument("--throws", type=int, default=30, help="benchmark: throws per case; generate: throws")
    parser.add_argument("--profile", type=Path, default=None, help="generate: reality profile JSON (default nominal)")
    parser.add_argument("--real-log", action="store_true", help="generate: logs like a real machine's (noise, no payload channel, no open flag, missing impacts)")
    parser.add_argument("--keep-data", type=Path, default=None, help="benchmark: keep the generated datasets here")
    parser.add_argument("--mapping", type=Path, default=None, help="convert: column mapping JSON (sim_twin.diagnosis.convert), or for rosbag2 "
                             "the ROS 2 bridge mapping (sim_twin.diagnosis.rosbag)")
    parser.add_argument("--impacts", type=Path, default=None, help="convert: CSV with throw_id, target_x_m, target_y_m, impact_x_m, impact_y_m")


def run(args: argparse.Namespace) -> int:
    from sim_twin.diagnosis.convert import ConvertError
    from sim_twin.diagnosis.dataset import DatasetError

    try:
        if args.what == "effects":
            from sim_twin.twin.effects import EFFECTS

            print(json.dumps({n: c.describe() for n, c in EFFECTS.items()}, indent=1))
            return 0
        if args.what == "generate":
            return _generate(args)
        if args.what == "convert":
            from sim_twin.diagnosis import rosbag
            from sim_twin.diagnosis.convert import convert

            if not (args.mapping and args.impacts and args.out and args.inputs):
                raise ValueError("convert needs --mapping, --impacts, --out and the throw logs")
            bags = [rosbag.is_rosbag(p) for p in args.inputs]
            if any(bags) and not all(bags):
                raise ValueError("convert takes either rosbag2 bags or CSV/MCAP logs, not both")
            index = (rosbag.convert if all(bags) else convert)(args.inputs, args.mapping, args.impacts, args.out)
            log.info("dataset written: %s", index)
            return 0
        if args.what == "benchmark":
            from sim_twin.diagnosis import benchmark

            out = args.out or Path("reports") / "diagnosis_benchmark.json"
            mix = benchmark.SMALL_MIX if args.small else benchmark.MIX
            throws = benchmark.SMALL_THROWS if args.small else args.throws
            only = [int(c) for c in args.cases.split(",")] if args.cases else None
            shard = benchmark.parse_shard(args.shard) if args.shard else None
            res = benchmark.run(mix, throws, args.seed, args.workers or _cores(), out, args.keep_data, only=only, resume=args.resume,
                                shard=shard, deadline_s=args.deadline_s, plots=False)
            return _benchmark_done(res, out, not args.no_plots)
        if args.what == "merge":
            from sim_twin.diagnosis import benchmark

            if args.out is None or not args.inputs:
                raise ValueError("merge needs --out and the shards' benchmark reports")
            return _benchmark_done(benchmark.merge(args.inputs, args.out, plots=False), args.out, not args.no_plots)
        return _diagnose(args)
    except (DatasetError, ConvertError, ValueError, OSError) as e:
        print(f"slinger diagnose: {e}", file=sys.stderr)
        return 2


def _benchmark_done(res: dict, out: Path, plots: bool) -> int:
    """Print the summary of a benchmark result and write its figure; 0 when it holds cases."""
    from sim_twin.diagnosis import benchmark

    print(benchmark.format_summary(res))
    if res["cases"] and plots:
        from sim_twin.diagnosis import plots as figures

        print(f"figure: {figures.benchmark(res, out.with_suffix('.png'))}")
    return 0 if res["cases"] else 1


def _cores() -> int:
    import os

    return os.cpu_count() or 1


def _generate(args) -> int:
    from sim_twin.diagnosis import dataset
    from sim_twin.diagnosis.reallog import RealLogSpec
    from sim_twin.twin.profile import RealityProfile

    if args.out is None:
        raise ValueError("generate needs --out DIR")
    prof = RealityProfile.load(args.profile).to_dict() if args.profile else {"name": "nominal"}
    policy = args.policy or default_policy(args.mode)
    path = dataset.generate(args.out, prof, args.throws, policy, seed=args.seed, mode=args.mode, workers=args.workers or _cores(),
                            real_log=RealLogSpec() if args.real_log else None)
    log.info("dataset written: %s", path)
    return 0


def _diagnose(args) -> int:
    from sim_twin.diagnosis.diagnose import diagnose

    dataset_dir = Path(args.what)
    out = args.out or Path("reports") / "diagnosis" / dataset_dir.resolve().name
    cands = [c.strip() for c in args.candidates.split(",")] if args.candidates else None
    rep = diagnose(dataset_dir, out, args.test_fraction, args.seed, workers=args.workers, candidates=cands, plots=not args.no_plots)
    w = rep["where"]
    print(f"Where: {', '.join(w['carriers']) or 'no channel beyond its noise'}"
          + (f" (phases: {', '.join(f'{p} {100 * s:.0f}%' for p, s in w['phases'].items())})" if w["phases"] else ""))
    print(f"Verdict: {rep['verdict']['text']}")
    for r in rep["rounds"]:
        for c in r["candidates"]:
            print(f"  round {rep['rounds'].index(r) + 1}: {c['effect']:22s} wins {100 * c['wins']:3.0f}%  chi2 {c['chi2_before']:.0f} -> {c['chi2_after']:.0f}"
                  f"  {'admissible' if c['admissible'] else c['reason']}")
    hf = rep.get("how_far")
    if hf:
        print(f"Held out ({len(hf['test_throws'])} throws the fit never saw): gap shrink {hf['gap_shrink']:.0%}, impact RMS "
              f"{hf['impact_rms_m']['before']:.3f} -> {hf['impact_rms_m']['after']:.3f} m; shares {hf['share_of_shrink']}")
    if rep["skipped"]:
        print(f"Skipped throws: {rep['skipped']}")
    print(f"Report: {out / 'report.json'} ({rep['wall_s']:.0f} s)")
    return 0


def main(argv: list[str] | None = None) -> int:
    return module_main('slinger diagnose', __doc__, build_parser, run, argv, intermixed=True)


if __name__ == "__main__":
    raise SystemExit(main())
