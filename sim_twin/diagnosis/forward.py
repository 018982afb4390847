"""Forward selection of effects with bootstrap evidence (see :mod:`select` for the method).

:func:`select_effects` runs the rounds and returns the verdict's raw material: per round the
candidates with their fits, flags and win frequencies, the named effects, and why it stopped.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field

import numpy as np

from sim_twin.diagnosis import noise as nz
from sim_twin.diagnosis import select as sel
from sim_twin.diagnosis import stationarity as st
from sim_twin.twin.effects import Effect

log = logging.getLogger(__name__)

SWING_Z = 3.0  # excess z-score in the swing phase that lets a dynamics candidate in
CONFIRM_CHI2 = 25.0
"""A candidate is confirmed by channels other than the impact when its fit lowers their summed
chi-square by at least this much (a 5 sigma likelihood-ratio for one parameter; CHOSEN like
noise.Z_GAP). Below it the candidate's only evidence is the measured impact."""
Z_SPLIT = 4.0
"""A candidate's fits on the early and the late half of the log (throw order) disagree when they
differ by more than this many standard deviations of the difference (each half's 1 sigma taken
as sqrt(2) times the all-throw one; CHOSEN: about 3.3 sigma two-sided after a Bonferroni
correction over a handful of parameters, rounded up because the all-throw sigma is the largest
of several estimates)."""


@dataclass
class Candidate:
    """One candidate in one round (parameters in physical units)."""

    effect: str
    params: dict[str, float]
    sigma: dict[str, float]
    k: int
    at_bound: list[str]
    worse: dict[str, float]
    not_identifiable: list[str]
    params_train: dict[str, float]
    chi2_before: float
    chi2_after: float
    test_excess_before: float
    test_excess_after: float
    wins: float = 0.0
    beats_none: float = 0.0
    admissible: bool = False
    reason: str = ""
    wall_s: float = 0.0
    refit: bool = False
    sigma_parts: dict = field(default_factory=dict)
    pair_with: str = ""
    joint_gain: dict = field(default_factory=dict)  # non-separable per-joint effects: training chi-square each joint's coarse fit removed
    wins_admissible: float | None = None  # wins among the admissible candidates when the leader was not admissible
    evidence: dict = field(default_factory=dict)  # identifiability: which channels the fit changes and which confirm it (:func:`evidence_of`)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Round:
    gaps: list[str]
    candidates: list[Candidate] = field(default_factory=list)
    gated_out: dict[str, str] = field(default_factory=dict)
    wins_none: float = 0.0
    decision: str = ""
    named: str | None = None
    runner_up: str | None = None
    pair_tried: list[Candidate] = field(default_factory=list)  # second effects tried by the pair step (none named)
    residual: dict = field(default_factory=dict)
    """channel -> {"chi2", "dof", "gap"} of the round's base (the effects named before it) over all
    throws, with the plain noise test (:func:`noise.gap_test`, no RESIDUAL_SHARE rule): what
    "to within noise" is judged on."""

    def to_dict(self) -> dict:
        return {"gaps": self.gaps, "candidates": [c.to_dict() for c in self.candidates], "gated_out": self.gated_out,
                "wins_none": self.wins_none, "decision": self.decision, "named": self.named, "runner_up": self.runner_up,
                "pair_tried": [c.to_dict() for c in self.pair_tried], "residual": self.residual}


def channel_gaps(S: np.ndarray, D: np.ndarray, S_ref: np.ndarray | None = None, M: np.ndarray | None = None,
                 margin: np.ndarray | None = None) -> dict[str, dict]:
    """Channels (summed over throws and phases) with a gap: name -> {S, D, z, z_phase, phases:
    [phases with a gap of their own], kind: "excess" | "bias" | "excess+bias", bias: the bias
    test or None}. With ``S_ref`` (the nominal twin's), a trajectory channel whose excess is
    below RESIDUAL_SHARE of its nominal excess counts as explained. Impact channels keep the
    plain noise test: they carry one degree of freedom per throw (no statistically visible rest
    of a precise fit as on hundreds of trajectory blocks) and are the only place a release- or
    flight-stage effect shows, so a second effect there (e.g. a release delay beside passive
    friction) stays visible. With ``M`` (N, C) (:meth:`scoring.Scorer.signed`) a channel whose
    mean residual fails the bias test (:func:`noise.bias_tests`, Holm over the channels) has a
    gap too, though its chi-square excess is below the threshold (a small systematic shift);
    ``margin`` (N, C) is the bias tests' immaterial mean (:attr:`scoring.Scorer.bias_margin`;
    None: 0). A trajectory channel explained by the RESIDUAL_SHARE rule stays explained."""
    Sc, Dc = S.sum(axis=0), D.sum(axis=0)
    ref = None if S_ref is None else S_ref.sum(axis=(0, 2))
    bias = nz.bias_tests(M, D, margin=margin) if M is not None else {}
    out = {}
    for c, name in enumerate(nz.CHANNELS):
        gap, z = nz.gap_test(Sc[c].sum(), Dc[c].sum())
        b = bias.get(name)
        biased = bool(b and b["bias"])
        if ref is not None and nz.group_of(name) != "impact" and Sc[c].sum() - Dc[c].sum() < sel.RESIDUAL_SHARE * (ref[c] - Dc[c].sum()):
            # explained: the rest of a precise fit on hundreds of blocks; its mean is as visible
            # (the per-throw mean of ~100 rows shows a sub-noise systematic rest), so the bias
            # test does not reopen it
            gap = biased = False
        if gap or biased:
            zp = {nz.PHASES[p]: nz.gap_test(Sc[c, p], Dc[c, p])[1] for p in range(len(nz.PHASES)) if Dc[c, p] > 0}
            out[name] = {"S": float(Sc[c].sum()), "D": float(Dc[c].sum()), "z": z, "z_phase": zp,
                         "phases": [nz.PHASES[p] for p in range(len(nz.PHASES)) if nz.gap_test(Sc[c, p], Dc[c, p])[0]],
                         "kind": "excess+bias" if gap and biased else "excess" if gap else "bias", "bias": b}
    return out


