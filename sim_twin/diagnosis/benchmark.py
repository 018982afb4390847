"""Blind check of the diagnosis: throws generated under a hidden effect, diagnosed, scored.

Each case draws (seeded) one effect and a magnitude: library effects cycle through
:data:`CASES` (every library effect, some with two parameters), out-of-library cases use user-code
effects the diagnosis has no candidate for (:mod:`sim_twin.diagnosis.unmodelled`). The simulated
machine throws with the runtime's executor and the 2D policy under the nominal profile plus that
effect; the dataset directory holds only telemetry and impacts (the truth stays in the
benchmark's own record); :func:`sim_twin.diagnosis.diagnose.diagnose` then runs blind.

Scores per case: named correctly (library: the verdict names the true effect; outside: the
verdict is "unexplained"); primary parameter within ``tolerance`` (relative) of the truth; the
held-out impact-error gap shrink after adding the named effect (impact error with the payload
released at the logged opening; for the release delay, whose gap lies in the timing, the
predicted release). Cases whose nominal held-out impact error is below ``MIN_IMPACT_GAP_M``
have no impact gap to shrink beyond the scatter of the release jitter and are left out of that
bar (listed as n/a).
"""

from __future__ import annotations

import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from sim_twin.diagnosis import dataset as ds
from sim_twin.diagnosis.diagnose import diagnose
from sim_twin.effects import EFFECTS

log = logging.getLogger(__name__)

CASES: list[tuple[str, str, tuple[float, float], bool]] = [
    # (effect, primary parameter, magnitude range, random sign)
    ("release_delay", "mean_s", (0.35, 0.6), False),
    ("passive_friction", "viscous_per_s", (0.3, 1.5), False),
    ("valve_dead_band", "dead_band", (0.12, 0.25), False),
    ("valve_delay", "delay_s", (0.10, 0.25), False),
    ("valve_lag", "lag_s", (0.2, 0.45), False),
    ("joint_rate_limit", "fraction", (0.5, 0.8), False),
    ("payload_drag", "drag_coefficient", (0.5, 1.2), False),
    ("grasp_offset", "forward_m", (0.1, 0.3), True),
    ("cabin_drift", "rate_per_arm_speed", (0.03, 0.1), True),
    ("imu_passive", "latency_s", (0.04, 0.15), False),
    ("hanging_mass", "gripper_mass_kg", (1100.0, 1800.0), False),
    ("passive_friction", "coulomb_rad_per_s2", (0.5, 2.0), False),
    ("grasp_offset", "up_m", (0.1, 0.3), True),
]
OUTSIDE: list[tuple[str, str, tuple[float, float], bool]] = [
    ("sim_twin.diagnosis.unmodelled:CrossWind", "wind_mps", (4.0, 8.0), True),
    ("sim_twin.diagnosis.unmodelled:BoomCompliance", "coupling", (0.1, 0.25), True),
]
MIN_IMPACT_GAP_M = 0.10  # twice the ~5 cm impact scatter the nominal release jitter (15 ms) alone causes


