"""The sim-to-real gap diagnosis of a machine's logged throws: where, which, how far.

::

    report = diagnose("var/datasets/m1", out_dir="reports/diagnosis/m1")

1. **Where**: every throw replayed in the nominal twin (:mod:`replay`); the residual decomposed
   per channel and phase (:mod:`residuals`); plots of logged against replayed traces.
2. **Which**: every library effect fitted on a training split and scored on the held-out
   throws (:mod:`fit`); ranked; the best is named when it explains most of the gap, else the
   answer is "unexplained".
3. **How far**: held-out residual per channel and impact error before and after adding the
   named (or best) effect, and the twin's predicted accuracy against the observed accuracy per
   target distance (replayed; with ``policy`` also the policy in closed loop in the twin).

Writes ``report.json``, ``profile_fitted.json`` (the nominal profile plus the named effect) and
PNG plots into ``out_dir``.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from sim_twin.diagnosis import dataset as ds
from sim_twin.diagnosis import fit as ft
from sim_twin.diagnosis import replay as rp
from sim_twin.diagnosis import residuals as rs
from sim_twin.effects import EFFECTS, EffectStack
from sim_twin.profile import RealityProfile

log = logging.getLogger(__name__)

REPORT_FORMAT = "slinger-diagnosis/1"


def split(throws: list, test_fraction: float, seed: int) -> tuple[list, list]:
    """Seeded random split into (train, test); at least 2 throws in each.

    Raises:
        ds.DatasetError: fewer than 4 throws.
    """
    n = len(throws)
    if n < 4:
        raise ds.DatasetError(f"need at least 4 landed throws to diagnose (train and held-out), got {n}")
    n_test = min(max(2, round(test_fraction * n)), n - 2)
    order = np.random.default_rng(seed).permutation(n)
    test_idx = set(order[:n_test].tolist())
    return [t for i, t in enumerate(throws) if i not in test_idx], [t for i, t in enumerate(throws) if i in test_idx]


def _accuracy(throws: list, impacts: list[np.ndarray]) -> dict[str, dict]:
    """Per target distance (rounded to 0.5 m): n, mean and sigma of downrange error, mean
    crossrange, mean |error| of the given impacts."""
    from runtime.throw_geometry import impact_errors

    groups: dict[float, list] = {}
    for th, imp in zip(throws, impacts):
        groups.setdefault(round(th.distance_m * 2) / 2, []).append(impact_errors(th.target_m, imp))
    out = {}
    for d in sorted(groups):
        e = np.array(groups[d])
        out[f"{d:.1f}"] = {"n": len(e), "mean_downrange_m": float(e[:, 0].mean()), "sigma_downrange_m": float(e[:, 0].std()),
                           "mean_crossrange_m": float(e[:, 1].mean()), "mean_abs_error_m": float(np.hypot(e[:, 0], e[:, 1]).mean())}
    return out


def _closed_loop(policy: Path, profile: RealityProfile, distances: list[float], throws: int, out_dir: Path, tag: str, workers: int) -> dict:
    """The policy in closed loop in the twin under ``profile`` (sim_twin.evaluate protocol)."""
    from sim_twin.evaluate import evaluate

    path = out_dir / f"profile_{tag}.json"
    path.write_text(json.dumps(profile.to_dict(), indent=1) + "\n")
    rep = evaluate(policy, "2d", distances, throws, path, seed=7, workers=workers)
    return {f"{t['target_m']:.1f}": {k: t[k] for k in ("landed", "bias_m", "sigma_downrange_m", "mean_crossrange_m", "mean_abs_error_m")} for t in rep["targets"]}


def _verdict(ranked: list[ft.CandidateFit]) -> dict:
    best = ranked[0]
    if best.j_test_nominal < ft.MIN_GAP_J:
        return {"answer": "no_gap", "effect": None,
                "text": f"no significant gap: held-out J {best.j_test_nominal:.2f} < {ft.MIN_GAP_J} (residuals within their channel scales)"}
    if best.score >= ft.EXPLAINED_SCORE:
        ps = ", ".join(f"{k} = {v:.4g} ± {best.sigma.get(k, float('nan')):.2g}" for k, v in best.params.items() if k in best.sigma)
        return {"answer": "named", "effect": best.effect,
                "text": f"{best.effect} explains {100 * best.gain:.0f}% of the held-out gap ({ps})"}
    return {"answer": "unexplained", "effect": None,
            "text": f"no candidate explains most of the gap: the best, {best.effect}, explains {100 * max(best.gain, 0):.0f}% "
                    f"(penalised score {best.score:.2f} < {ft.EXPLAINED_SCORE})"}


def diagnose(dataset_dir: str | Path, out_dir: str | Path | None = None, test_fraction: float = 0.3, seed: int = 0,
             workers: int | None = None, candidates: list[str] | None = None, policy: str | Path | None = None,
             accuracy_throws: int = 0, plots: bool = True) -> dict:
    """Run the three questions on a dataset directory (:mod:`dataset` format). Logs progress.

    Returns:
        the report dict (also written to ``out_dir/report.json`` when out_dir is given).

    Raises:
        ds.DatasetError: unusable dataset (message says why).
    """
    t0 = time.time()
    throws, index = ds.load(dataset_dir)
    train, test = split(throws, test_fraction, seed)
    log.info("diagnosis: %d throws (%d train, %d held out)", len(throws), len(train), len(test))
    out = Path(out_dir) if out_dir else None
    if out:
        out.mkdir(parents=True, exist_ok=True)

    # 1. where
    nominal_all = rp.replay(throws, [EffectStack()])[0]
    where = rs.decompose(throws, nominal_all)
    where_pred = rs.decompose(throws, nominal_all, predicted=True)
    where["carriers"] = {
        "channels": [c for c, v in sorted(where["channels"].items(), key=lambda kv: -kv[1].get("share", 0)) if v.get("share", 0) >= 0.1],
        "phases": [p for p, v in sorted(where["phases"].items(), key=lambda kv: -kv[1]) if v >= 0.1],
    }
    log.info("where: J %.3g, carried by %s in %s", where["J"], where["carriers"]["channels"], where["carriers"]["phases"])
    log.info("where: J %.3g; groups %s; phases %s (%.1f s)", where["J"], {k: round(v, 2) for k, v in where["groups"].items()},
             {k: round(v, 2) for k, v in where["phases"].items()}, time.time() - t0)

    # 2. which
    ranked = ft.fit_all(train, test, candidates, workers=workers)
    verdict = _verdict(ranked)
    log.info("which: %s (%.0f s)", verdict["text"], time.time() - t0)

    # 3. how far (named effect, or the best candidate when unexplained)
    best = ranked[0]
    effect = EFFECTS[best.effect](**best.params)
    reps = rp.replay(test, [EffectStack(), EffectStack([effect])])
    before, after = rs.decompose(test, reps[0]), rs.decompose(test, reps[1])
    before_p, after_p = rs.decompose(test, reps[0], predicted=True), rs.decompose(test, reps[1], predicted=True)
    fitted = RealityProfile(name=f"fitted-{best.effect}", effects=[effect])
    how_far = {
        "effect": best.effect,
        "named": verdict["answer"] == "named",
        "J_before": before["J"], "J_after": after["J"],
        "channels": {c: {"rms_before": before["channels"][c]["rms"], "rms_after": after["channels"][c]["rms"], "unit": before["channels"][c]["unit"]}
                     for c in before["channels"]},
        "impact_error_m": {
            "conditioned_before": before["impact"]["rms_m"], "conditioned_after": after["impact"]["rms_m"],
            "predicted_before": before_p["impact"]["rms_m"], "predicted_after": after_p["impact"]["rms_m"],
        },
        "accuracy": {
            "observed": _accuracy(test, [th.impact_m for th in test]),
            "replayed_nominal": _accuracy(test, [r.pred["impact_m"] for r in reps[0]]),
            "replayed_fitted": _accuracy(test, [r.pred["impact_m"] for r in reps[1]]),
        },
    }
    imp = how_far["impact_error_m"]
    how_far["impact_gap_shrink"] = 1 - imp["predicted_after"] / imp["predicted_before"] if imp["predicted_before"] > 0 else None
    if policy is not None and accuracy_throws > 0 and out is not None:
        dists = sorted({round(th.distance_m * 2) / 2 for th in test})
        how_far["accuracy"]["closed_loop_nominal"] = _closed_loop(Path(policy), RealityProfile(), dists, accuracy_throws, out, "nominal", workers or 1)
        how_far["accuracy"]["closed_loop_fitted"] = _closed_loop(Path(policy), fitted, dists, accuracy_throws, out, "fitted", workers or 1)
    log.info("how far: held-out J %.3g -> %.3g; impact error (predicted) %.3f -> %.3f m", before["J"], after["J"],
             imp["predicted_before"], imp["predicted_after"])

    report = {
        "format": REPORT_FORMAT,
        "dataset": str(dataset_dir),
        "machine_id": index.get("machine_id"),
        "throws": len(throws), "train": [t.throw_id for t in train], "test": [t.throw_id for t in test],
        "seed": seed,
        "verdict": verdict,
        "where": {"conditioned": where, "predicted_release": where_pred},
        "which": [r.to_dict() for r in ranked],
        "how_far": how_far,
        "effects_library": {name: cls.describe() for name, cls in EFFECTS.items()},
        "thresholds": {"explained_score": ft.EXPLAINED_SCORE, "min_gap_J": ft.MIN_GAP_J},
        "wall_s": time.time() - t0,
    }
    if out:
        (out / "profile_fitted.json").write_text(json.dumps(fitted.to_dict(), indent=1) + "\n")
        if plots:
            from sim_twin.diagnosis import plots as pl

            report["plots"] = pl.write_all(report, throws, nominal_all, test, reps, out)
        (out / "report.json").write_text(json.dumps(_json_safe(report), indent=1) + "\n")
    log.info("diagnosis done in %.1f s: %s", time.time() - t0, verdict["text"])
    return report


def _json_safe(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v