def gated(cls: type[Effect], gaps: dict[str, dict]) -> str | None:
    """None if the candidate can act where the gap is, else why not (its stage and footprint
    against the where): it must act on a channel group with a gap, and a dynamics effect, which
    changes the swing first, needs a gap in the swing phase of its trajectory channels."""
    groups = set(cls.groups())
    hit = [c for c in gaps if nz.group_of(c) in groups]
    if not hit:
        return f"acts on {sorted(groups)}; the gap is in {sorted({nz.group_of(c) for c in gaps})}"
    traj = [c for c in hit if nz.group_of(c) in ("active", "passive")]
    if cls.stage == "dynamics" and traj and not any(gaps[c]["z_phase"].get("swing", 0.0) > SWING_Z or gaps[c].get("kind") == "bias" for c in traj):
        return "a dynamics effect changes the swing first; its channels match in the swing"
    return None


def bootstrap_weights(N: int, seed: int) -> np.ndarray:
    """(select.BOOTSTRAP, N) throw weights of the bootstrap resamples (counts of each throw in
    a draw of N with replacement; seeded)."""
    rng = np.random.default_rng(seed)
    return np.stack([np.bincount(rng.integers(0, N, N), minlength=N) for _ in range(sel.BOOTSTRAP)]).astype(float)


def _profile_sigmas(sw: sel.Sweep, S_fit: np.ndarray, D: np.ndarray, fitted: list[str], span: dict[str, float]) -> dict[str, float]:
    """Likelihood-profile 1 sigma (physical units) of each fitted parameter from the all-throw
    chi-square on the grid (per-joint effects: each joint's own channels), scaled by the Birge
    ratio sqrt(chi2 / dof) of the fit when that exceeds 1 (a misfit the noise does not
    explain widens the interval instead of being ignored)."""
    has_dof = D.sum(axis=(0, 2)) > 0
    birge = float(np.sqrt(max(1.0, S_fit[:, has_dof].sum() / D.sum())))
    if sw.joints is None:
        ps = sel.profile_sigma(sw.X, sw.S.sum(axis=(1, 2, 3)))
        out = {n: float(ps[i] * span[n] * birge) for i, n in enumerate(sw.names) if n in fitted}
    else:
        out = {n: float(v * birge) for n, v in _per_joint(sw, fitted, span, lambda X, S: sel.profile_sigma(X, S.sum(axis=(1, 2, 3)))[0]).items()}
    for n in sw.polished:  # polished fits: the profile interval itself (chi-square up by Birge^2), not the local quadratic
        if n not in fitted:
            continue
        if sw.joints is None:
            X, T = sw.X, sw.S.sum(axis=(1, 2, 3))
        else:
            X, S = sw.grid_of(n)
            T = S[:, :, dict(sw.joints)[n]].sum(axis=(1, 2, 3))
        iv = sel.profile_interval(X, T, rise=birge**2)
        if iv is not None:
            # with how well the optimiser bracketed the minimum (it lies between the best point's
            # evaluated neighbours; a quarter of that bracket) and the local fit's shift from the best point
            xs = np.sort(X[:, 0])
            xb = float(X[int(np.argmin(T)), 0])
            bracket = float(xs[xs > xb].min(initial=1.0) - xs[xs < xb].max(initial=0.0)) / 4
            shift = abs(float(sel.local_fit(X, T)[0][0]) - xb)
            out[n] = float(np.sqrt(((iv[1] - iv[0]) / 2) ** 2 + bracket**2 + shift**2) * span[n])
    return {n: out.get(n, np.inf) for n in fitted}


