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
* ``drifting``: the gap is not the same early and late in the log (:mod:`stationarity`: a change
  in a channel's per-throw residuals, before or after the fit, or a named effect whose fits on
  the two halves of the log disagree): where, since which throw, how fast; nothing is fitted as
  a constant effect and nothing is offered for adaptation;
* ``no_gap``: no channel differs from the nominal twin beyond noise, neither in its chi-square
  nor in its mean; with the smallest effects these throws could have shown (:mod:`power`).

"Confirmed" means the same for a part of an answer as for the whole (:func:`confirmation`): a
named effect is confirmed only if channels other than the impact confirm it, it won WIN_FREQ of
the resamples against every other candidate and against "no further effect", no parameter sits
at a prior bound, it makes no channel worse, and the residual it leaves is consistent across
the throws (none of the channels it changes keeps a gap, nor do the channels of a joint it is
fitted to: :func:`fitted_joint_channels`; its residual does not change during the log, its fits
on the two halves of the log agree). Otherwise it is "partly consistent with X", never
confirmed.
"""

from __future__ import annotations

from sim_twin.diagnosis import forward as fw
from sim_twin.diagnosis import noise as nz
from sim_twin.diagnosis import select as sel
from sim_twin.diagnosis import stationarity as st
from sim_twin.twin.effects import Effect, PerJointEffect, effect_class

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


IMPACT_CHANNELS = ("impact.downrange", "impact.crossrange")


MOVED_SIGMA = 2.0
"""A per-joint parameter counts as fitted to its joint when its fit lies more than this many of its
standard errors (``Candidate.sigma``) from the nominal (:func:`fitted_joint_channels`)."""


def fitted_joint_channels(c: fw.Candidate) -> dict[str, list[str]]:
    """The joints a per-joint candidate is fitted to, with their own channels.

    A per-joint effect (:class:`sim_twin.twin.effects.PerJointEffect`: an encoder offset, a valve
    lag per joint) names the joints whose parameter its fit moved from the nominal by more than
    MOVED_SIGMA standard errors. Such a part claims something about that joint (recalibrate the
    boom's encoder, service the boom's valve), so it explains the gap only if the joint's own
    channels (``q.<joint>``, ``qd.<joint>``) keep no gap with it in the twin, whether or not the
    fit changed them: a non-separable effect such as an encoder offset may act only through the
    shared channels (the gripper's swing, the impact) and leave its joint's channels untouched.

    Returns:
        {joint: [its channels in :data:`noise.CHANNELS`]}; {} for an effect that is not per joint,
        is not resolvable by name, or whose fit left every joint nominal.
    """
    try:
        cls = effect_class(c.effect)
    except ValueError:
        return {}
    if not issubclass(cls, PerJointEffect):
        return {}
    nominal = {p.name: p.nominal for p in cls.params}
    out: dict[str, list[str]] = {}
    for j in cls.joints:
        name = f"{cls.joint_base}_{j}"
        if name not in c.params or name in c.not_identifiable or name not in nominal:
            continue
        if abs(c.params[name] - nominal[name]) > MOVED_SIGMA * max(c.sigma.get(name, 0.0), 0.0):
            out[j] = [ch for ch in (f"q.{j}", f"qd.{j}") if ch in nz.CH_INDEX]
    return out


def confirmation(c: fw.Candidate, remaining: list[str], drift: dict | None = None) -> list[str]:
    """Why named candidate ``c`` is not confirmed (empty: confirmed; module doc).

    Args:
        c: a named candidate (its evidence from :func:`forward.evidence_of`, ``wins_all`` and
            ``split`` from :func:`forward.select_effects` / :func:`forward.split_fits`).
        remaining: the channels that keep a gap once every named effect is in the twin; a part
            is not confirmed while one of them is a channel it changes or a channel of a joint
            it is fitted to (:func:`fitted_joint_channels`).
        drift: :func:`drift_of` (its ``after_fit`` channels that change during the log), or None.
    """
    why = []
    ev = c.evidence
    if ev.get("impact_only", False):
        why.append("no joint, IMU or payload channel changes with it")
    wins = ev.get("wins_all", c.wins)
    if wins < sel.WIN_FREQ:
        why.append(f"wins only {100 * wins:.0f}% of resamples against every other candidate and no further effect")
    if c.at_bound:
        why.append(f"at its prior bound ({', '.join(c.at_bound)})")
    if c.worse and not c.pair_with:
        why.append(f"makes {', '.join(c.worse)} worse beyond noise")
    own = sorted(ch for ch, d in ev.get("changes", {}).items() if d > 0 and ch not in IMPACT_CHANNELS)
    left = [ch for ch in own if ch in remaining]
    if left:
        why.append(f"leaves a gap in channels it changes ({', '.join(left)}): its residual is not noise")
    for j, chs in fitted_joint_channels(c).items():
        chs = [ch for ch in chs if ch in remaining and ch not in left]
        if chs:
            why.append(f"leaves the gap in {', '.join(chs)} unexplained, the channels of the {j} it is fitted to: "
                       f"something else acts on the {j}, and this part cannot be told from it")
    split = ev.get("split") or {}
    if split.get("drifting"):
        zs = split.get("z", {})
        n = max(zs, key=lambda k: abs(zs[k]))
        why.append(f"its fits on the early and the late half of the log disagree ({n}: {split['early'][n]:.4g} -> {split['late'][n]:.4g}, z = {zs[n]:.1f})")
    moving = [ch for ch in own if ch in ((drift or {}).get("after_fit") or [])]
    if moving:
        why.append(f"the residual it leaves changes during the log in {', '.join(moving)}")
    return why


def drift_of(nominal: dict | None, after_fit: dict | None, named_c: list[fw.Candidate], throw_ids: list[str]) -> dict:
    """The stationarity findings of one diagnosis (:mod:`stationarity`).

    Args:
        nominal / after_fit: :func:`stationarity.test_series` of the per-throw mean residuals of
            the nominal twin / of the twin with the named effects (None: not tested), each with
            its channels' combined test under :data:`stationarity.COMBINED`. The combined rows
            decide: they are Holm-corrected here together, in place (:func:`stationarity.holm`),
            so the decision has one family-wise false-alarm rate, ALPHA. The channels' own rows
            only describe.
        named_c: the named candidates (their ``split`` evidence).
        throw_ids: the throws in log order.

    Returns:
        {"drifting": bool, "together": [the combined rows that change], "channels": {channel:
        its shape at the change} (the channels of those rows), "nominal", "after_fit": [the
        channels that change, by family], "split": {effect: split fits} of the named effects
        whose halves disagree, "since": the throw id after the most significant change, "text":
        one sentence}.
    """
    fams = {"nominal": nominal or {}, "after_fit": after_fit or {}}
    combined = {fam: src[st.COMBINED] for fam, src in fams.items() if st.COMBINED in src}
    st.holm(combined.values())
    together = sorted((r for r in combined.values() if r["drifting"]), key=lambda r: r["p_holm"])
    rows: dict[str, dict] = {}
    for r in reversed(together):  # the most significant last, so its shapes win
        rows.update({ch: {**r["shapes"][ch], "n": r["n"], "p_holm": r["p_holm"]} for ch in r["channels"]})
    split = {c.effect: c.evidence["split"] for c in named_c if (c.evidence.get("split") or {}).get("drifting")}
    out: dict = {"drifting": bool(together or split), "together": together, "channels": rows,
                 **{fam: sorted(combined[fam]["channels"]) if fam in combined and combined[fam]["drifting"] else [] for fam in fams},
                 "split": split, "since": None, "text": ""}
    if not out["drifting"]:
        return out
    parts = st.describe_combined(together[0], throw_ids) if together else []
    if together:
        k = together[0]["change_at"]
        out["since"] = throw_ids[k] if k is not None and k < len(throw_ids) else None
    for e, sp in split.items():
        n = max(sp["z"], key=lambda k: abs(sp["z"][k]))
        parts.append(f"{e} fitted on the first {sp['halves']} throws gives {n} = {sp['early'][n]:.4g}, on the last {sp['halves']} "
                     f"{sp['late'][n]:.4g} (z = {sp['z'][n]:.1f})")
    out["text"] = "; ".join(parts)
    return out


def _within_noise(rounds: list[fw.Round]) -> list[str]:
    """Channels whose chi-square still exceeds their noise (plain test) with every named effect in
    the twin (the last round's base), most excess first; [] when every channel is within noise."""
    res = rounds[-1].residual if rounds else {}
    return sorted((ch for ch, r in res.items() if r.get("gap")), key=lambda ch: -res[ch]["chi2"] / max(res[ch]["dof"], 1e-9))


def _impact_only_listed(last: fw.Round, named: set[str]) -> list[fw.Candidate]:
    """Impact-only candidates of the last round that explain a gap left only in the impact: they
    beat "no further effect" in at least half the resamples, remove enough of the gap and sit at no
    prior bound (best first)."""
    out = [c for c in last.candidates if c.effect not in named and c.evidence.get("impact_only", False) and c.beats_none >= 0.5
           and "removes only" not in c.reason and not c.at_bound and not c.worse]
    return sorted(out, key=lambda c: -c.beats_none)


def verdict_of(where: dict, rounds: list[fw.Round], named: list[Effect], power: dict | None = None, drift: dict | None = None) -> dict:
    """{"answer": named | consistent | ambiguous | unexplained | drifting | no_gap, "effects": [...],
    "confirmed": [...], "not_confirmed": [{effect, alternatives, outside, measurements, ...}],
    "partly_consistent": [{effect, why}], "where": [...], "text": ..., "evidence": {...}}
    (module doc; ``power``: :func:`power.detectable` result, quoted in a "no gap"; ``drift``:
    :func:`drift_of`)."""
    carriers = where["carriers"]
    where_txt = ", ".join(carriers[:4]) + (" …" if len(carriers) > 4 else "")
    phases = [p for p, s in sorted(where.get("phases", {}).items(), key=lambda kv: -kv[1]) if s >= 0.1]
    named_c, named_r = [], []
    for r in rounds:
        if r.decision == "named":
            named_c.append(next(c for c in r.candidates if c.effect == r.named))
            named_r.append(r)
    evidence: dict = {}
    if rounds:
        last = rounds[-1]
        evidence = {
            "named": [{"effect": c.effect, "params": c.params, "sigma": c.sigma, "sigma_parts": c.sigma_parts, "refit": c.refit, "wins": c.wins,
                       "beats_none": c.beats_none, "identifiability": c.evidence} for c in named_c],
            "last_round": {"decision": last.decision, "wins_none": last.wins_none,
                           "candidates": [{"effect": c.effect, "wins": c.wins, "admissible": c.admissible, "reason": c.reason,
                                           "at_bound": c.at_bound, "worse": list(c.worse), "identifiability": c.evidence} for c in last.candidates]},
            "at_bound": [{"effect": c.effect, "params": c.at_bound} for r in rounds for c in r.candidates if c.at_bound],
        }
    if drift and drift.get("drifting"):
        return {"answer": "drifting", "effects": [], "confirmed": [], "not_confirmed": [], "partly_consistent": [], "evidence": evidence,
                "power": None, "drift": drift, "since": drift.get("since"),
                "where": sorted(drift["channels"]) or carriers,
                "text": (f"drifting gap: the throws early and late in the log differ: {drift['text']}. Not fitted as a constant effect: "
                         "diagnose the throws since the change on their own, and look for what changed at that throw")}
    if not where["gap"]:
        text = "no gap: every channel matches the nominal twin within its measured noise, in its chi-square and in its mean"
        if power and power.get("text"):
            text += f"; {power['text']}"
        return {"answer": "no_gap", "effects": [], "where": [], "text": text, "evidence": {}, "power": power, "drift": drift}
    last = rounds[-1]
    remaining = last.gaps if last.decision != "no gap left" else []
    why = {c.effect: confirmation(c, remaining, drift) for c in named_c}
    confirmed = [c.effect for c in named_c if not why[c.effect]]
    not_conf = [_consistent_note(c, r) for c, r in zip(named_c, named_r) if c.evidence.get("impact_only", False)]
    partly = [{"effect": c.effect, "why": why[c.effect]} for c in named_c if why[c.effect] and not c.evidence.get("impact_only", False)]
    listed: list[fw.Candidate] = []
    if remaining and all(ch in IMPACT_CHANNELS for ch in remaining) and last.decision not in ("named", "ambiguous"):
        listed = _impact_only_listed(last, {c.effect for c in named_c})
        if listed:
            note = _consistent_note(listed[0], last)
            note["alternatives"] = [c.effect for c in listed[1:]] + [a for a in note["alternatives"] if a not in {c.effect for c in listed}]
            not_conf.append(note)
    base = {"effects": [c.effect for c in named_c], "confirmed": confirmed, "not_confirmed": not_conf, "partly_consistent": partly,
            "evidence": evidence, "power": power, "drift": drift}

    def one(c: fw.Candidate) -> str:
        tag = "" if c.effect in confirmed else ", not confirmed"
        return f"{c.effect} ({_fmt_params(c)}; wins {100 * c.wins:.0f}% of resamples{tag})"

    def part_txt(c: fw.Candidate) -> str:
        return f"{one(c)}: {'; '.join(why[c.effect])}"

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
    if named_c and not remaining and not not_conf and not partly:
        rest = _within_noise(rounds)
        how = ("to within noise" if not rest else
               "; a rest beyond noise stays in " + ", ".join(f"{ch} (chi-square {rounds[-1].residual[ch]['chi2'] / rounds[-1].residual[ch]['dof']:.1f} "
                                                             f"times its degrees of freedom)" for ch in rest[:3]))
        return {**base, "answer": "named", "where": carriers, "rest_beyond_noise": rest,
                "text": (f"{names_txt} explain{'s' if len(named_c) == 1 else ''} the gap in {where_txt} {how}, "
                         f"confirmed by {', '.join(sorted({g for c in named_c for g in c.evidence.get('confirmed_by', [])}))} channels")}
    if (named_c or listed) and (not remaining or listed):
        parts = []
        for n in not_conf:
            parts.append(f"{n['effect']} is consistent with the impacts but not confirmed: no joint, IMU or payload channel changes with it, "
                         f"and {', '.join(n['alternatives'])} or causes outside the library ({'; '.join(n['outside'])}) would shift the impacts alike; "
                         f"to separate them: {'; '.join(n['measurements'])}")
        conf_txt = f"{' + '.join(one(c) for c in named_c if c.effect in confirmed)} confirmed; " if confirmed else ""
        partly_txt = "".join(f"partly consistent with {part_txt(c)}; " for c in named_c if why[c.effect] and not c.evidence.get("impact_only", False))
        cons = [one(c) for c in named_c if c.evidence.get("impact_only", False)]
        cons += [f"{c.effect} (beats no further effect in {100 * c.beats_none:.0f}% of resamples, not confirmed)" for c in listed[:1]]
        return {**base, "answer": "consistent", "where": carriers,
                "text": f"gap in {where_txt}: {conf_txt}{partly_txt}" + (f"consistent with {' + '.join(cons)}. " if cons else "") + " ".join(parts)}
    reason = last.decision
    part = ""
    if named_c:
        conf_part = [one(c) for c in named_c if c.effect in confirmed]
        part = (f"partly explained by {' + '.join(conf_part)} (confirmed); " if conf_part else "")
        part += "".join(f"partly consistent with {part_txt(c)}; " for c in named_c if c.effect not in confirmed)
    rem = ", ".join(remaining[:4]) if remaining else where_txt
    return {**base, "answer": "unexplained", "partial": bool(named_c), "where": remaining or carriers, "phases": phases,
            "text": f"{part}unexplained gap in {rem} ({', '.join(phases) or 'all phases'}): {reason}"}
