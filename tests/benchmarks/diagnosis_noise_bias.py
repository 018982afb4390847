"""The where stage on noise-only logs: how often it finds a gap, and the replay's systematic error.

Run: ``python tests/benchmarks/diagnosis_noise_bias.py [--throws 30] [--data DIR]
[--report reports/diagnosis_noise_bias.json]``. Generates noise-only datasets (the nominal
simulated machine, logs like a real machine's: ``RealLogSpec()``, the benchmark's ``noise``
cases of seed 0 (seeds 68-77, two of them 3D) and ten more 2D seeds 101-110), replays each in
the nominal twin and runs only the where stage (no candidate fits). It reports, per dataset,
whether the where stage finds a gap with the bias tests' margin (``noise.BIAS_MARGIN``) and with
none (the plain t-test), and, pooled over all throws, each trajectory channel's per-sample mean
residual in units of its noise sigma (the replay's systematic error the margin must cover) with
its standard error. ``--data`` keeps the datasets (a second run reuses them). The report (JSON +
.txt) is stamped afterwards with ``slinger results --stamp``. No assertions.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

SEEDS = [(s, "3d" if s in (72, 77) else "2d") for s in range(68, 78)] + [(s, "2d") for s in range(101, 111)]
"""(seed, mode): the benchmark's noise cases of seed 0 (sim_twin.diagnosis.benchmark.draw_cases)
and ten more 2D datasets."""


def where_of(directory: Path) -> dict:
    """Nominal replay and where stage of one dataset: {"with_margin", "plain"} where dicts
    (diagnose._where), M (N, C), rows (N,) scored rows."""
    from sim_twin.diagnosis import dataset as ds
    from sim_twin.diagnosis import replay as rp
    from sim_twin.diagnosis import scoring as sc
    from sim_twin.diagnosis.diagnose import _where
    from sim_twin.twin.effects import EffectStack

    throws, index = ds.load(directory)
    cache = rp.simulate(throws, [EffectStack()], long=True)[0]
    nominal = rp.replay(throws, [EffectStack()], dynamics_cache=cache)[0]
    noise = sc.estimate_noise(throws, nominal, index.get("sensors", {}))
    scorer = sc.Scorer(throws, noise)
    S, M = scorer.score(nominal), scorer.signed(nominal)
    return {"with_margin": _where(throws, S, scorer.D, noise, nominal, M, scorer.bias_margin),
            "plain": _where(throws, S, scorer.D, noise, nominal, M, None),
            "M": M, "rows": np.array([rp.score_rows(th) for th in throws], dtype=float)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--throws", type=int, default=30)
    parser.add_argument("--data", type=Path, default=None, help="keep (and reuse) the datasets here")
    parser.add_argument("--report", type=Path, default=None)
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    import tempfile

    from sim_twin.diagnosis import dataset as ds
    from sim_twin.diagnosis import noise as nz
    from sim_twin.diagnosis.benchmark import POLICIES
    from sim_twin.diagnosis.reallog import RealLogSpec

    t0 = time.time()
    with tempfile.TemporaryDirectory(prefix="slinger-noise-bias-") as tmp:
        root = args.data or Path(tmp)
        rows, Ms, Ls = [], [], []
        for seed, mode in SEEDS:
            d = root / f"{mode}_{seed}"
            if not (d / "index.json").exists():
                ds.generate(d, {"name": "nominal"}, args.throws, POLICIES[mode], seed=seed, mode=mode, real_log=RealLogSpec())
            w = where_of(d)
            Ms.append(w["M"])
            Ls.append(w["rows"])

            def smallest(where):
                tested = {n: c["bias"] for n, c in where["channels"].items() if c.get("bias")}
                n = min(tested, key=lambda k: tested[k]["p_holm"])
                return {"channel": n, "p_holm": tested[n]["p_holm"], "t": tested[n]["t"], "t_material": tested[n]["t_material"]}

            row = {"seed": seed, "mode": mode, "throws": len(w["M"]),
                   "gap_with_margin": w["with_margin"]["gap"], "carriers_with_margin": w["with_margin"]["carriers"],
                   "gap_plain": w["plain"]["gap"], "carriers_plain": w["plain"]["carriers"],
                   "smallest_holm_p_with_margin": smallest(w["with_margin"]), "smallest_holm_p_plain": smallest(w["plain"])}
            rows.append(row)
            print(f"{mode} seed {seed}: gap with margin {row['carriers_with_margin'] or 'none'}, plain {row['carriers_plain'] or 'none'}", flush=True)
    M, L = np.concatenate(Ms), np.concatenate(Ls)
    pooled = {}
    for c, (name, kind, _j) in enumerate(nz.TRAJ):
        x = M[:, c] / np.sqrt(L)  # per-sample mean residual, units of sigma
        pooled[name] = {"kind": kind, "mean_per_sample": float(x.mean()), "se": float(x.std(ddof=1) / np.sqrt(len(x))),
                        "sd_per_throw": float(x.std(ddof=1)), "margin": nz.BIAS_MARGIN[kind]}
    report = {"throws_per_dataset": args.throws, "datasets": len(rows), "throws": int(len(M)), "bias_margin": nz.BIAS_MARGIN,
              "alpha": nz.BIAS_ALPHA, "no_gap_with_margin": sum(not r["gap_with_margin"] for r in rows),
              "no_gap_plain": sum(not r["gap_plain"] for r in rows), "pooled_trajectory": pooled, "cases": rows, "wall_s": time.time() - t0}
    text = format_report(report)
    print(text)
    if args.report:
        args.report.parent.mkdir(parents=True, exist_ok=True)
        args.report.write_text(json.dumps(report, indent=1) + "\n")
        args.report.with_suffix(".txt").write_text(text + "\n")
    return 0


def format_report(r: dict) -> str:
    """The .txt summary of a report dict (:func:`main`)."""
    n = r["datasets"]
    lines = [f"Where stage on noise-only logs (nominal simulated machine, real-log noise): {n} datasets, {r['throws']} throws",
             f"  'no gap' with the bias margin {r['bias_margin']} (sigma per sample): {r['no_gap_with_margin']} of {n}"
             f"; with the plain t-test (no margin): {r['no_gap_plain']} of {n}  (bias tests family-wise {100 * r['alpha']:g}%)",
             "  pooled per-sample mean residual of the nominal replay (units of the channel's noise sigma; the replay's systematic error):"]
    for name, p in r["pooled_trajectory"].items():
        lines.append(f"    {name:18s} {p['mean_per_sample']:+.4f} +- {p['se']:.4f}   (margin {p['margin']:g})")
    lines.append("  datasets: seed mode -> gap with margin | plain t-test; smallest Holm p with margin; smallest Holm p plain")
    for c in r["cases"]:
        s, m = c["smallest_holm_p_plain"], c["smallest_holm_p_with_margin"]
        lines.append(f"    {c['seed']:4d} {c['mode']} -> {', '.join(c['carriers_with_margin']) or 'no gap'} | {', '.join(c['carriers_plain']) or 'no gap'};"
                     f" {m['channel']} p_holm {m['p_holm']:.3g} (t_material {m['t_material']:+.2f}); {s['channel']} p_holm {s['p_holm']:.3g} (t {s['t']:+.2f})")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
