"""The sim-to-real gap diagnosis of a machine's logged throws: where, which, how far.

::

    report = diagnose("var/datasets/m1", out_dir="reports/diagnosis/m1")

1. **Where**: every throw replayed in the nominal twin (:mod:`replay`); residuals in units of
   the log's measured noise (or the declared sensor spec) per channel and phase (:mod:`noise`,
   :mod:`scoring`); channels whose chi-square exceeds their noise carry the gap. None: "no gap".
2. **Which**: forward selection over the candidates that act where the gap is (:mod:`select`,
   :mod:`forward`): grid fits, bootstrap win frequencies over throws, admissibility (no channel
   worse beyond noise, no parameter at a prior bound). Verdict: "named" (the named effects
   explain every channel to within noise), "ambiguous" (between A and B, with the measurement
   that would separate them), "unexplained" (with the where and any partial names), "no_gap".
3. **How far**: held-out throws (never used by the fit) replayed with the named effects
   fitted on the training throws: chi-square excess, impact error and accuracy per target
   distance before and after, and each named effect's share of the shrink.

Writes ``report.json`` (``which``: the named effects with parameters and 1 sigma, what
``slinger adapt`` reads), ``profile_fitted.json`` (a reality profile: the nominal one plus the
named effects, their 1 sigma in its ``uncertainty`` block, :func:`sim_twin.twin.uncertainty.with_fitted_sigma`)
and PNG plots.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from sim_twin.diagnosis import dataset as ds
from sim_twin.diagnosis import forward as fw
from sim_twin.diagnosis import noise as nz
from sim_twin.diagnosis import replay as rp
from sim_twin.diagnosis import scoring as sc
from sim_twin.diagnosis import select as sel
from sim_twin.diagnosis import stationarity as st
from sim_twin.diagnosis.verdict import drift_of, verdict_of
from sim_twin.twin.effects import EFFECTS, Effect, EffectStack, effect_class
from sim_twin.twin.profile import RealityProfile

log = logging.getLogger(__name__)

REPORT_FORMAT = "slinger-diagnosis/2"


def split(throws: list, test_fraction: float, seed: int) -> tuple[list, list]:
    """Seeded random split into (train, test); at least 2 throws in each.

    Raises:
        ds.DatasetError: fewer than 4 throws.
    """
    mask = split_mask(len(throws), test_fraction, seed)
    return [t for t, m in zip(throws, mask) if m], [t for t, m in zip(throws, mask) if not m]


def split_mask(n: int, test_fraction: float, seed: int) -> np.ndarray:
    """(n,) bool, True = training throw (see :func:`split`)."""
    if n < 4:
        raise ds.DatasetError(f"need at least 4 landed throws to diagnose (train and held-out), got {n}")
    n_test = min(max(2, round(test_fraction * n)), n - 2)
    mask = np.ones(n, bool)
    mask[np.random.default_rng(seed).permutation(n)[:n_test]] = False
    return mask


def resolve_candidates(candidates: list[str] | None) -> list[type[Effect]]:
    """Library names and ``package.module:Class`` user effects, checked before any work.

    Raises:
        ValueError: unknown name, unimportable class, not an Effect, or an effect without a
            fittable (non-stochastic) parameter.
    """
    out = []
    for spec in candidates or list(EFFECTS):
        cls = effect_class(spec)
        det = [p for p in cls.params if not p.stochastic]
        if not det:
            raise ValueError(f"candidate {spec!r}: no deterministic parameter to fit")
        if len(det) > 2 and not getattr(cls, "joint_base", ""):
            raise ValueError(f"candidate {spec!r}: {len(det)} parameters; the diagnosis fits at most 2 per effect (or per joint)")
        out.append(cls)
    return out


def _where(throws, S: np.ndarray, D: np.ndarray, noise: nz.NoiseModel, nominal, M: np.ndarray, margin: np.ndarray | None = None) -> dict:
    """The where stage (docs/diagnosis.md): per channel the chi-square excess and the bias test
    of the nominal replay's residuals; ``margin`` (N, C): :attr:`scoring.Scorer.bias_margin`."""
    gaps = fw.channel_gaps(S, D, None, M, margin)
    bias = nz.bias_tests(M, D, margin=margin)
    Sc, Dc = S.sum(axis=0), D.sum(axis=0)
    chans: dict[str, dict[str, Any]] = {}  # channel name -> its statistics (mixed value types)
    for c, name in enumerate(nz.CHANNELS):
        if Dc[c].sum() == 0:
            continue
        chans[name] = {"chi2": float(Sc[c].sum()), "dof": float(Dc[c].sum()), "excess_z": nz.gap_test(Sc[c].sum(), Dc[c].sum())[1],
                       "gap": name in gaps, "group": nz.group_of(name), "kind": gaps.get(name, {}).get("kind"), "bias": bias.get(name),
                       "by_phase": {nz.PHASES[p]: {"chi2": float(Sc[c, p]), "dof": float(Dc[c, p])} for p in range(len(nz.PHASES)) if Dc[c, p] > 0}}
    excess = {n: max(v["chi2"] - v["dof"], 0.0) for n, v in chans.items() if v["gap"] and v["kind"] != "bias"}
    tot = sum(excess.values())
    phase_ex = {p: sum(max(v["by_phase"].get(p, {}).get("chi2", 0) - v["by_phase"].get(p, {}).get("dof", 0), 0) for n, v in chans.items() if v["gap"])
                for p in nz.PHASES}
    ptot = sum(phase_ex.values())
    r, _ = sc.impact_residuals(throws, nominal)
    bias_only = sorted((n for n in gaps if n not in excess), key=lambda n: bias[n]["p"])
    return {
        "gap": bool(gaps), "channels": chans,
        "carriers": sorted(excess, key=lambda n: -excess[n]) + bias_only, "bias_only": bias_only,
        "share": {n: e / tot for n, e in excess.items()} if tot > 0 else {},
        "phases": {p: e / ptot for p, e in phase_ex.items()} if ptot > 0 else {},
        "groups": sorted({nz.group_of(n) for n in gaps}),
        "impact": {"mean_downrange_m": float(r[:, 0].mean()), "mean_crossrange_m": float(r[:, 1].mean()),
                   "rms_m": float(np.sqrt(np.mean(np.sum(r * r, axis=1))))},
        "noise": noise.to_dict(),
    }