def _per_joint(sw: sel.Sweep, fitted: list[str], span: dict[str, float], sigma_of) -> dict[str, float]:
    """Per-joint sweeps: ``sigma_of(X, S_joint)`` (normalised units) of each fitted joint from its
    own channels on its grid (:meth:`select.Sweep.grid_of`: X (G, 1), S_joint (G, N, c, P)),
    times the joint's prior span."""
    if sw.joints is None:  # cannot happen: both callers take this branch only when sw.joints is set
        raise ValueError("_per_joint needs a per-joint sweep (sw.joints set)")
    out = {}
    for name, ch in sw.joints:
        if name in fitted:
            X, S = sw.grid_of(name)
            out[name] = float(sigma_of(X, S[:, :, ch]) * span[name])
    return out


def _scatter_sigmas(sw: sel.Sweep, fitted: list[str], span: dict[str, float]) -> dict[str, float]:
    """Between-throw 1 sigma (physical units) of each fitted parameter of a 1-D sweep
    (:func:`select.scatter_sigma`; per-joint effects: each joint's own channels). 0 for sweeps of
    more than one parameter (not estimated there)."""
    out = {n: 0.0 for n in fitted}
    if sw.joints is None:
        if sw.names[0] in fitted:  # scatter_sigma is 0 for a grid of more than one parameter
            out[sw.names[0]] = sel.scatter_sigma(sw.X, sw.S.sum(axis=(2, 3))) * span[sw.names[0]]
    else:
        out.update(_per_joint(sw, fitted, span, lambda X, S: sel.scatter_sigma(X, S.sum(axis=(2, 3)))))
    return out


def evidence_of(S_base: np.ndarray, S_fit: np.ndarray, D: np.ndarray) -> dict:
    """Which channels a candidate's all-throw fit changes and whether channels other than the
    impact confirm it.

    Args:
        S_base / S_fit: (N, C, P) chi-square before / at the fit; D: (N, C, P) degrees of freedom.

    Returns:
        {"changes": {channel: chi-square drop (positive = better)} for channels it changes
        beyond noise (:func:`noise.worse_tolerance`), "impact_drop", "trajectory_drop" (every
        channel but the impact: joints, IMU, payload tracking, logged opening), "confirmed_by":
        [channel groups whose drop is at least CONFIRM_CHI2], "impact_only": True when the
        impact is the only evidence}.
    """
    b, f, Dc = S_base.sum(axis=(0, 2)), S_fit.sum(axis=(0, 2)), D.sum(axis=(0, 2))
    tol = nz.worse_tolerance(Dc)
    drop = b - f
    has = Dc > 0
    changes = {nz.CHANNELS[c]: float(drop[c]) for c in range(len(nz.CHANNELS)) if has[c] and abs(drop[c]) > tol[c]}
    imp = [nz.CH_INDEX["impact.downrange"], nz.CH_INDEX["impact.crossrange"]]
    traj = [c for c in range(len(nz.CHANNELS)) if has[c] and c not in imp]
    groups: dict[str, float] = {}
    for c in traj:
        groups[nz.group_of(nz.CHANNELS[c])] = groups.get(nz.group_of(nz.CHANNELS[c]), 0.0) + float(drop[c])
    confirmed = sorted(g for g, d in groups.items() if d >= CONFIRM_CHI2)
    return {"changes": changes, "impact_drop": float(drop[imp].sum()), "trajectory_drop": float(drop[traj].sum()),
            "drop_by_group": groups, "confirmed_by": confirmed, "impact_only": not confirmed}


