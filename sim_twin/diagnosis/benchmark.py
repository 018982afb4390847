"""Blind benchmark of the diagnosis on logs like a real machine's.

Every case throws THROWS times with the simulated machine (the runtime's executor and the 2D or
3D policy) under hidden effects and writes logs like a real machine's
(:class:`reallog.RealLogSpec`: white noise on every joint channel in the loop, 5 cm impact
noise, no payload channel, no payload-free flag, ~7 % of impacts missing). The dataset holds
only logs and impacts; the truth stays in the benchmark's record. Kinds of case:

* ``single``: one library effect (:data:`SINGLES`, cycled; magnitude drawn in its range);
* ``pair``: two library effects at once (:data:`PAIRS`);
* ``outside``: an effect outside the library that some library effect mimics in one channel
  (:mod:`unmodelled`; used while tuning);
* ``heldout``: outside effects kept out of tuning (:mod:`unmodelled_heldout`);
* ``impact_only``: outside effects that only move the measured impact (:mod:`unmodelled_impact`:
  a payload held sideways, a scale error of the impact measurement); right answer: not named
  (best "consistent with X, not confirmed" with the alternatives);
* ``multijoint``: a per-joint library effect on several joints at once, each its own value;
* ``power``: a library effect below what the throws can show; right answer "no gap" with the
  detectable size stated (a correct name or "consistent" with the truth is not wrong either);
* ``noise``: the nominal machine, noise only;
* ``mimic``: an outside effect that mimics a library effect in some trajectory channels
  (:mod:`unmodelled_mimic`: backlash, a valve gain error, sensor scale errors, compliance of
  another joint); right answer: no library effect confirmed, not even as a part of the answer;
* ``drifting``: an effect that changes during the log (a ramp from nominal, or a step half-way;
  library and outside effects); right answer "drifting";
* ``impact_pair``: a trajectory-visible library effect with an impact-only one; right answer:
  the first confirmed and the second listed (consistent or ambiguous).

Library effects that act only on the impact in a real machine's log (:data:`IMPACT_ONLY_LIBRARY`:
no payload channel, no open flag) are right when named with a confirming channel or listed by a
"consistent" or "ambiguous" answer (:func:`score`).

Scores: singles named (exactly the true effect), pairs (both named), parameters within
TOLERANCE of the truth (every identifiable joint for per-joint effects), 1-sigma intervals that
contain the truth, outside effects "unexplained"/"ambiguous" vs confidently wrong ("named"),
noise-only "no gap", and the held-out shrink of the named effects (throws the fit never saw).
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import time
from collections import deque
from concurrent.futures import FIRST_COMPLETED, wait
from pathlib import Path
from typing import Any

import numpy as np

from sim_twin import default_policy
from sim_twin.diagnosis import dataset as ds
from sim_twin.diagnosis.reallog import RealLogSpec
from sim_twin.provenance import short_commit
from sim_twin.twin.pools import process_pool

log = logging.getLogger(__name__)

FORMAT = "slinger-diagnosis-benchmark/2"
TOLERANCE = 0.2
POLICIES = {"2d": default_policy("2d"), "3d": default_policy("3d")}
# (effect, parameter, range, random sign)
SINGLES = [
    ("release_delay", "mean_s", (0.36, 0.6), False),
    ("valve_lag", "lag_s", (0.2, 0.32), False),
    ("passive_friction", "viscous_per_s", (0.4, 1.5), False),
    ("payload_drag", "drag_coefficient", (0.8, 1.3), False),
    ("valve_delay", "delay_s", (0.10, 0.25), False),
    ("hanging_mass", "gripper_mass_kg", (1150.0, 1800.0), False),
    ("wind", "wind_x_mps", (4.0, 9.0), True),
    ("valve_dead_band", "dead_band", (0.12, 0.25), False),
    ("grasp_offset", "forward_m", (0.12, 0.3), True),
    ("encoder_offset", "offset_boom", (0.02, 0.06), True),
    ("joint_rate_limit", "fraction", (0.5, 0.8), False),
    ("imu_offset", "offset_gripper_pitch", (0.02, 0.06), True),
    ("cabin_drift", "rate_per_arm_speed", (0.03, 0.1), True),
    ("valve_asymmetry", "asymmetry", (0.15, 0.35), True),
    ("imu_passive", "latency_s", (0.05, 0.15), False),
    ("structural_compliance", "coupling", (0.1, 0.3), True),
    ("stiction", "breakaway_fraction", (0.12, 0.3), False),
    ("valve_lag", "lag_s_dipper", (0.25, 0.45), False),
    ("wind", "wind_y_mps", (4.0, 9.0), True),
    ("impact_bias", "bias_x_m", (0.15, 0.3), True),
]
IMPACT_ONLY_LIBRARY = {"release_delay", "payload_drag", "wind", "grasp_offset", "impact_bias"}
"""Library effects whose only footprint in a real machine's log is the measured impact."""
MULTI_JOINT = [
    [("valve_asymmetry", "asymmetry_boom", (0.15, 0.3), True), ("valve_asymmetry", "asymmetry_dipper", (0.15, 0.3), True),
     ("valve_asymmetry", "asymmetry_telescope", (0.15, 0.3), True)],
    [("valve_lag", "lag_s_boom", (0.2, 0.35), False), ("valve_lag", "lag_s_dipper", (0.25, 0.45), False)],
    [("valve_dead_band", "dead_band_boom", (0.12, 0.25), False), ("valve_dead_band", "dead_band_telescope", (0.12, 0.25), False)],
]
IMPACT_ONLY = [
    ("sim_twin.diagnosis.unmodelled_impact:SidewaysGrasp", "side_m", (0.2, 0.35), True),
    ("sim_twin.diagnosis.unmodelled_impact:ImpactScale", "scale", (0.008, 0.015), True),
]
POWER_LIMITED = [
    ("release_delay", "mean_s", (0.268, 0.283), False),
    ("impact_bias", "bias_x_m", (0.008, 0.015), True),
    ("hanging_mass", "gripper_mass_kg", (845.0, 855.0), False),
]
"""Changes below the detectable sizes of 30 throws at real-log noise (sim_twin.diagnosis.power:
release delay ~50-75 ms, impact bias ~4-6 cm, hanging mass ~37 kg on the nominal 839 kg)."""
PAIRS = [
    (("release_delay", "mean_s", (0.34, 0.5), False), ("passive_friction", "viscous_per_s", (0.3, 1.0), False)),
    (("hanging_mass", "gripper_mass_kg", (1200.0, 1600.0), False), ("grasp_offset", "forward_m", (0.12, 0.25), True)),
    (("valve_lag", "lag_s", (0.22, 0.4), False), ("payload_drag", "drag_coefficient", (0.5, 1.0), False)),
    (("valve_dead_band", "dead_band", (0.12, 0.22), False), ("wind", "wind_y_mps", (4.0, 8.0), True)),
    (("encoder_offset", "offset_dipper", (0.02, 0.05), True), ("release_delay", "mean_s", (0.36, 0.55), False)),
]
OUTSIDE = [
    ("sim_twin.diagnosis.unmodelled:HoseSpring", "stiffness_nm_per_rad", (6000.0, 15000.0), False),
    ("sim_twin.diagnosis.unmodelled:ValveCrossFlow", "share", (0.3, 0.7), False),
    ("sim_twin.diagnosis.unmodelled:SpinLift", "lift_per_s", (0.1, 0.3), True),
    ("sim_twin.diagnosis.unmodelled:TelescopeCreep", "gain", (0.1, 0.3), False),
]
HELD_OUT = [
    ("sim_twin.diagnosis.unmodelled_heldout:BoomEncoderScale", "scale", (0.04, 0.1), True),
    ("sim_twin.diagnosis.unmodelled_heldout:PumpDroop", "droop", (0.3, 0.8), False),
    ("sim_twin.diagnosis.unmodelled_heldout:PitchArmature", "armature_kgm2", (400.0, 1200.0), False),
]
MIMIC = [
    ("sim_twin.diagnosis.unmodelled_mimic:BoomBacklash", "play", (0.15, 0.35), False),
    ("sim_twin.diagnosis.unmodelled_mimic:ValveGain", "gain", (0.6, 0.8), False),
    ("sim_twin.diagnosis.unmodelled_mimic:PitchImuScale", "scale", (0.08, 0.2), True),
    ("sim_twin.diagnosis.unmodelled_mimic:DipperEncoderScale", "scale", (0.05, 0.12), True),
    ("sim_twin.diagnosis.unmodelled_mimic:DipperCompliance", "coupling", (0.15, 0.35), True),
]
DRIFTING = [
    # (effect, parameter, range of the value at the end of the log, random sign, shape): from nominal at the first throw
    ("valve_lag", "lag_s_boom", (0.3, 0.45), False, "ramp"),
    ("sim_twin.diagnosis.unmodelled_mimic:ValveGain", "gain", (0.55, 0.7), False, "step"),
    ("impact_bias", "bias_x_m", (0.3, 0.45), True, "step"),
]
IMPACT_PAIRS = [
    (("passive_friction", "viscous_per_s", (0.5, 1.2), False), ("release_delay", "mean_s", (0.42, 0.55), False)),
    (("valve_lag", "lag_s", (0.22, 0.35), False), ("wind", "wind_x_mps", (5.0, 9.0), True)),
    (("hanging_mass", "gripper_mass_kg", (1200.0, 1600.0), False), ("impact_bias", "bias_x_m", (0.2, 0.35), True)),
]
"""A trajectory-visible library effect with an impact-only library one (real-log-like logs)."""
MIX = {"single": 24, "pair": 10, "outside": 8, "heldout": 8, "impact_only": 6, "multijoint": 6, "power": 6, "noise": 10,
       "mimic": 10, "drifting": 6, "impact_pair": 6}