def stationarity(throws, M: np.ndarray, D: np.ndarray, seed: int = 0) -> dict[str, dict]:
    """Change test of every channel's per-throw mean residual in throw order (:mod:`stationarity`):
    channels with data in every throw, the target distance regressed out, Holm over the channels,
    and their combined test (the row :data:`stationarity.COMBINED`: what decides, Holm over the
    nominal and the after-fit one together in :func:`verdict.drift_of`).

    Args:
        throws: the N logged throws in log order; M: (N, C) standardised mean residuals
            (:meth:`scoring.Scorer.signed`); D: (N, C, P) degrees of freedom.

    Returns:
        channel -> :func:`stationarity.test_series` row (units: noise sigma of the per-throw mean).
    """
    has = D.sum(axis=2) > 0
    series = {name: M[:, c] for c, name in enumerate(nz.CHANNELS) if has[:, c].all() and len(throws) >= st.MIN_THROWS}
    if not series:
        return {}
    return st.test_series(series, covariates=np.array([t.distance_m for t in throws]), seed=seed)


def _accuracy(throws: list, impacts: list[np.ndarray]) -> dict[str, dict]:
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


def _how_far(throws, train: np.ndarray, scorer: sc.Scorer, rounds: list[fw.Round], named: list[Effect], nominal: list,
             carriers: tuple[str, ...] | list[str] = ()) -> dict:
    """Held-out throws, named effects fitted on the training throws only. ``gap_shrink`` is the
    smallest shrink over the gap channels (``carriers``, each on its own) and the impact RMS, with
    the channel it comes from (``gap_shrink_channel``); ``shrink_by_channel`` lists each."""
    test = [t for t, m in zip(throws, train) if not m]
    test_scorer = sc.Scorer(test, scorer.noise)
    fits = {r.named: next(c for c in r.candidates if c.effect == r.named) for r in rounds if r.decision == "named"}
    train_effects = [type(e)(**fits[e.spec()].params_train) for e in named]
    stacks = [EffectStack()] + [EffectStack(train_effects[: i + 1]) for i in range(len(train_effects))]
    reps = rp.replay(test, stacks)
    S = [test_scorer.score(r) for r in reps]
    D = test_scorer.D
    ex = [float(s.sum() - D.sum()) for s in S]
    imp = [sc.impact_residuals(test, r)[0] for r in reps]
    rms = [float(np.sqrt(np.mean(np.sum(i * i, axis=1)))) for i in imp]
    shares = {}
    total = ex[0] - ex[-1]
    for i, e in enumerate(named):
        shares[e.spec()] = (ex[i] - ex[i + 1]) / total if total > 0 else None
    const = _constant_shift(throws, train, test_scorer, reps[0], ex[0], rms[0], nominal)
    # per channel, never pooled: a channel whose noise was over-estimated sits far below its
    # degrees of freedom and would hide another's misfit in a pooled excess
    by_channel = {}
    for ch in carriers:
        c = nz.CH_INDEX[ch]
        dof = float(D[:, c].sum())
        if dof <= 0:
            continue
        before, after = float(S[0][:, c].sum() - dof), float(S[-1][:, c].sum() - dof)
        by_channel[ch] = {"excess_before": before, "excess_after": after,
                          "shrink": (1 - max(after, 0.0) / before) if before > 0 else None}
    shrinks = [(ch, v["shrink"]) for ch, v in by_channel.items() if v["shrink"] is not None]
    if rms[0] > 0:
        shrinks.append(("impact (RMS)", 1 - rms[-1] / rms[0]))
    worst = min(shrinks, key=lambda cs: cs[1]) if shrinks and named else None
    return {
        "constant_shift": const,
        "test_throws": [t.throw_id for t in test],
        "named_fitted_on_train": [e.to_dict() for e in train_effects],
        "chi2_excess_before": ex[0], "chi2_excess_after": ex[-1], "dof": float(D.sum()),
        "gap_shrink": worst[1] if worst else None, "gap_shrink_channel": worst[0] if worst else None,
        "shrink_by_channel": by_channel,
        "impact_rms_m": {"before": rms[0], "after": rms[-1], "steps": rms},
        "impact_gap_shrink": (1 - rms[-1] / rms[0]) if rms[0] > 0 and named else None,
        "share_of_shrink": shares,
        "channels": {nz.CHANNELS[c]: {"chi2_before": float(S[0][:, c].sum()), "chi2_after": float(S[-1][:, c].sum()), "dof": float(D[:, c].sum())}
                     for c in range(len(nz.CHANNELS)) if D[:, c].sum() > 0},
        "accuracy": {
            "observed": _accuracy(test, [t.impact_m for t in test]),
            "replayed_nominal": _accuracy(test, [r.pred["impact_m"] for r in reps[0]]),
            "replayed_fitted": _accuracy(test, [r.pred["impact_m"] for r in reps[-1]]),
        },
    }