def evaluate_candidate(ev: sel.Evaluator, sw: sel.Sweep, D: np.ndarray, train: np.ndarray, W: np.ndarray) -> tuple[Candidate, np.ndarray, np.ndarray]:
    """Fits, flags, the bootstrap out-of-bag losses (B,) and S (N, C, P) at the all-throw fit of one sweep."""
    t0 = time.time()
    N = D.shape[0]
    params, S_all = ev.fit(sw, np.ones(N))
    params_train, S_train = ev.fit(sw, train.astype(float))
    per_joint = sw.joints is not None
    not_ident = [n for (n, _), ok in zip(sw.joints or [], sw.identifiable) if not ok] if per_joint else []
    if sw.held_nominal:  # non-separable per-joint effect: the joints not fitted stay nominal
        def with_held(fit: dict[str, float]) -> dict[str, float]:  # every joint, in the class's order
            return {p.name: fit.get(p.name, p.nominal) for p in sw.cls.params if p.name in fit or p.name in sw.held_nominal}

        params, params_train, not_ident = with_held(params), with_held(params_train), list(sw.held_nominal)
    fitted = [n for n in params if n not in not_ident]
    # bootstrap: parameter spread and out-of-bag losses
    theta_rows: list[list[float]] = []
    oob = np.zeros(len(W))
    for b, w in enumerate(W):
        pb, Sb = ev.fit(sw, w)
        theta_rows.append([pb[n] for n in fitted])
        oob[b] = np.sum((w == 0) * Sb.sum(axis=(1, 2)))
    thetas = np.array(theta_rows, dtype=float).reshape(len(W), len(fitted))
    span = {p.name: p.hi - p.lo for p in sw.cls.params}
    spread = np.std(thetas, axis=0, ddof=1) if len(W) > 1 else np.zeros(len(fitted))
    # no grid-quantisation term (h / sqrt(12)): the fit interpolates between grid points, and on a
    # tuning case (seed 1, valve lag per joint) that term was 10x the actual error
    boot = {n: float(spread[i]) for i, n in enumerate(fitted)}
    prof = _profile_sigmas(sw, S_all, D, fitted, span)
    grid = {n: sw.resolution * span[n] / np.sqrt(12.0) for n in fitted}  # only when nothing else bounds it
    scat = _scatter_sigmas(sw, fitted, span)
    sigma = {n: max(boot[n], prof[n] if np.isfinite(prof[n]) else 0.0, scat[n]) or float(grid[n]) for n in fitted}
    k = len(fitted)
    oob += sel.PENALTY_PER_PARAM * k * (W == 0).mean(axis=1)
    # flags
    base_c, fit_c, Dc = ev.S_base.sum(axis=(0, 2)), S_all.sum(axis=(0, 2)), D.sum(axis=(0, 2))
    tol = nz.worse_tolerance(Dc)
    worse = {nz.CHANNELS[c]: float(fit_c[c] - base_c[c]) for c in range(len(nz.CHANNELS)) if Dc[c] > 0 and fit_c[c] - base_c[c] > tol[c]}
    at_bound = []
    for p in sw.cls.params:
        if p.name in fitted:
            x = (params[p.name] - p.lo) / (p.hi - p.lo)
            x_nom = (p.nominal - p.lo) / (p.hi - p.lo)
            # a lower bound of 0 on a magnitude is physics (no negative friction), not a prior cut
            if (x < sel.BOUND_MARGIN and x_nom > sel.BOUND_MARGIN and p.lo != 0.0) or (x > 1 - sel.BOUND_MARGIN and x_nom < 1 - sel.BOUND_MARGIN):
                at_bound.append(p.name)
    test = ~train
    split = split_fits(ev, sw, fitted, sigma, N)
    ev.fit(sw, np.ones(N))  # the per-joint identifiability flags of the all-throw fit again
    cand = Candidate(
        effect=sw.cls.spec(), params=params, params_train=params_train, sigma=sigma, k=k, at_bound=at_bound, worse=worse, not_identifiable=not_ident,
        sigma_parts={"bootstrap": boot, "profile": {n: (v if np.isfinite(v) else None) for n, v in prof.items()}, "scatter": scat},
        chi2_before=float(ev.S_base.sum()), chi2_after=float(S_all.sum()),
        test_excess_before=float(ev.S_base[test].sum() - D[test].sum()), test_excess_after=float(S_train[test].sum() - D[test].sum()),
        joint_gain=dict(sw.joint_gain), wall_s=time.time() - t0, evidence={**evidence_of(ev.S_base, S_all, D), "split": split})
    return cand, oob, S_all


def split_fits(ev: sel.Evaluator, sw: sel.Sweep, fitted: list[str], sigma: dict[str, float], N: int) -> dict:
    """The candidate fitted on the early and on the late half of the log (throw order,
    :func:`stationarity.split_halves`), from the same grid (no replay).

    Returns:
        {"early": params, "late": params, "z": {param: (late - early) / (2 sigma)} (each half's
        1 sigma taken as sqrt(2) sigma), "drifting": any |z| > Z_SPLIT, "halves": throws per half}.
    """
    early, late = st.split_halves(N)
    pe, _ = ev.fit(sw, early)
    pl, _ = ev.fit(sw, late)
    z = {n: float((pl[n] - pe[n]) / (2.0 * sigma[n])) if sigma.get(n, 0.0) > 0 else 0.0 for n in fitted}
    return {"early": {n: pe[n] for n in fitted}, "late": {n: pl[n] for n in fitted}, "z": z,
            "drifting": bool(any(abs(v) > Z_SPLIT for v in z.values())), "halves": int(early.sum())}


def residual_of(S: np.ndarray, D: np.ndarray) -> dict:
    """channel -> {"chi2", "dof", "gap", "z"} of S (N, C, P) over all throws and phases (channels with data)."""
    Sc, Dc = S.sum(axis=(0, 2)), D.sum(axis=(0, 2))
    out = {}
    for c, name in enumerate(nz.CHANNELS):
        if Dc[c] > 0:
            gap, z = nz.gap_test(Sc[c], Dc[c])
            out[name] = {"chi2": float(Sc[c]), "dof": float(Dc[c]), "gap": gap, "z": z}
    return out


