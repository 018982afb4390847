"""The diagnosis' verdict in words and as data, from the where and the selection rounds."""

from __future__ import annotations

from sim_twin.diagnosis import forward as fw
from sim_twin.effects import Effect, effect_class

SEPARATING = {
    "release": "log the gripper's payload-free (open) flag: it measures the release timing directly",
    "flight": "track the payload in flight (/payload): it shows the flight path itself",
    "payload": "track the payload while held (/payload): it shows where it sits in the gripper",
    "measurement": "check the sensors against an independent reference (e.g. a total station on the gripper)",
    "dynamics": "log more throws over a wider range of targets and poses: the two act differently on the swing",
}


def separating_measurement(a: str, b: str) -> str:
    """What measurement would tell effect ``a`` from ``b`` (by their stages and footprints)."""
    ca, cb = effect_class(a), effect_class(b)
    stages = [s for s in (ca.stage, cb.stage)]
    for s in stages:
        if s != "dynamics" and stages[0] != stages[1]:
            return SEPARATING[s]
    if ca.stage == cb.stage and ca.stage != "dynamics":
        return SEPARATING[ca.stage] + " (both act there)"
    if set(ca.groups()) != set(cb.groups()):
        return f"compare {'/'.join(ca.groups())} with {'/'.join(cb.groups())} channels on more throws"
    return SEPARATING["dynamics"]


def _fmt_params(c: fw.Candidate) -> str:
    return ", ".join(f"{k} = {v:.4g} ± {c.sigma[k]:.2g}" for k, v in c.params.items() if k in c.sigma)


def verdict_of(where: dict, rounds: list[fw.Round], named: list[Effect]) -> dict:
    """{"answer": named | ambiguous | unexplained | no_gap, "effects": [...], "where": [...],
    "text": ..., "evidence": {...}}."""
    carriers = where["carriers"]
    where_txt = ", ".join(carriers[:4]) + (" …" if len(carriers) > 4 else "")
    phases = [p for p, s in sorted(where.get("phases", {}).items(), key=lambda kv: -kv[1]) if s >= 0.1]
    if not where["gap"]:
        return {"answer": "no_gap", "effects": [], "where": [], "text": "no gap: every channel matches the nominal twin within its measured noise",
                "evidence": {}}
    named_c = []
    for r in rounds:
        if r.decision == "named":
            named_c.append(next(c for c in r.candidates if c.effect == r.named))
    last = rounds[-1]
    remaining = last.gaps if last.decision != "no gap left" else []
    evidence = {
        "named": [{"effect": c.effect, "params": c.params, "sigma": c.sigma, "sigma_parts": c.sigma_parts, "refit": c.refit, "wins": c.wins, "beats_none": c.beats_none} for c in named_c],
        "last_round": {"decision": last.decision, "wins_none": last.wins_none,
                       "candidates": [{"effect": c.effect, "wins": c.wins, "admissible": c.admissible, "reason": c.reason,
                                       "at_bound": c.at_bound, "worse": list(c.worse)} for c in last.candidates]},
        "at_bound": [{"effect": c.effect, "params": c.at_bound} for r in rounds for c in r.candidates if c.at_bound],
    }
    names_txt = " + ".join(f"{c.effect} ({_fmt_params(c)}; wins {100 * c.wins:.0f}% of resamples)" for c in named_c)
    if last.decision == "ambiguous":
        meas = separating_measurement(last.named, last.runner_up)
        a = next(c for c in last.candidates if c.effect == last.named)
        b = next(c for c in last.candidates if c.effect == last.runner_up)
        pre = f"{names_txt}; then " if named_c else ""
        return {"answer": "ambiguous", "effects": [c.effect for c in named_c], "between": [a.effect, b.effect], "where": carriers,
                "measurement": meas, "evidence": evidence,
                "text": (f"{pre}ambiguous between {a.effect} (wins {100 * a.wins:.0f}%) and {b.effect} (wins {100 * b.wins:.0f}%) "
                         f"for the gap in {where_txt}; to separate them: {meas}")}
    if named_c and not remaining:
        return {"answer": "named", "effects": [c.effect for c in named_c], "where": carriers, "evidence": evidence,
                "text": f"{names_txt} explain{'s' if len(named_c) == 1 else ''} the gap in {where_txt} to within noise"}
    why = last.decision
    part = f"partly explained by {names_txt}; " if named_c else ""
    rem = ", ".join(remaining[:4]) if remaining else where_txt
    return {"answer": "unexplained", "effects": [c.effect for c in named_c], "partial": bool(named_c), "where": remaining or carriers,
            "phases": phases, "evidence": evidence,
            "text": f"{part}unexplained gap in {rem} ({', '.join(phases) or 'all phases'}): {why}"}