def _constant_shift(throws, train: np.ndarray, test_scorer: sc.Scorer, nominal_test, ex_before: float, rms_before: float, nominal: list) -> dict:
    """The held-out shrink a constant shift of the impact would give (no physics): the mean
    impact residual (downrange, crossrange) of the TRAINING throws against the nominal replay,
    subtracted from the held-out throws' residuals. A named effect whose held-out shrink is no
    better than this adds nothing the impacts alone could show."""
    train_th = [t for t, m in zip(throws, train) if m]
    nominal_train = [r for r, m in zip(nominal, train) if m]
    shift = sc.impact_residuals(train_th, nominal_train)[0].mean(axis=0) if train_th else np.zeros(2)
    r, v = sc.impact_residuals(test_scorer.throws, nominal_test)
    S = test_scorer.score(nominal_test)
    var = test_scorer.noise.impact_sigma_m**2 + v
    S[:, sc.IMPACT, 2] = (r - shift) ** 2 / var
    ex = float(S.sum() - test_scorer.D.sum())
    rms = float(np.sqrt(np.mean(np.sum((r - shift) ** 2, axis=1))))
    return {"shift_downrange_m": float(shift[0]), "shift_crossrange_m": float(shift[1]), "chi2_excess_after": ex,
            "gap_shrink": (1 - max(ex, 0.0) / ex_before) if ex_before > 0 else None,
            "impact_rms_after_m": rms, "impact_gap_shrink": (1 - rms / rms_before) if rms_before > 0 else None}