_POOL_EV: sel.Evaluator | None = None
"""The round's evaluator, inherited by the forked sweep processes (never pickled)."""


def _sweep_job(args) -> tuple[Candidate, np.ndarray, np.ndarray, sel.Sweep]:
    cls, train, W, D = args
    t0 = time.time()
    ev = _POOL_EV
    if ev is None:  # cannot happen: sweep_candidates sets _POOL_EV before running (or forking for) any job
        raise RuntimeError("_sweep_job runs only inside sweep_candidates")
    sw = ev.sweep(cls, train)
    cand, oob, S_fit = evaluate_candidate(ev, sw, D, train, W)
    cand.wall_s = time.time() - t0
    return cand, oob, S_fit, sw


def resolve_workers(workers: int | None) -> int:
    """Processes for the candidate sweeps: ``workers`` (>= 1), default every core this process
    may run on (``os.sched_getaffinity``).

    Raises:
        ValueError: workers < 1.
    """
    if workers is None:
        return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    return int(workers)


def sweep_candidates(ev: sel.Evaluator, classes: list[type[Effect]], train: np.ndarray, W: np.ndarray, D: np.ndarray,
                     workers: int = 1) -> list[tuple[Candidate, np.ndarray, np.ndarray, sel.Sweep]]:
    """Sweep and evaluate each candidate on top of ``ev``'s base: [(candidate, out-of-bag losses
    (B,), S (N, C, P) at the all-throw fit, sweep)] in ``classes`` order.

    With ``workers`` > 1 the candidates run in a process pool (``concurrent.futures``, fork
    start: the processes inherit ``ev``, its throws and its dynamics cache without pickling; only
    the results travel back). The dynamics candidates (MuJoCo replays, the slow ones) are
    submitted first so that the cheap ones fill the gaps. The result does not depend on
    ``workers``: every candidate's fit is deterministic.
    """
    global _POOL_EV
    jobs = [(cls, train, W, D) for cls in classes]
    if workers <= 1 or len(jobs) <= 1:
        _POOL_EV = ev
        try:
            return [_sweep_job(j) for j in jobs]
        finally:
            _POOL_EV = None
    order = sorted(range(len(jobs)), key=lambda i: classes[i].stage != "dynamics")
    _POOL_EV = ev
    try:
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=multiprocessing.get_context("fork")) as pool:
            futs = {i: pool.submit(_sweep_job, jobs[i]) for i in order}
            return [futs[i].result() for i in range(len(jobs))]
    finally:
        _POOL_EV = None


