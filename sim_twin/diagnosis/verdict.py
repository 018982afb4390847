"""The diagnosis' verdict in words and as data, from the where and the selection rounds.

Verdict classes (``answer``; docs/diagnosis.md says how to read each):

* ``named``: every named effect explains the gap and channels other than the impact confirm it
  (:func:`forward.evidence_of`);
* ``consistent``: an effect fits, but its only evidence is the measured impact, which other
  candidates and causes outside the library (a bias of the impact measurement, a target survey
  error, a payload held off-centre) would shift alike: "consistent with X, not confirmed", with
  the alternatives and the measurement that would separate them;
* ``ambiguous``: two candidates explain the gap about equally often;
* ``unexplained``: no candidate (or set) explains the gap;
* ``no_gap``: no channel differs from the nominal twin beyond noise, neither in its chi-square
  nor in its mean; with the smallest effects these throws could have shown (:mod:`power`).
"""

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


OUTSIDE_IMPACT = ("a bias of the impact measurement (camera or survey calibration)", "a target survey error",
                  "a payload held off-centre in the gripper (sideways)")
"""Causes outside the library that move only the measured impact (named in every "consistent" verdict)."""
IMPACT_CHECKS = (
    "a survey mark under the gripper at a stand-still release (checks the impact measurement and the target survey)",
    ("throws at another distance and cabin angle (a measurement bias stays put in the site frame; release, flight and "
     "calibration effects grow with the distance and turn with the cabin)"),
    "a camera check of where the payload sits in the gripper",
)


def _fmt_params(c: fw.Candidate) -> str:
    return ", ".join(f"{k} = {v:.4g} ± {c.sigma[k]:.2g}" for k, v in c.params.items() if k in c.sigma)


def alternatives_of(rnd: fw.Round, effect: str) -> list[str]:
    """Other candidates of the round that also explain the impact: they beat "no effect" on the
    left-out throws of at least half the resamples and are not ruled out for removing too little."""
    return [c.effect for c in rnd.candidates if c.effect != effect and c.beats_none >= 0.5 and "removes only" not in c.reason]


def _consistent_note(c: fw.Candidate, rnd: fw.Round) -> dict:
    alts = alternatives_of(rnd, c.effect)
    if c.effect != "impact_bias" and "impact_bias" not in alts:
        alts.append("impact_bias")
    meas = list(IMPACT_CHECKS)
    stage = effect_class(c.effect).stage
    if stage in SEPARATING and stage != "measurement":
        meas.append(SEPARATING[stage])
    return {"effect": c.effect, "alternatives": alts, "outside": list(OUTSIDE_IMPACT), "measurements": meas,
            "changes": c.evidence.get("changes", {}), "impact_drop": c.evidence.get("impact_drop"),
            "trajectory_drop": c.evidence.get("trajectory_drop")}