"""Cases per kind of the full benchmark (100; the first 78 as before the last three kinds)."""
KINDS = ("single", "pair", "outside", "heldout", "impact_only", "multijoint", "power", "noise", "mimic", "drifting", "impact_pair")
OUTSIDE_KINDS = ("outside", "heldout", "impact_only", "mimic")


def _draw(rng, spec) -> tuple[str, str, float]:
    effect, param, (lo, hi), signed = spec
    v = float(rng.uniform(lo, hi)) * (float(rng.choice([-1.0, 1.0])) if signed else 1.0)
    return effect, param, round(v, 4)


def draw_cases(mix: dict[str, int], seed: int, every_3d: int = 5) -> list[dict]:
    """The case list (seeded): kinds in ``mix`` order, every ``every_3d``-th case of a kind in 3D."""
    rng = np.random.default_rng(seed)
    pools: dict[str, list[Any]] = {"single": SINGLES, "pair": PAIRS, "outside": OUTSIDE, "heldout": HELD_OUT, "impact_only": IMPACT_ONLY,
             "multijoint": MULTI_JOINT, "power": POWER_LIMITED, "noise": [None], "mimic": MIMIC, "drifting": DRIFTING,
             "impact_pair": IMPACT_PAIRS}
    out: list[dict[str, Any]] = []
    for kind, n in mix.items():
        for i in range(n):
            spec = pools[kind][i % len(pools[kind])]
            extra: dict[str, Any] = {}
            if kind == "noise":
                truth = []
            elif kind in ("pair", "multijoint", "impact_pair"):
                truth = [_draw(rng, s) for s in spec]
            elif kind == "drifting":
                truth = [_draw(rng, spec[:4])]
                extra = {"shape": spec[4]}
            else:
                truth = [_draw(rng, spec)]
            mode = "3d" if i % every_3d == every_3d - 1 else "2d"
            out.append({"case": len(out), "kind": kind, "mode": mode, "seed": int(seed * 1000 + len(out)),
                        "truth": [{"effect": e, "param": p, "value": v, **extra} for e, p, v in truth]})
    return out