def diagnose(dataset_dir: str | Path, out_dir: str | Path | None = None, test_fraction: float = 0.3, seed: int = 0,
             workers: int | None = None, candidates: list[str] | None = None, policy: str | Path | None = None,
             accuracy_throws: int = 0, plots: bool = True, sensors: dict | None = None) -> dict:
    """Run the three questions on a dataset directory (:mod:`dataset` format). Logs progress.

    Args:
        candidates: library names or ``package.module:Class`` (default: the whole library).
        sensors: declared sensor spec (overrides the dataset's ``sensors``).
        workers: processes for the candidate sweeps (default: every core this process may
            use; 1: in this process). A caller that already runs diagnoses in parallel passes 1.
        policy, accuracy_throws: accepted for compatibility (unused).

    Returns:
        the report dict (also written to ``out_dir/report.json`` when out_dir is given).

    Raises:
        ds.DatasetError: unusable dataset; ValueError: bad candidates (both before any work).
    """
    t0, c0 = time.time(), cpu_seconds()
    workers = fw.resolve_workers(workers)
    classes = resolve_candidates(candidates)
    throws, index = ds.load(dataset_dir)
    train = split_mask(len(throws), test_fraction, seed)
    log.info("diagnosis: %d throws (%d train, %d held out), %d candidates", len(throws), int(train.sum()), int((~train).sum()), len(classes))
    cache = rp.simulate(throws, [EffectStack()], long=True)[0]
    nominal = rp.replay(throws, [EffectStack()], dynamics_cache=cache)[0]
    noise = sc.estimate_noise(throws, nominal, {**index.get("sensors", {}), **(sensors or {})})
    scorer = sc.Scorer(throws, noise)
    S0 = scorer.score(nominal)
    M0 = scorer.signed(nominal)
    where = _where(throws, S0, scorer.D, noise, nominal, M0, scorer.bias_margin)
    where["stationarity"] = stationarity(throws, M0, scorer.D, seed)
    log.info("where: gap in %s (%.1f s)", where["carriers"] or "no channel", time.time() - t0)
    rounds, named = fw.select_effects(lambda base: sel.Evaluator(throws, scorer, base, cache), classes, scorer.D, train, seed, workers)
    stat_fit = None
    if named:  # is the residual the named effects leave the same early and late in the log?
        fit_reps = rp.replay(throws, [EffectStack(named)], dynamics_cache=cache)[0]
        stat_fit = stationarity(throws, scorer.signed(fit_reps), scorer.D, seed)
    named_c = [next(c for c in r.candidates if c.effect == r.named) for r in rounds if r.decision == "named"]
    drift = drift_of(where["stationarity"], stat_fit, named_c, [t.throw_id for t in throws])
    power = None
    if not where["gap"] and not drift["drifting"]:
        from sim_twin.diagnosis.power import detectable

        power = detectable(throws, scorer, cache, M0, scorer.D)
    verdict = verdict_of(where, rounds, named, power, drift)
    log.info("which: %s (%.0f s)", verdict["text"], time.time() - t0)
    how_far = _how_far(throws, train, scorer, rounds, named, nominal, where["carriers"]) if named and verdict["answer"] != "drifting" else None
    if how_far and how_far.get("impact_gap_shrink") is not None and how_far["constant_shift"].get("impact_gap_shrink") is not None:
        def pct(x: float) -> str:
            return f"{100 * abs(x):.0f}% {'smaller' if x >= 0 else 'LARGER'}"

        verdict["text"] += (f" [held-out throws: impact RMS {pct(how_far['impact_gap_shrink'])} with the fit, "
                            f"{pct(how_far['constant_shift']['impact_gap_shrink'])} with a constant impact shift")
        if how_far.get("gap_shrink_channel") and how_far["gap_shrink_channel"] != "impact (RMS)":
            verdict["text"] += f"; least shrink in {how_far['gap_shrink_channel']}: {100 * how_far['gap_shrink']:.0f}%"
        verdict["text"] += "]"
    fitted = RealityProfile(name="fitted-" + "+".join(e.name for e in named) if named else "fitted-none", effects=named)
    report = {
        "format": REPORT_FORMAT, "dataset": str(dataset_dir), "machine_id": index.get("machine_id"),
        "throws": len(throws), "skipped": index.get("skipped", []),
        "train": [t.throw_id for t, m in zip(throws, train) if m], "test": [t.throw_id for t, m in zip(throws, train) if not m],
        "seed": seed, "verdict": verdict, "where": where, "rounds": [r.to_dict() for r in rounds], "how_far": how_far,
        "which": [c.to_dict() for r in rounds for c in r.candidates if r.decision == "named" and c.effect == r.named],
        "effects_library": {name: cls.describe() for name, cls in EFFECTS.items()},
        "method": {"block_rows": nz.BLOCK_ROWS, "z_gap": nz.Z_GAP, "r_gap": nz.R_GAP, "bootstrap": sel.BOOTSTRAP,
                   "win_freq": sel.WIN_FREQ, "ambiguous_freq": sel.AMBIGUOUS_FREQ, "penalty_per_param": sel.PENALTY_PER_PARAM,
                   "stationarity": {"alpha": st.ALPHA, "permutations": st.PERMUTATIONS, "change_t": st.CHANGE_T, "min_segment": st.MIN_SEGMENT,
                                    "z_split": fw.Z_SPLIT}},
        "wall_s": time.time() - t0, "workers": workers, "cpu_s": cpu_seconds() - c0,
    }
    if out_dir:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        from sim_twin.twin.uncertainty import with_fitted_sigma

        prof = with_fitted_sigma(fitted, {w["effect"]: w["sigma"] for w in report["which"]}).to_dict()
        (out / "profile_fitted.json").write_text(json.dumps(prof, indent=1) + "\n")
        if plots:
            from sim_twin.diagnosis import plots as pl

            report["plots"] = pl.write_all(report, out)
        (out / "report.json").write_text(json.dumps(_json_safe(report), indent=1) + "\n")
    log.info("diagnosis done in %.1f s: %s", time.time() - t0, verdict["text"])
    return _json_safe(report)


def cpu_seconds() -> float:
    """CPU seconds of this process and its finished child processes (the sweep pool), user + system."""
    import resource

    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


def _json_safe(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return _json_safe(v.tolist())
    return v