def verdict_of(where: dict, rounds: list[fw.Round], named: list[Effect], power: dict | None = None) -> dict:
    """{"answer": named | consistent | ambiguous | unexplained | no_gap, "effects": [...],
    "confirmed": [...], "not_confirmed": [{effect, alternatives, outside, measurements, ...}],
    "where": [...], "text": ..., "evidence": {...}} (module doc; ``power``: :func:`power.detectable`
    result, quoted in a "no gap")."""
    carriers = where["carriers"]
    where_txt = ", ".join(carriers[:4]) + (" …" if len(carriers) > 4 else "")
    phases = [p for p, s in sorted(where.get("phases", {}).items(), key=lambda kv: -kv[1]) if s >= 0.1]
    if not where["gap"]:
        text = "no gap: every channel matches the nominal twin within its measured noise, in its chi-square and in its mean"
        if power and power.get("text"):
            text += f"; {power['text']}"
        return {"answer": "no_gap", "effects": [], "where": [], "text": text, "evidence": {}, "power": power}
    named_c, named_r = [], []
    for r in rounds:
        if r.decision == "named":
            named_c.append(next(c for c in r.candidates if c.effect == r.named))
            named_r.append(r)
    last = rounds[-1]
    remaining = last.gaps if last.decision != "no gap left" else []
    evidence = {
        "named": [{"effect": c.effect, "params": c.params, "sigma": c.sigma, "sigma_parts": c.sigma_parts, "refit": c.refit, "wins": c.wins,
                   "beats_none": c.beats_none, "identifiability": c.evidence} for c in named_c],
        "last_round": {"decision": last.decision, "wins_none": last.wins_none,
                       "candidates": [{"effect": c.effect, "wins": c.wins, "admissible": c.admissible, "reason": c.reason,
                                       "at_bound": c.at_bound, "worse": list(c.worse), "identifiability": c.evidence} for c in last.candidates]},
        "at_bound": [{"effect": c.effect, "params": c.at_bound} for r in rounds for c in r.candidates if c.at_bound],
    }
    confirmed = [c.effect for c in named_c if not c.evidence.get("impact_only", False)]
    not_conf = [_consistent_note(c, r) for c, r in zip(named_c, named_r) if c.evidence.get("impact_only", False)]
    base = {"effects": [c.effect for c in named_c], "confirmed": confirmed, "not_confirmed": not_conf, "evidence": evidence, "power": power}

    def one(c: fw.Candidate) -> str:
        tag = "" if c.effect in confirmed else ", not confirmed"
        return f"{c.effect} ({_fmt_params(c)}; wins {100 * c.wins:.0f}% of resamples{tag})"

    names_txt = " + ".join(one(c) for c in named_c)
    if last.decision == "ambiguous":
        if last.named is None or last.runner_up is None:
            raise RuntimeError("an ambiguous round without both its leading effects")
        meas = separating_measurement(last.named, last.runner_up)
        a = next(c for c in last.candidates if c.effect == last.named)
        b = next(c for c in last.candidates if c.effect == last.runner_up)
        pre = f"{names_txt}; then " if named_c else ""
        if a.evidence.get("impact_only") and b.evidence.get("impact_only"):
            meas = f"{meas}; or {IMPACT_CHECKS[1]}"
        return {**base, "answer": "ambiguous", "between": [a.effect, b.effect], "where": carriers, "measurement": meas,
                "text": (f"{pre}ambiguous between {a.effect} (wins {100 * a.wins:.0f}%) and {b.effect} (wins {100 * b.wins:.0f}%) "
                         f"for the gap in {where_txt}; to separate them: {meas}")}
    if named_c and not remaining and not not_conf:
        return {**base, "answer": "named", "where": carriers,
                "text": (f"{names_txt} explain{'s' if len(named_c) == 1 else ''} the gap in {where_txt} to within noise, "
                         f"confirmed by {', '.join(sorted({g for c in named_c for g in c.evidence.get('confirmed_by', [])}))} channels")}
    if named_c and not remaining:
        parts = []
        for n in not_conf:
            parts.append(f"{n['effect']} is consistent with the impacts but not confirmed: no joint, IMU or payload channel changes with it, "
                         f"and {', '.join(n['alternatives'])} or causes outside the library ({'; '.join(n['outside'])}) would shift the impacts alike; "
                         f"to separate them: {'; '.join(n['measurements'])}")
        conf_txt = f"{' + '.join(one(c) for c in named_c if c.effect in confirmed)} confirmed; " if confirmed else ""
        return {**base, "answer": "consistent", "where": carriers,
                "text": f"gap in {where_txt}: {conf_txt}consistent with {' + '.join(one(c) for c in named_c if c.effect not in confirmed)}. " + " ".join(parts)}
    why = last.decision
    part = f"partly explained by {names_txt}; " if named_c else ""
    rem = ", ".join(remaining[:4]) if remaining else where_txt
    return {**base, "answer": "unexplained", "partial": bool(named_c), "where": remaining or carriers, "phases": phases,
            "text": f"{part}unexplained gap in {rem} ({', '.join(phases) or 'all phases'}): {why}"}