def profile_of(case: dict) -> dict:
    """The hidden reality profile: one entry per effect (parameters of the same effect merged,
    e.g. a valve lag on two joints)."""
    effects: dict[str, dict] = {}
    for t in case["truth"]:
        effects.setdefault(t["effect"], {})[t["param"]] = t["value"]
    return {"name": f"case-{case['case']}", "effects": [{"effect": e, "params": p} for e, p in effects.items()]}


def per_throw_profiles(case: dict, throws: int) -> list[dict] | None:
    """A drifting case's profile per throw (the truth's value reached at the last throw from the
    nominal at the first: a straight ramp, or a step half-way); None for other kinds."""
    if case["kind"] != "drifting":
        return None
    from sim_twin.twin.effects import effect_class

    out = []
    for i in range(throws):
        effects: dict[str, dict] = {}
        for t in case["truth"]:
            p0 = next(p.nominal for p in effect_class(t["effect"]).params if p.name == t["param"])
            f = i / max(throws - 1, 1) if t.get("shape") == "ramp" else float(i >= throws // 2)
            effects.setdefault(t["effect"], {})[t["param"]] = round(p0 + f * (t["value"] - p0), 6)
        out.append({"name": f"case-{case['case']}-throw-{i}", "effects": [{"effect": e, "params": p} for e, p in effects.items()]})
    return out


def _compare(truth: dict, named: list[dict]) -> list[dict]:
    """Fitted vs true values of one true effect: per compared parameter (identifiable joints
    for per-joint effects): truth, fit, sigma, relative error, inside 1 sigma."""
    from sim_twin.twin.effects import effect_class

    cand = next((c for c in named if c["effect"] == truth["effect"]), None)
    if cand is None:
        return []
    cls = effect_class(truth["effect"])
    values = cls(**{truth["param"]: truth["value"]}).values
    keys = [k for k, v in values.items() if k in cand["sigma"] and abs(v - next(p.nominal for p in cls.params if p.name == k)) > 1e-12]
    out = []
    for k in keys:
        fit, sig, tv = cand["params"][k], cand["sigma"][k], values[k]
        out.append({"param": k, "truth": tv, "fit": fit, "sigma": sig, "rel_error": abs(fit - tv) / abs(tv),
                    "in_1sigma": bool(abs(fit - tv) <= sig), "z": (fit - tv) / sig if sig > 0 else None,
                    "sigma_parts": {part: (v or {}).get(k) for part, v in cand.get("sigma_parts", {}).items()}})
    return out


def run_case(case: dict, throws: int, workdir: Path, keep: bool = False) -> dict:
    """Generate, diagnose blind, score one case."""
    from sim_twin.diagnosis.diagnose import diagnose

    t0 = time.time()
    c0 = time.process_time()
    data_dir = workdir / f"case{case['case']:03d}"
    ds.generate(data_dir, profile_of(case), throws, POLICIES[case["mode"]], seed=case["seed"], mode=case["mode"], real_log=RealLogSpec(),
                per_throw=per_throw_profiles(case, throws))
    t_gen = time.time() - t0
    rep = diagnose(data_dir, None, seed=case["seed"], plots=False, workers=1)  # cases run in parallel already
    v = rep["verdict"]
    named = v.get("evidence", {}).get("named", [])
    row = {**case, "answer": v["answer"], "effects": v.get("effects", []), "between": v.get("between"), "text": v["text"],
           "throws_used": rep["throws"], "skipped": len(rep["skipped"]), "gen_s": t_gen}
    row["alternatives"] = [a for n in v.get("not_confirmed", []) for a in n.get("alternatives", [])]
    row["confirmed"] = list(v.get("confirmed", []))
    row["consistent"] = [n["effect"] for n in v.get("not_confirmed", [])]
    row["power_stated"] = bool(v.get("power") and v["power"].get("text"))
    score(row)
    kind = case["kind"]
    row["params"] = [c for t in case["truth"] for c in _compare(t, named)] if kind in ("single", "pair", "multijoint", "impact_pair") else []
    hf = rep.get("how_far") or {}
    row["held_out"] = {k: hf.get(k) for k in ("gap_shrink", "impact_gap_shrink", "share_of_shrink", "impact_rms_m", "test_throws", "constant_shift")} if hf else None
    row["wall_s"] = time.time() - t0
    row["cpu_s"] = time.process_time() - c0
    if not keep:
        import shutil

        shutil.rmtree(data_dir, ignore_errors=True)
    log.info("case %d %s %s %s -> %s (%s) %.0f s", case["case"], kind, case["mode"], [(t["effect"].split(":")[-1], t["value"]) for t in case["truth"]],
             v["text"][:160], "ok" if row["correct"] else "WRONG", row["wall_s"])
    return row


def score(row: dict) -> dict:
    """Right or wrong, from the row's truth and recorded answer (``answer``, ``effects``,
    ``between``, ``alternatives``, ``power_stated``), in place; also ``one_named`` (pairs),
    ``confidently_wrong`` (outside kinds), ``no_gap`` (power).

    An impact-only library effect (:data:`IMPACT_ONLY_LIBRARY`) is right when named with a
    confirming channel or listed by a "consistent" or "ambiguous" answer (the effect, its
    alternatives, or the two it is ambiguous between): on a real machine's log the impacts alone
    cannot tell it from the others.
    """
    kind, ans = row["kind"], row["answer"]
    truth = [t["effect"] for t in row["truth"]]
    effects = list(row.get("effects") or [])
    listed = set(effects) | set(row.get("alternatives") or []) | set(row.get("between") or []) | set(row.get("consistent") or [])
    confirmed = list(row.get("confirmed") or [])  # rows of a run before "confirmed" was recorded: none
    stated = row.get("power_stated")
    if stated is None:  # rows of a run before power_stated was recorded
        stated = "would not be visible" in row.get("text", "")

    def found(e: str) -> bool:
        if e in IMPACT_ONLY_LIBRARY:
            return (ans in ("named", "consistent") and e in effects) or (ans in ("consistent", "ambiguous") and e in listed)
        return e in effects and ans in ("named", "consistent", "ambiguous")

    if kind == "single" and truth[0] in IMPACT_ONLY_LIBRARY:
        row["correct"] = (ans == "named" and effects == truth) or (ans in ("consistent", "ambiguous") and truth[0] in listed)
    elif kind in ("single", "multijoint"):
        row["correct"] = ans == "named" and effects == sorted(set(truth), key=truth.index)
    elif kind == "pair":
        row["correct"] = ans in ("named", "consistent", "ambiguous") and all(found(e) for e in truth) and (ans != "ambiguous" or any(e in IMPACT_ONLY_LIBRARY for e in truth))
        row["one_named"] = bool(set(truth) & set(effects))
    elif kind == "impact_pair":
        traj, imp = truth[0], truth[1]
        row["correct"] = ans in ("consistent", "ambiguous") and traj in confirmed and imp in listed
        row["one_named"] = bool(set(truth) & set(effects))
    elif kind in OUTSIDE_KINDS:
        # a library effect confirmed as a part of the answer is as wrong as one named for the whole
        row["correct"] = ans in ("unexplained", "ambiguous", "consistent", "drifting") and not confirmed
        row["confidently_wrong"] = ans == "named" or bool(confirmed)
    elif kind == "drifting":
        row["correct"] = ans == "drifting"
    elif kind == "power":
        row["no_gap"] = ans == "no_gap"
        row["correct"] = (row["no_gap"] and stated) or (ans in ("named", "consistent") and truth[0] in listed)
    elif kind == "noise":
        row["correct"] = ans == "no_gap" and stated
    else:  # error rows keep what error_row set
        row.setdefault("correct", False)
    return row


def _frac(xs) -> float | None:
    xs = list(xs)
    return sum(bool(x) for x in xs) / len(xs) if xs else None


def summarise(rows: list[dict]) -> dict:
    by = {k: [r for r in rows if r["kind"] == k] for k in KINDS}
    outside = by["outside"] + by["heldout"] + by["impact_only"] + by["mimic"]
    lib = by["single"] + by["pair"] + by["multijoint"]
    params = [p for r in lib if r["correct"] for p in r["params"]]
    per_case_ok = [all(p["rel_error"] <= TOLERANCE for p in r["params"]) and bool(r["params"]) for r in lib if r["correct"]]
    shrink = [r["held_out"]["gap_shrink"] for r in rows if r.get("held_out") and r["held_out"].get("gap_shrink") is not None and r["correct"]]
    ishrink = [r["held_out"]["impact_gap_shrink"] for r in rows if r.get("held_out") and r["held_out"].get("impact_gap_shrink") is not None and r["correct"]]
    cshrink = [(r["held_out"].get("constant_shift") or {}).get("impact_gap_shrink") for r in rows
               if r.get("held_out") and r["correct"] and (r["held_out"].get("constant_shift") or {}).get("impact_gap_shrink") is not None]
    imp_only = [r for r in by["single"] if r["truth"][0]["effect"] in IMPACT_ONLY_LIBRARY] + by["impact_only"]
    answers: dict[str, dict[str, int]] = {}
    for r in rows:
        answers.setdefault(r["kind"], {}).setdefault(r["answer"], 0)
        answers[r["kind"]][r["answer"]] += 1
    return {
        "cases": len(rows), "by_kind": {k: len(v) for k, v in by.items() if v}, "errors": sum(r["answer"] == "error" for r in rows),
        "answers_by_kind": answers,
        "singles_named": _frac(r["correct"] for r in by["single"]),
        "singles_confirmed_named": _frac(r["correct"] for r in by["single"] if r["truth"][0]["effect"] not in IMPACT_ONLY_LIBRARY),
        "singles_impact_only_consistent": _frac(r["correct"] for r in by["single"] if r["truth"][0]["effect"] in IMPACT_ONLY_LIBRARY),
        "impact_only_not_named": _frac(r["answer"] != "named" for r in imp_only),
        "multijoint_named": _frac(r["correct"] for r in by["multijoint"]),
        "pairs_both_named": _frac(r["correct"] for r in by["pair"]),
        "pairs_one_named": _frac(r.get("one_named") for r in by["pair"]),
        "params_within_tolerance_cases": _frac(per_case_ok), "params_within_tolerance_values": _frac(p["rel_error"] <= TOLERANCE for p in params),
        "params_compared": len(params), "tolerance": TOLERANCE,
        "one_sigma_coverage": _frac(p["in_1sigma"] for p in params),
        "one_sigma_coverage_singles": _frac(p["in_1sigma"] for r in by["single"] if r["correct"] for p in r["params"]),
        "one_sigma_coverage_pairs": _frac(p["in_1sigma"] for r in by["pair"] if r["correct"] for p in r["params"]),
        "abs_z_median": float(np.median([abs(p["z"]) for p in params if p.get("z") is not None])) if params else None,
        "outside_unexplained_or_ambiguous": _frac(r["correct"] for r in outside),
        "outside_confidently_wrong": _frac(r["confidently_wrong"] for r in outside),
        "outside_visible": _frac(r["correct"] for r in by["outside"]), "outside_heldout": _frac(r["correct"] for r in by["heldout"]),
        "outside_impact_only": _frac(r["correct"] for r in by["impact_only"]),
        "power_no_gap": _frac(r.get("no_gap") and r.get("power_stated") for r in by["power"]),
        "power_correct": _frac(r["correct"] for r in by["power"]),
        "noise_no_gap": _frac(r["correct"] for r in by["noise"]),
        "false_drifting": _frac(r["answer"] == "drifting" for r in rows if r["kind"] not in ("drifting",)),
        "mimic_not_confirmed": _frac(r["correct"] for r in by["mimic"]),
        "drifting_found": _frac(r["correct"] for r in by["drifting"]),
        "impact_pairs_listed": _frac(r["correct"] for r in by["impact_pair"]),
        "wall_s_per_case": float(np.mean([r["wall_s"] for r in rows])) if rows else None,
        "held_out_gap_shrink_median": float(np.median(shrink)) if shrink else None,
        "held_out_impact_shrink_median": float(np.median(ishrink)) if ishrink else None,
        "held_out_impact_shrink_constant_shift_median": float(np.median(np.asarray(cshrink, dtype=float))) if cshrink else None,
        "cpu_s": float(sum(r["cpu_s"] for r in rows)),
        "cpu_s_per_case": float(np.mean([r["cpu_s"] for r in rows])) if rows else None,
        "cpu_s_per_case_by_kind": {k: float(np.mean([r["cpu_s"] for r in v])) for k, v in by.items() if v},
    }


BARS: list[tuple[str, str, Any]] = [("singles_named", ">=", 0.9), ("multijoint_named", ">=", 0.9), ("pairs_both_named", ">=", 0.7),
        ("params_within_tolerance_cases", ">=", 0.8), ("outside_unexplained_or_ambiguous", ">=", 0.9), ("outside_confidently_wrong", "<=", 0.0),
        ("impact_only_not_named", ">=", 1.0), ("power_no_gap", ">=", 0.9), ("noise_no_gap", ">=", 0.9), ("one_sigma_coverage", "in", (0.6, 0.75)),
        ("mimic_not_confirmed", ">=", 1.0), ("drifting_found", ">=", 0.8), ("impact_pairs_listed", ">=", 0.7)]


def format_summary(result: dict) -> str:
    s = result["summary"]

    def pct(x):
        return "n/a" if x is None else f"{100 * x:.0f}%"

    lines = [f"Blind diagnosis benchmark (real-log-like: noise on every channel, no payload channel, no open flag, missing impacts): "
             f"{s['cases']} cases {s['by_kind']}, {result['throws_per_case']} throws each, seed {result['seed']}"
             + ("" if result.get("complete", True) else f"  [PARTIAL: {s['cases']} of {result.get('cases_planned')} cases finished]"),
             f"date {result.get('date')}, commit {result.get('commit')}, host {result.get('host')} ({result.get('cpu_count')} cores), "
             f"policy SHA-256 {result.get('policy_sha256')}, command: {result.get('command')}",
             f"wall {result['wall_s'] / 60:.1f} min, CPU {s['cpu_s'] / 60:.1f} min (workers {result['workers']}, machine shared); CPU per case "
             + (f"{s['cpu_s_per_case']:.0f} s (" + ", ".join(f"{k} {v:.0f} s" for k, v in s.get('cpu_s_per_case_by_kind', {}).items()) + ")"
                if s.get("cpu_s_per_case") is not None else "n/a"), ""]
    for key, op, bar in BARS:
        x = s[key]
        ok = x is not None and (x >= bar if op == ">=" else x <= bar if op == "<=" else bar[0] <= x <= bar[1])
        lines.append(f"  {key:36s} {pct(x):>5s}   bar {op} {bar if op == 'in' else pct(bar)}   {'met' if ok else 'MISSED'}")
    lines += [f"  outside (visible / held-out / impact-only): {pct(s['outside_visible'])} / {pct(s['outside_heldout'])} / {pct(s.get('outside_impact_only'))}",
              f"  singles confirmed-named / impact-only answered consistent: {pct(s.get('singles_confirmed_named'))} / {pct(s.get('singles_impact_only_consistent'))}",
              f"  answers by kind: {s.get('answers_by_kind')}",
              f"  pairs with one effect named:         {pct(s['pairs_one_named'])}",
              f"  parameter values within ±20%:        {pct(s['params_within_tolerance_values'])} of {s['params_compared']}",
              f"  1 sigma coverage singles / pairs:    {pct(s.get('one_sigma_coverage_singles'))} / {pct(s.get('one_sigma_coverage_pairs'))}"
              + (f"; median |fit - truth| / sigma {s['abs_z_median']:.2f} (0.67 for calibrated Gaussian errors)" if s.get("abs_z_median") is not None else ""),
              f"  held-out (unseen throws) chi2-excess shrink, median: {pct(s['held_out_gap_shrink_median'])}; impact RMS shrink: {pct(s['held_out_impact_shrink_median'])}"
              f" (a constant impact shift fitted on the training throws: {pct(s.get('held_out_impact_shrink_constant_shift_median'))})",
              "", "case kind mode truth -> answer"]
    for r in result["cases"]:
        truth = ", ".join(f"{t['effect'].split(':')[-1]} {t['param']}={t['value']:+g}" for t in r["truth"]) or "-"
        lines.append(f"  {r['case']:3d} {r['kind']:11s} {r['mode']} {'ok   ' if r['correct'] else 'WRONG'} {truth} -> {r['answer']} {' + '.join(r['effects'])}"
                     + (f" between {r['between']}" if r.get("between") else "") + (f" (alternatives {', '.join(r['alternatives'])})" if r.get("alternatives") else ""))
    return "\n".join(lines)


def _job(args):
    case, throws, work, keep = args
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    for name in ("sim_twin.diagnosis.forward", "sim_twin.diagnosis.dataset"):
        logging.getLogger(name).setLevel(logging.WARNING)
    t0, c0 = time.time(), time.process_time()
    try:
        return run_case(case, throws, Path(work), keep)
    except Exception as e:  # noqa: BLE001  one broken case must not lose a long run: it is recorded as a wrong answer
        import traceback

        log.error("case %d failed: %s\n%s", case["case"], e, traceback.format_exc())
        return error_row(case, f"{type(e).__name__}: {e}", time.time() - t0, time.process_time() - c0)


def error_row(case: dict, error: str, wall_s: float, cpu_s: float) -> dict:
    """The row of a case whose diagnosis raised: answer "error", scored as not correct (for an
    outside effect: not "unexplained"; counted in the summary's ``errors``)."""
    return {**case, "answer": "error", "effects": [], "between": None, "alternatives": [], "text": f"error: {error}", "error": error, "throws_used": None, "skipped": 0,
            "gen_s": None, "correct": False, "one_named": False, "confidently_wrong": False, "params": [],
            "held_out": None, "wall_s": wall_s, "cpu_s": cpu_s}


def plot(result: dict, png: Path) -> Path:
    """``png``: left, the share of cases answered right per kind (with the count); right, the
    answers per kind (named / consistent / ambiguous / unexplained / no_gap / error) as stacked bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["cases"]
    kinds = [k for k in KINDS if any(r["kind"] == k for r in rows)]
    answers = ("named", "consistent", "ambiguous", "unexplained", "no_gap", "error")
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5))
    share = [np.mean([bool(r["correct"]) for r in rows if r["kind"] == k]) for k in kinds]
    n = [sum(r["kind"] == k for r in rows) for k in kinds]
    a1.bar(kinds, share, color="tab:green")
    for i, (v, c) in enumerate(zip(share, n)):
        a1.text(i, v + 0.02, f"{100 * v:.0f}% of {c}", ha="center", fontsize=8)
    a1.set_ylim(0, 1.15)
    a1.set_ylabel("answered right")
    a1.set_title("diagnosis benchmark: right answers per kind")
    bottom = np.zeros(len(kinds))
    for a in answers:
        h = np.array([sum(r["kind"] == k and r["answer"] == a for r in rows) for k in kinds], dtype=float)
        if h.any():
            a2.bar(kinds, h, bottom=bottom, label=a)
            bottom += h
    a2.set_ylabel("cases")
    a2.set_title("answers per kind")
    a2.legend(fontsize=8)
    for ax in (a1, a2):
        ax.tick_params(axis="x", rotation=30, labelsize=8)
    sub = f"{result.get('date')} commit {result.get('commit')}, {result['throws_per_case']} throws per case" + ("" if result.get("complete", True) else ", PARTIAL run")
    fig.suptitle(sub, fontsize=9)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return png


def _write(out: Path | None, result: dict) -> str:
    text = format_summary(result)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1) + "\n")
        out.with_suffix(".txt").write_text(text + "\n")
    return text


def provenance() -> dict:
    """Date (UTC), host, the policies' SHA-256 and the command line of this run."""
    import hashlib
    import platform
    import sys
    from datetime import UTC, datetime

    return {"date": datetime.now(UTC).isoformat(timespec="seconds"), "host": platform.node(),
            "policy_sha256": {m: hashlib.sha256(Path(p).read_bytes()).hexdigest() for m, p in POLICIES.items()},
            "command": " ".join(["slinger diagnose"] + sys.argv[1:])}


def load_done(out: Path, seed: int, throws: int, mix: dict[str, int]) -> list[dict]:
    """Rows of a previous run of the same benchmark in ``out`` (to resume it); [] when there is none.

    Raises:
        ValueError: ``out`` holds a run with another seed, throw count, mix or format.
    """
    if not out.exists():
        return []
    prev = json.loads(out.read_text())
    theirs = (prev.get("format"), prev.get("seed"), prev.get("throws_per_case"), prev.get("mix"))
    if theirs != (FORMAT, seed, throws, mix):
        raise ValueError(f"cannot resume {out}: it holds format/seed/throws/mix {theirs}, this run is {(FORMAT, seed, throws, mix)}")
    return list(prev.get("cases", []))


COST_S = {"single": 44.0, "pair": 45.0, "outside": 88.0, "heldout": 141.0, "impact_only": 18.0, "multijoint": 65.0, "power": 5.0, "noise": 14.0,
          "mimic": 90.0, "drifting": 60.0, "impact_pair": 45.0}
"""Mean CPU seconds of one 30-throw case per kind (reports/diagnosis_benchmark.json, 2-core VM,
2026-11-22): used only to start the long cases first, which shortens the wall time of a parallel
run (longest-processing-time-first scheduling)."""


def parse_shard(text: str) -> tuple[int, int]:
    """``"I/N"`` (1 <= I <= N) as ``(I, N)``.

    Raises:
        ValueError: not of that form.
    """
    try:
        i, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise ValueError(f"a shard is I/N with 1 <= I <= N, got {text!r}") from None
    if not 1 <= i <= n:
        raise ValueError(f"a shard is I/N with 1 <= I <= N, got {text!r}")
    return i, n


def shard_of(cases: list[dict], shard: tuple[int, int]) -> list[dict]:
    """The cases of shard ``(I, N)``: the cases ordered by kind (as :func:`draw_cases` lists
    them) and dealt round-robin, the p-th to shard ``p % N + 1``, so every shard gets each kind's
    cases within one and the N shards together hold every case exactly once."""
    i, n = shard
    return [c for p, c in enumerate(sorted(cases, key=lambda c: (KINDS.index(c["kind"]), c["case"]))) if p % n == i - 1]


def stop_workers(pool) -> None:
    """Stop the cases still running in ``pool`` (the processes this run started) and shut it down."""
    terminate = getattr(pool, "terminate_workers", None)  # Python >= 3.14
    if terminate is not None:
        terminate()
        return
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        proc.terminate()
    pool.shutdown(wait=True, cancel_futures=True)


def run(mix: dict[str, int], throws: int, seed: int, workers: int, out: Path | None, keep_data: Path | None = None,
        only: list[int] | None = None, resume: bool = False, shard: tuple[int, int] | None = None,
        deadline_s: float | None = None, plots: bool = True) -> dict:
    """The benchmark (cases in parallel over ``workers`` processes, one case per process, the
    long kinds first); writes ``out`` (JSON) and ``out`` with .txt after every finished case
    (``complete`` says whether all cases of the benchmark ran).

    Args:
        only: case numbers to run (default all).
        resume: keep the finished cases already in ``out`` (same seed, throws, mix) and run only
            the others; CPU seconds of earlier runs stay in their rows.
        shard: ``(I, N)``: only the cases of shard I of N (:func:`shard_of`); :func:`merge`
            combines the N reports.
        deadline_s: wall seconds from the start: no case starts after it, and cases still
            running at it are stopped (with ``workers`` > 1; one worker finishes its case) and
            left out of the report, which then says ``complete`` false and lists them under
            ``not_run``; ``--resume`` runs them later.
        plots: write the figure ``out`` with .png.

    Raises:
        ValueError: ``resume`` with an ``out`` from another benchmark (:func:`load_done`).
    """
    cases = draw_cases(mix, seed)
    if shard is not None:
        cases = shard_of(cases, shard)
    if only is not None:
        cases = [c for c in cases if c["case"] in only]
    t0 = time.time()
    rows: list[dict] = load_done(out, seed, throws, mix) if resume and out is not None else []
    done = {r["case"] for r in rows}
    planned = len({c["case"] for c in cases} | done)
    wall_before = float(json.loads(out.read_text()).get("wall_s", 0.0)) if rows and out is not None else 0.0
    cases = [c for c in cases if c["case"] not in done]

    def result(complete: bool) -> dict:
        done = sorted(rows, key=lambda r: r["case"])
        got = {r["case"] for r in rows}
        return {"format": FORMAT, "seed": seed, "throws_per_case": throws, "workers": workers, "mix": mix, "wall_s": wall_before + time.time() - t0,
                "cpu_count": os.cpu_count(), "commit": short_commit(), "complete": complete, "cases_planned": planned,
                "shard": list(shard) if shard else None, "deadline_s": deadline_s,
                "not_run": sorted(c["case"] for c in cases if c["case"] not in got), **provenance(),
                "summary": summarise(done), "cases": done}

    def past_deadline() -> bool:
        return deadline_s is not None and time.time() - t0 >= deadline_s

    with tempfile.TemporaryDirectory(prefix="slinger-bench-") as tmp:
        work = keep_data or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        jobs = deque((c, throws, str(work), keep_data is not None) for c in sorted(cases, key=lambda c: (-COST_S.get(c["kind"], 0.0), c["case"])))
        if workers > 1:
            pool = process_pool(workers)
            running: dict = {}
            try:
                while jobs or running:
                    while jobs and len(running) < workers and not past_deadline():
                        job = jobs.popleft()
                        running[pool.submit(_job, job)] = job
                    if not running:
                        break
                    left = None if deadline_s is None else max(0.0, deadline_s - (time.time() - t0))
                    finished, _ = wait(running, timeout=left, return_when=FIRST_COMPLETED)
                    for fut in finished:  # written as each case finishes
                        running.pop(fut)
                        rows.append(fut.result())
                        _write(out, result(False))
                    if not finished and past_deadline():
                        log.warning("deadline of %.0f s: stopping %d running cases (%s)", deadline_s, len(running), sorted(j[0]["case"] for j in running.values()))
                        break
            finally:
                if running:
                    stop_workers(pool)
                else:
                    pool.shutdown(wait=True)
        else:
            while jobs and not past_deadline():
                rows.append(_job(jobs.popleft()))
                _write(out, result(False))
    res = result(len(rows) == planned == len(draw_cases(mix, seed)))
    log.info("\n%s", _write(out, res))
    if plots and out is not None and rows:
        plot(res, out.with_suffix(".png"))
    return res


def merge(reports: list[Path], out: Path | None, plots: bool = True) -> dict:
    """One benchmark report from the reports of its shards (or of any runs of the same benchmark:
    same format, seed, throws per case and mix): the cases of all, the summary recomputed,
    ``complete`` when every case of the benchmark is there, ``wall_s`` the longest run's,
    ``shards`` the provenance of each input (file, date, commit, host, cores, workers, command,
    wall seconds, cases). Writes ``out`` (JSON, .txt and, with ``plots``, .png) when given.

    Raises:
        ValueError: no reports, a report of another benchmark or format, or one case in two
            reports with different answers.
    """
    if not reports:
        raise ValueError("merge needs at least one benchmark report")
    parts = []
    for path in reports:
        try:
            body = json.loads(Path(path).read_text())
        except (OSError, ValueError) as e:
            raise ValueError(f"{path}: not a readable benchmark report: {e}") from e
        if not isinstance(body, dict) or body.get("format") != FORMAT:
            raise ValueError(f"{path}: not a {FORMAT} report (format {body.get('format') if isinstance(body, dict) else None!r})")
        parts.append((Path(path), body))
    key = {(b["seed"], b["throws_per_case"], json.dumps(b["mix"], sort_keys=True), json.dumps(b.get("policy_sha256"), sort_keys=True)) for _, b in parts}
    if len(key) > 1:
        raise ValueError(f"the reports are of different benchmarks (seed, throws, mix, policies): {sorted(key)}")
    _, first = parts[0]
    rows: dict[int, dict] = {}
    for path, body in parts:
        for r in body["cases"]:
            old = rows.get(r["case"])
            if old is not None and (old["answer"], old["effects"]) != (r["answer"], r["effects"]):
                raise ValueError(f"case {r['case']} is in two reports with different answers ({old['answer']} {old['effects']} vs "
                                 f"{r['answer']} {r['effects']}; the second in {path})")
            rows.setdefault(r["case"], r)
    done = sorted(rows.values(), key=lambda r: r["case"])
    everything = draw_cases(first["mix"], first["seed"])
    commits = sorted({str(b.get("commit")) for _, b in parts})
    res = {"format": FORMAT, "seed": first["seed"], "throws_per_case": first["throws_per_case"], "workers": max(b["workers"] for _, b in parts),
           "mix": first["mix"], "wall_s": max(float(b["wall_s"]) for _, b in parts), "cpu_count": max(b.get("cpu_count") or 0 for _, b in parts),
           "commit": commits[0] if len(commits) == 1 else " ".join(commits), "complete": len(done) == len(everything),
           "cases_planned": len(everything), "not_run": sorted({c["case"] for c in everything} - set(rows)),
           "date": max(str(b.get("date")) for _, b in parts), "host": " ".join(sorted({str(b.get("host")) for _, b in parts})),
           "policy_sha256": first.get("policy_sha256"),
           "command": "; ".join(str(b.get("command")) for _, b in parts) + "; slinger diagnose merge",
           "shards": [{"file": str(p), **{k: b.get(k) for k in ("shard", "date", "commit", "host", "cpu_count", "workers", "command", "wall_s", "deadline_s")},
                       "cases": len(b["cases"]), "cpu_s": b["summary"]["cpu_s"]} for p, b in parts],
           "summary": summarise(done), "cases": done}
    log.info("\n%s", _write(out, res))
    if plots and out is not None and done:
        plot(res, out.with_suffix(".png"))
    return res


SMALL_MIX = {"single": 2, "pair": 1, "outside": 1, "heldout": 0, "impact_only": 1, "multijoint": 1, "power": 1, "noise": 1,
             "mimic": 1, "drifting": 1, "impact_pair": 1}
SMALL_THROWS = 16
"""The CI version (tests/test_diagnosis.py runs a few of its cases)."""