def draw_cases(n_library: int, n_outside: int, seed: int) -> list[dict]:
    """The case list: library cases cycle through CASES (so any n >= 11 spans every library
    effect), outside cases alternate between OUTSIDE; magnitudes uniform in range, seeded."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_library + n_outside):
        lib = i < n_library
        effect, param, (lo, hi), signed = CASES[i % len(CASES)] if lib else OUTSIDE[(i - n_library) % len(OUTSIDE)]
        value = float(rng.uniform(lo, hi)) * (float(rng.choice([-1.0, 1.0])) if signed else 1.0)
        out.append({"case": i, "effect": effect, "param": param, "value": round(value, 4), "library": lib, "seed": int(seed * 1000 + i)})
    return out


def run_case(case: dict, throws: int, policy: Path, workers: int, workdir: Path) -> dict:
    """Generate, diagnose blind, score one case."""
    t0 = time.time()
    profile = {"name": f"case-{case['case']}", "effects": [{"effect": case["effect"], "params": {case["param"]: case["value"]}}]}
    data_dir = workdir / f"case{case['case']:03d}"
    ds.generate(data_dir, profile, throws, policy, seed=case["seed"], workers=workers)
    report = diagnose(data_dir, out_dir=None, seed=case["seed"], workers=workers, plots=False)
    verdict = report["verdict"]
    best = report["which"][0]
    hf = report["how_far"]["impact_error_m"]
    row = {**case, "answer": verdict["answer"], "named": verdict["effect"], "best": best["effect"], "best_score": best["score"],
           "best_params": best["params"], "j_test_nominal": best["j_test_nominal"], "landed_throws": report["throws"], "wall_s": None}
    if case["library"]:
        row["correct"] = verdict["answer"] == "named" and verdict["effect"] == case["effect"]
        fitted = next(r for r in report["which"] if r["effect"] == case["effect"])
        est = fitted["params"][case["param"]]
        row["fitted"] = est
        row["sigma"] = fitted["sigma"].get(case["param"])
        row["rel_error"] = abs(est - case["value"]) / abs(case["value"])
        row["param_ok"] = bool(row["correct"] and row["rel_error"] <= 0.2)
        key = "predicted" if EFFECTS[case["effect"]].stage == "release" else "conditioned"
        before, after = hf[f"{key}_before"], hf[f"{key}_after"]
        row["impact_gap_m"] = {"kind": key, "before": before, "after": after}
        row["impact_shrink"] = (1 - after / before) if row["correct"] and before >= MIN_IMPACT_GAP_M else None
    else:
        row["correct"] = verdict["answer"] == "unexplained"
    row["wall_s"] = time.time() - t0
    log.info("case %d %s %s=%+.4g -> %s %s (%s) %.0f s", case["case"], case["effect"].split(":")[-1], case["param"], case["value"],
             verdict["answer"], verdict["effect"] or "", "ok" if row["correct"] else "WRONG", row["wall_s"])
    return row


def summarise(rows: list[dict], tolerance: float = 0.2) -> dict:
    """Bars and the confusion matrix (truth -> answer)."""
    lib = [r for r in rows if r["library"]]
    out = [r for r in rows if not r["library"]]
    named_ok = [r for r in lib if r["correct"]]
    shrink = [r["impact_shrink"] for r in named_ok if r.get("impact_shrink") is not None]
    truth_names = [r["effect"] if r["library"] else "outside:" + r["effect"].split(":")[-1] for r in rows]
    answers = [r["named"] if r["answer"] == "named" else r["answer"] for r in rows]
    labels_t = sorted(set(truth_names), key=lambda n: (n.startswith("outside"), n))
    labels_a = [n for n in list(EFFECTS) if n in answers] + [a for a in ("unexplained", "no_gap") if a in answers]
    matrix = {t: {a: sum(1 for tt, aa in zip(truth_names, answers) if tt == t and aa == a) for a in labels_a} for t in labels_t}
    return {
        "cases": len(rows), "library_cases": len(lib), "outside_cases": len(out),
        "named_correctly": len(named_ok) / len(lib) if lib else None,
        "param_within_tolerance": sum(r["param_ok"] for r in lib) / len(lib) if lib else None,
        "tolerance": tolerance,
        "impact_gap_shrink_mean": float(np.mean(shrink)) if shrink else None,
        "impact_gap_shrink_min": float(np.min(shrink)) if shrink else None,
        "impact_gap_shrink_cases_ge_70pct": (sum(s >= 0.7 for s in shrink) / len(shrink)) if shrink else None,
        "impact_gap_cases": len(shrink),
        "outside_unexplained": sum(r["correct"] for r in out) / len(out) if out else None,
        "confusion": {"truth": labels_t, "answer": labels_a, "matrix": matrix},
    }


def confusion_text(summary: dict) -> str:
    """The confusion matrix as a fixed-width table (rows: truth, columns: answer)."""
    c = summary["confusion"]
    short = {a: a.replace("valve_", "v_").replace("passive_", "p_").replace("joint_", "j_")[:11] for a in c["answer"]}
    w = max(len(t) for t in c["truth"]) + 2
    lines = ["truth \\ answer".ljust(w) + " ".join(f"{short[a]:>11s}" for a in c["answer"])]
    for t in c["truth"]:
        lines.append(t.ljust(w) + " ".join(f"{(c['matrix'][t][a] or '.'):>11}" for a in c["answer"]))
    return "\n".join(lines)


def run(n_library: int, n_outside: int, throws: int, seed: int, policy: Path, workers: int, out: Path | None, keep_data: Path | None = None) -> dict:
    """The whole benchmark; writes ``out`` (JSON) and ``out`` with .txt (summary + confusion)."""
    cases = draw_cases(n_library, n_outside, seed)
    t0 = time.time()
    rows = []
    with tempfile.TemporaryDirectory(prefix="slinger-bench-") as tmp:
        work = keep_data or Path(tmp)
        for i, case in enumerate(cases):
            rows.append(run_case(case, throws, policy, workers, work))
            log.info("benchmark: %d/%d cases (%.0f s)", i + 1, len(cases), time.time() - t0)
    summary = summarise(rows)
    result = {"format": "slinger-diagnosis-benchmark/1", "seed": seed, "throws_per_case": throws, "policy": str(policy),
              "wall_s": time.time() - t0, "summary": summary, "cases": rows}
    text = format_summary(result)
    print(text, flush=True)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1) + "\n")
        out.with_suffix(".txt").write_text(text + "\n")
    return result


def format_summary(result: dict) -> str:
    s = result["summary"]

    def pct(x):
        return "n/a" if x is None else f"{100 * x:.0f}%"

    lines = [
        (f"Blind diagnosis benchmark: {s['cases']} cases ({s['library_cases']} library, {s['outside_cases']} outside), "
         f"{result['throws_per_case']} throws each, seed {result['seed']}, {result['wall_s'] / 60:.1f} min"),
        f"  named correctly (library):               {pct(s['named_correctly'])}",
        f"  parameter within ±{100 * s['tolerance']:.0f}% of truth:          {pct(s['param_within_tolerance'])}",
        (f"  held-out impact gap shrink when named:   mean {pct(s['impact_gap_shrink_mean'])}, min {pct(s['impact_gap_shrink_min'])}, "
         f">=70% in {pct(s['impact_gap_shrink_cases_ge_70pct'])} of {s['impact_gap_cases']} cases with an impact gap"),
        f"  outside the library -> unexplained:      {pct(s['outside_unexplained'])}",
        "",
        confusion_text(s),
    ]
    return "\n".join(lines)
