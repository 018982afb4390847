"""Continuous parameter fits: the diagnosis' grid and local quadratic against MuJoCo's
system-identification engine (``mujoco.sysid``), on benchmark cases with one library effect.

Run: ``python tests/benchmarks/diagnosis_sysid_compare.py [--seed 1] [--cases 5,10,15,16]
[--throws 30] [--report reports/diagnosis_sysid_compare.json]``. For each case (drawn as the
benchmark draws it, logs like a real machine's) both fit the true effect's parameters on all
throws, from the same replay (our hydraulic replay and noise-scaled scoring):

* grid: ``select.Evaluator.sweep`` and ``forward.evaluate_candidate``, what the diagnosis
  reports (local quadratic fit; 1 sigma the largest of bootstrap, Birge-scaled profile and
  between-throw scatter);
* sysid: ``mujoco.minimize.least_squares`` (the Levenberg-Marquardt solver behind
  ``mujoco.sysid.optimize``, finite-difference Jacobian, box bounds of the prior, started at the
  nominal) on ``Scorer.residuals`` (the noise-scaled residual vector: block residuals of every
  joint and IMU channel, the impact; without the start-state correction), parameters normalised
  to [0, 1]; 1 sigma from ``mujoco.sysid.calculate_intervals`` (s^2 (J'J)^-1 with s^2 the residual
  variance, Student t at 68.27 %).

Prints and reports per case and parameter: truth, both fits, their 1 sigma, |fit - truth| / sigma,
CPU seconds and replays. Needs mujoco's sysid extras (colorama, tabulate, absl-py). No assertions.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def _setup(case: dict, throws_n: int, work: Path):
    from sim_twin.diagnosis import benchmark as bm
    from sim_twin.diagnosis import dataset as ds
    from sim_twin.diagnosis import replay as rp
    from sim_twin.diagnosis import scoring as sc
    from sim_twin.diagnosis import select as sel
    from sim_twin.diagnosis.reallog import RealLogSpec
    from sim_twin.twin.effects import EffectStack

    d = work / f"case{case['case']}"
    ds.generate(d, bm.profile_of(case), throws_n, bm.POLICIES[case["mode"]], seed=case["seed"], mode=case["mode"], real_log=RealLogSpec())
    throws, index = ds.load(d)
    cache = rp.simulate(throws, [EffectStack()], long=True)[0]
    nominal = rp.replay(throws, [EffectStack()], dynamics_cache=cache)[0]
    scorer = sc.Scorer(throws, sc.estimate_noise(throws, nominal, index.get("sensors", {})))
    return throws, cache, scorer, sel.Evaluator(throws, scorer, [], cache)


def grid_fit(ev, scorer, cls, seed: int) -> dict:
    from sim_twin.diagnosis import forward as fw

    N = scorer.D.shape[0]
    c0 = time.process_time()
    sw = ev.sweep(cls, np.ones(N, bool))
    cand, _, _ = fw.evaluate_candidate(ev, sw, scorer.D, np.ones(N, bool), fw.bootstrap_weights(N, seed))
    return {"params": cand.params, "sigma": cand.sigma, "cpu_s": time.process_time() - c0, "replays": int(len(sw.X))}


def sysid_fit(throws, cache, scorer, cls) -> dict:
    from mujoco import minimize
    from mujoco.sysid import calculate_intervals

    from sim_twin.diagnosis import replay as rp
    from sim_twin.twin.effects import EffectStack

    det = [p for p in cls.params if not p.stochastic]
    lo, span = np.array([p.lo for p in det]), np.array([p.hi - p.lo for p in det])
    count = {"replays": 0}

    def residual(x: np.ndarray) -> np.ndarray:  # x (k, points) normalised -> (m, points)
        effects = [cls(**{p.name: float(v) for p, v in zip(det, lo + span * col)}) for col in x.T]
        count["replays"] += len(effects)
        reps = rp.replay(throws, [EffectStack([e]) for e in effects], dynamics_cache=cache)
        return np.stack([scorer.residuals(r) for r in reps], axis=1)

    x0 = np.array([(p.nominal - p.lo) / (p.hi - p.lo) for p in det])
    c0 = time.process_time()
    x, _ = minimize.least_squares(x0, residual, bounds=[np.zeros(len(det)), np.ones(len(det))], eps=1e-6,
                                      verbose=minimize.Verbosity.SILENT, max_iter=50)
    r = residual(x.reshape(-1, 1))
    bounds = [np.zeros((len(det), 1)), np.ones((len(det), 1))]
    J = minimize.jacobian_fd(residual=residual, x=x.reshape(-1, 1), r=r, eps=1e-6, n_res=0, bounds=bounds)[0]  # at the solution
    r = r[:, 0]
    _, half = calculate_intervals([r], np.asarray(J), alpha=1 - 0.6827)
    return {"params": {p.name: float(v) for p, v in zip(det, lo + span * x.ravel())}, "sigma": {p.name: float(h * s) for p, h, s in zip(det, half, span)},
            "cpu_s": time.process_time() - c0, "replays": count["replays"], "chi2": float(r @ r), "residuals": int(r.size)}


def _z_txt(fit: dict) -> str:
    return "unbounded" if fit["abs_z"] is None else f"{fit['abs_z']:.2f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cases", default="5,10,15,16")
    parser.add_argument("--throws", type=int, default=30)
    parser.add_argument("--report", type=Path, default=None)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    from sim_twin.diagnosis import benchmark as bm
    from sim_twin.twin.effects import effect_class

    wanted = {int(c) for c in args.cases.split(",")}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for case in [c for c in bm.draw_cases(bm.MIX, args.seed) if c["case"] in wanted]:
            if len(case["truth"]) != 1 or ":" in case["truth"][0]["effect"]:
                raise ValueError(f"case {case['case']}: one library effect per case, got {case['truth']}")
            t = case["truth"][0]
            cls = effect_class(t["effect"])
            truth = cls(**{t["param"]: t["value"]}).values
            throws, cache, scorer, ev = _setup(case, args.throws, Path(tmp))
            fits = {"grid": grid_fit(ev, scorer, cls, case["seed"]), "sysid": sysid_fit(throws, cache, scorer, cls)}
            for name in fits["grid"]["sigma"]:
                row = {"case": case["case"], "effect": t["effect"], "param": name, "truth": truth[name]}
                for engine, f in fits.items():
                    err = f["params"][name] - truth[name]
                    sig = f["sigma"].get(name)
                    bounded = sig is not None and 0 < sig < np.inf  # an infinite sigma: the data do not bound it
                    row[engine] = {"fit": f["params"][name], "sigma": sig, "abs_z": abs(err) / sig if bounded else None,
                                   "rel_error": abs(err) / abs(truth[name]) if truth[name] else None, "cpu_s": f["cpu_s"], "replays": f["replays"]}
                rows.append(row)
                print(f"case {case['case']:3d} {name:22s} truth {truth[name]:.5g}: " + "; ".join(
                    f"{e} {row[e]['fit']:.5g} ± {row[e]['sigma']:.2g} (|z| {_z_txt(row[e])}, {row[e]['cpu_s']:.1f} CPU s, {row[e]['replays']} replays)"
                    for e in fits), flush=True)
    summary = {e: {"within_1sigma": float(np.mean([r[e]["abs_z"] is not None and r[e]["abs_z"] <= 1 for r in rows])),
                   "unbounded": sum(r[e]["abs_z"] is None for r in rows),
                   "median_abs_z": float(np.median([r[e]["abs_z"] for r in rows if r[e]["abs_z"] is not None])),
                   "median_rel_error": float(np.median([r[e]["rel_error"] for r in rows if r[e]["rel_error"] is not None])),
                   "cpu_s": float(sum({r["case"]: r[e]["cpu_s"] for r in rows}.values()))} for e in ("grid", "sysid")}  # per case once
    print(json.dumps(summary, indent=1))
    if args.report:
        args.report.write_text(json.dumps({"seed": args.seed, "throws": args.throws, "cases": sorted(wanted), "summary": summary, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