def select_effects(ev_factory, classes: list[type[Effect]], D: np.ndarray, train: np.ndarray, seed: int = 0,
                   workers: int = 1) -> tuple[list[Round], list[Effect]]:
    """Forward selection (module doc of :mod:`select`).

    Args:
        ev_factory: base effects -> :class:`select.Evaluator`.
        classes: candidate effect classes.
        D: (N, C, P) degrees of freedom; train: (N,) bool training split.
        workers: processes for the candidate sweeps (:func:`sweep_candidates`).

    Returns:
        (rounds, named effects at their all-throw fits).
    """
    W = bootstrap_weights(D.shape[0], seed)
    named: list[Effect] = []
    rounds: list[Round] = []
    S_nominal = None
    while len(named) < sel.MAX_EFFECTS:
        ev = ev_factory(named)
        S_nominal = ev.S_base if S_nominal is None else S_nominal
        gaps = channel_gaps(ev.S_base, D, S_nominal if named else None, getattr(ev, "M_base", None), getattr(ev, "bias_margin", None))  # an evaluator without signed residuals: no bias test
        rnd = Round(gaps=sorted(gaps), residual=residual_of(ev.S_base, D))
        rounds.append(rnd)
        if not gaps:
            rnd.decision = "no gap left"
            break
        oobs, cands, cand_S = [], [], {}
        names_done = {type(e) for e in named}
        todo = []
        for cls in classes:
            if cls in names_done:
                continue
            why = gated(cls, gaps)
            if why:
                rnd.gated_out[cls.spec()] = why
                continue
            todo.append(cls)
        for cand, oob, S_fit, sw in sweep_candidates(ev, todo, train, W, D, workers):
            cand_S[cand.effect] = S_fit
            cands.append((cand, sw))
            oobs.append(oob)
            log.info("round %d: %-22s chi2 %.0f -> %.0f, params %s, worse %s, at bound %s (%.1f s)", len(rounds), cand.effect,
                     cand.chi2_before, cand.chi2_after, {k: round(v, 4) for k, v in cand.params.items()}, list(cand.worse), cand.at_bound, cand.wall_s)
        if not cands:
            rnd.decision = "no candidate acts where the gap is"
            break
        none_oob = np.array([np.sum((w == 0) * ev.S_base.sum(axis=(1, 2))) for w in W])
        L = np.vstack([none_oob[None]] + [o[None] for o in oobs])  # (1 + K, B)
        winner = np.argmin(L, axis=0)
        rnd.wins_none = float(np.mean(winner == 0))
        for i, (cand, _) in enumerate(cands):
            cand.wins = float(np.mean(winner == i + 1))
            cand.evidence["wins_all"] = cand.wins  # against every candidate and "none" (wins may be re-scored below)
            cand.beats_none = float(np.mean(L[i + 1] < L[0]))
            reasons = []
            if cand.at_bound:
                reasons.append(f"at its prior bound: {', '.join(cand.at_bound)}")
            if cand.worse:
                reasons.append("makes " + ", ".join(cand.worse) + " worse beyond noise")
            if cand.k == 0:
                reasons.append("no parameter identifiable")
            gap_idx = [nz.CH_INDEX[g] for g in gaps]
            excess = float(ev.S_base[:, gap_idx].sum() - D[:, gap_idx].sum())
            removed = float(ev.S_base[:, gap_idx].sum() - cand_S[cand.effect][:, gap_idx].sum())
            if excess > 0 and removed < sel.MIN_SHARE * excess:
                reasons.append(f"removes only {100 * max(removed, 0) / excess:.0f}% of the gap")
            cand.admissible = not reasons
            cand.reason = "; ".join(reasons)
        rnd.candidates = [c for c, _ in sorted(cands, key=lambda cs: -cs[0].wins)]
        order = sorted(range(len(cands)), key=lambda i: -cands[i][0].wins)
        best, best_sw = cands[order[0]]
        runner = cands[order[1]][0] if len(order) > 1 else None
        if rnd.wins_none >= best.wins:
            rnd.decision = "no candidate beats the twin without it on held-out throws"
            break
        if not best.admissible:
            pair, rnd2 = pair_step(ev_factory, classes, named, ev, best, best_sw, L, D, train, W, S_nominal, workers)
            if pair is None:
                rnd.pair_tried = rnd2.candidates if rnd2 is not None else []
                adm = [i for i, (c, _) in enumerate(cands) if c.admissible]
                if adm:
                    # the inadmissible leader split the resamples with the admissible ones (e.g. an
                    # encoder offset beside a release delay and an impact bias): those compete again
                    # among themselves and "none" (their wins_admissible), as a round would
                    won = np.argmin(L[[0] + [i + 1 for i in adm]], axis=0)
                    wins_a: dict[int, float] = {}  # candidate index -> its wins_admissible (as a float)
                    for j, i in enumerate(adm):
                        wins_a[i] = cands[i][0].wins_admissible = float(np.mean(won == j + 1))
                    order_a = sorted(adm, key=lambda i: -wins_a[i])
                    a, a_sw = cands[order_a[0]]
                    if wins_a[order_a[0]] >= sel.WIN_FREQ and wins_a[order_a[0]] > float(np.mean(won == 0)):
                        rnd.decision, rnd.named = "named", a.effect
                        a.wins = wins_a[order_a[0]]
                        polish_named(ev, a, a_sw, D, train, W)
                        named.append(a_sw.cls(**a.params))
                        continue
                    if len(order_a) > 1 and wins_a[order_a[1]] >= sel.AMBIGUOUS_FREQ and wins_a[order_a[0]] > float(np.mean(won == 0)):
                        rnd.decision, rnd.named, rnd.runner_up = "ambiguous", a.effect, cands[order_a[1]][0].effect
                        a.wins, cands[order_a[1]][0].wins = wins_a[order_a[0]], wins_a[order_a[1]]
                        break
                rnd.decision = f"best candidate {best.effect} not admissible ({best.reason})"
                break
            if rnd2 is None or rnd2.named is None:  # cannot happen: pair_step returns with every pair its round, which names the second
                raise RuntimeError("pair_step returned a pair without the round naming it")
            second, second_sw = pair
            rnd.decision, rnd.named, best.pair_with = "named", best.effect, rnd2.named
            polish_named(ev, best, best_sw, D, train, W)
            named.append(best_sw.cls(**best.params))
            rounds.append(rnd2)
            if second is None:  # the first is named, the second ambiguous between two that complete it
                break
            if second_sw is None:  # cannot happen: pair_step returns a second candidate with its sweep
                raise RuntimeError("pair_step returned a candidate without its sweep")
            named.append(second_sw.cls(**second.params))
            continue
        if best.wins < sel.WIN_FREQ:
            if runner is not None and runner.admissible and runner.wins >= sel.AMBIGUOUS_FREQ:
                rnd.decision = "ambiguous"
                rnd.named, rnd.runner_up = best.effect, runner.effect
            else:
                rnd.decision = f"best candidate {best.effect} wins only {100 * best.wins:.0f}% of resamples"
            break
        rnd.decision = "named"
        rnd.named = best.effect
        polish_named(ev, best, best_sw, D, train, W)
        named.append(best_sw.cls(**best.params))
    if len(named) >= 2:
        backfit(ev_factory, rounds, named, D, train, W)
    return rounds, named


def polish_named(ev: sel.Evaluator, cand: Candidate, sw: sel.Sweep, D: np.ndarray, train: np.ndarray, W: np.ndarray) -> None:
    """A named effect's fit converged off the grid (:meth:`select.Evaluator.polish` with force) and
    its parameters, 1 sigma (the profile part from the profile interval), prior-bound flags and
    evidence re-evaluated on the polished grid, in place (its win frequencies stay the round's)."""
    if not ev.polish(sw, force=True):
        return
    new, _, _ = evaluate_candidate(ev, sw, D, train, W)
    cand.params, cand.params_train, cand.sigma, cand.sigma_parts, cand.at_bound = new.params, new.params_train, new.sigma, new.sigma_parts, new.at_bound
    cand.evidence = {**new.evidence, "wins_all": cand.evidence.get("wins_all", cand.wins), "polished": list(sw.polished)}
    log.info("polished %s: %s", cand.effect, {k: round(v, 5) for k, v in cand.params.items()})


def pair_step(ev_factory, classes, named: list[Effect], ev: sel.Evaluator, first: Candidate, first_sw: sel.Sweep, L: np.ndarray,
              D: np.ndarray, train: np.ndarray, W: np.ndarray, S_nominal: np.ndarray, workers: int = 1
              ) -> tuple[tuple[Candidate, sel.Sweep] | tuple[None, None] | None, Round | None]:
    """Forward selection's pair step: two effects whose joint fit explains the gap when no single one is admissible.

    Tried only when the pair fits within MAX_EFFECTS, the round's best candidate ``first`` wins
    at least WIN_FREQ of the resamples and its sole flaw is a channel it makes worse beyond noise (e.g. a hanging mass fitted to the
    gripper swing pushes the impact further off while a grasp offset is what moves the impact).
    Every candidate that can act on the channels ``first`` made worse is fitted on top of ``first``
    (at its all-throw fit). A second effect completes the pair only if (a) the pair leaves no
    channel worse than the round's base beyond its noise, (b) no gap is left anywhere, (c) its
    parameters are identifiable and inside the prior, and (d) the pair, penalised
    PENALTY_PER_PARAM per parameter of both effects, beats "none" and every single candidate of
    the round on the left-out throws of at least WIN_FREQ of the resamples. When several second
    effects pass, they compete as in a round: one that wins WIN_FREQ of the resamples against the
    others completes the pair; otherwise ``first`` is named (every passing pair contains it) and
    the second is "ambiguous" between the two best.

    Args:
        L: (1 + K, B) the round's out-of-bag losses ("none" first, then the single candidates).
        S_nominal: (N, C, P) chi-square of the nominal twin (for the "no gap left" test).

    Returns:
        ((second candidate, its sweep), the round that names it); ((None, None), the round)
        when the second is ambiguous; (None, the round of second effects tried) when none
        completes the pair; (None, None) when the step is not tried.
    """
    reasons = first.reason.split("; ")
    if len(named) + 2 > sel.MAX_EFFECTS or first.wins < sel.WIN_FREQ or not first.worse or first.at_bound or first.k == 0 or not all(r.startswith("makes ") for r in reasons):
        return None, None
    ev2 = ev_factory(named + [first_sw.cls(**first.params)])
    gaps2 = channel_gaps(ev2.S_base, D, S_nominal, getattr(ev2, "M_base", None), getattr(ev2, "bias_margin", None))
    worse_gaps = {c: gaps2[c] for c in first.worse if c in gaps2}
    if not worse_gaps:
        return None, None
    rnd = Round(gaps=sorted(gaps2))
    base_c, tol = ev.S_base.sum(axis=(0, 2)), nz.worse_tolerance(D.sum(axis=(0, 2)))
    has_dof = D.sum(axis=(0, 2)) > 0
    passed = []
    done = {type(e) for e in named} | {first_sw.cls}
    todo = []
    for cls in classes:
        if cls in done:
            continue
        why = gated(cls, worse_gaps) or gated(cls, gaps2)
        if why:
            rnd.gated_out[cls.spec()] = why
            continue
        todo.append(cls)
    for cand, oob, S_fit, sw in sweep_candidates(ev2, todo, train, W, D, workers):
        pair_oob = oob + sel.PENALTY_PER_PARAM * first.k * (W == 0).mean(axis=1)
        cand.wins = float(np.mean(pair_oob < L.min(axis=0)))
        cand.beats_none = float(np.mean(pair_oob < L[0]))
        fit_c = S_fit.sum(axis=(0, 2))
        worse = [nz.CHANNELS[c] for c in range(len(nz.CHANNELS)) if has_dof[c] and fit_c[c] - base_c[c] > tol[c]]
        left = channel_gaps(S_fit, D, S_nominal)
        reasons = []
        if worse:
            reasons.append(f"the pair with {first.effect} makes " + ", ".join(worse) + " worse beyond noise")
        if left:
            reasons.append(f"the pair with {first.effect} leaves a gap in " + ", ".join(sorted(left)))
        if cand.at_bound:
            reasons.append(f"at its prior bound: {', '.join(cand.at_bound)}")
        if cand.k == 0:
            reasons.append("no parameter identifiable")
        if cand.wins < sel.WIN_FREQ:
            reasons.append(f"the pair wins only {100 * cand.wins:.0f}% of resamples")
        cand.admissible, cand.reason, cand.pair_with = not reasons, "; ".join(reasons), first.effect
        rnd.candidates.append(cand)
        log.info("pair step on %s: %-22s params %s, pair wins %.2f, %s", first.effect, cand.effect,
                 {k: round(v, 4) for k, v in cand.params.items()}, cand.wins, cand.reason or "admissible")
        if cand.admissible:
            passed.append((cand, sw, pair_oob))
    rnd.candidates.sort(key=lambda c: -c.wins)
    if not passed:
        rnd.decision = f"pair step on {first.effect}: no second effect completes it"
        return None, rnd
    # several complete it: they compete on the left-out throws as in a round (WIN_FREQ names one)
    # (its wins: the share of resamples where it beats "none", every single and the other pairs)
    won = np.argmin(np.vstack([L.min(axis=0)[None]] + [o[None] for _, _, o in passed]), axis=0)
    for i, (c, _, _) in enumerate(passed):
        c.wins = float(np.mean(won == i + 1))
    passed.sort(key=lambda p: -p[0].wins)
    rnd.candidates.sort(key=lambda c: (not c.admissible, -c.wins))
    second, sw, _ = passed[0]
    second.evidence["wins_all"] = second.wins  # the pair against "none", every single and the other pairs
    rnd.wins_none = float(1.0 - second.beats_none)
    if second.wins < sel.WIN_FREQ:
        rnd.decision, rnd.named, rnd.runner_up = "ambiguous", second.effect, passed[1][0].effect
        return (None, None), rnd
    rnd.decision, rnd.named = "named", second.effect
    return (second, sw), rnd


def backfit(ev_factory, rounds: list[Round], named: list[Effect], D: np.ndarray, train: np.ndarray, W: np.ndarray) -> None:
    """Refit every named effect with the others in the model (one pass, in naming order), in place.

    An effect named in round 1 was fitted before the later ones were in the model and has
    absorbed part of them (e.g. passive friction fitted alone takes up some of a release delay's
    downrange bias). Each is swept again on top of the others: all throws with the others at
    their all-throw fits (the reported parameters and 1 sigma), and the training throws with the
    others at their training fits (``params_train``, what the held-out check replays, so that no
    held-out throw enters any fit). The rounds' named candidates get the new values and
    ``refit = True``; ``named`` gets the all-throw refits.
    """
    named_rounds = [r for r in rounds if r.decision == "named"]
    cands = [next(c for c in r.candidates if c.effect == r.named) for r in named_rounds]
    ones = np.ones(D.shape[0], bool)
    for i, e in enumerate(list(named)):
        cls = type(e)
        others = named[:i] + named[i + 1:]
        ev = ev_factory(others)
        sw_all = ev.sweep(cls, ones)
        ev.polish(sw_all, force=True)  # the reported fit converges off the grid (polish_named)
        c_all, _, _ = evaluate_candidate(ev, sw_all, D, train, W)
        others_train = [type(o)(**cands[j].params_train) for j, o in enumerate(named) if j != i]
        ev_t = ev_factory(others_train)
        c_train, _, _ = evaluate_candidate(ev_t, ev_t.sweep(cls, train), D, train, W[:0])
        c = cands[i]
        # the one pass is not iterated to convergence: its own shift joins the 1 sigma (the interplay of the effects)
        shift = {n: abs(c_all.params[n] - c.params.get(n, c_all.params[n])) for n in c_all.sigma}
        c_all.sigma_parts["backfit_shift"] = shift
        c.sigma = {n: float(np.hypot(c_all.sigma[n], shift[n])) for n in c_all.sigma}
        c.params, c.sigma_parts, c.at_bound, c.params_train, c.refit = c_all.params, c_all.sigma_parts, c_all.at_bound, c_train.params_train, True
        c.evidence = {**c_all.evidence, "wins_all": c.evidence.get("wins_all", c.wins)}  # with the others in the model: what this effect alone adds
        named[i] = cls(**c_all.params)
        log.info("backfit: %s %s (train %s)", c.effect, {k: round(v, 4) for k, v in c.params.items()}, {k: round(v, 4) for k, v in c.params_train.items()})
