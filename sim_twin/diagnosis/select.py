"""Which effects explain the gap: grid fits, bootstrap over throws, forward selection.

Per candidate (on top of the effects already named) the deterministic parameters are swept
over their prior on a grid (normalised to [0, 1]; 1 parameter: COARSE_1D points, refined with
3 points around the training optimum; 2 parameters: a COARSE_2D^2 grid refined by 3 x 3;
per-joint effects: one common sweep, each joint fitted from its own channels; per-joint effects
that are not separable, ``separable = False``: a 1-D sweep per joint over all channels, the joint
whose fit lowers the training chi-square most is fitted, the others stay nominal); the refinement
halves the spacing each time (at least 3 times, at most MAX_REFINE) until the best training
chi-square stops improving by REFINE_STOP_CHI2. Every grid point
replays ALL throws once, which gives the noise-scaled chi-square S (grid, throw, channel,
phase) (:mod:`scoring`). Everything after that is arithmetic on S:

* a fit on any weighting of the throws is the minimum of a local quadratic through the
  nearest grid points (credible for objectives that are not smooth: no finite differences);
* parameter uncertainty: the spread of that fit over BOOTSTRAP resamples of the throws,
  or the likelihood profile, or the scatter of the per-throw minima (:func:`scatter_sigma`: the
  replay's start state is noisy), whichever is largest (:func:`profile_sigma`, :func:`forward.evaluate_candidate`;
  the grid's resolution h / sqrt(12) only when neither bounds the parameter);
* win frequencies: per resample, each candidate is fitted on the resampled throws and scored
  on the throws left out (plus PENALTY_PER_PARAM per fitted parameter, scaled to the left-out
  share); the lowest wins. "none" (no further effect) competes too;
* the held-out claim: fitted on the training split only, scored on the held-out throws.

A candidate is **admissible** when its all-throw fit removes at least MIN_SHARE of the gap
channels' chi-square excess, leaves no channel worse beyond its noise
(:func:`noise.worse_tolerance`) and no parameter at a prior bound that is not its nominal value
(a lower bound of 0 on a magnitude is a physical limit, not a prior cut, and is allowed).
Forward selection names the candidate that wins at least WIN_FREQ of the resamples if it is
admissible, adds it to the base and repeats while a gap remains (at most MAX_EFFECTS; once an
effect is named, a channel whose excess is below RESIDUAL_SHARE of its nominal excess counts as
explained: at a large signal a fit within a few percent leaves a statistically visible rest).
Otherwise the round ends "ambiguous" (an admissible runner-up wins at least AMBIGUOUS_FREQ) or
"unexplained". A leader that is not admissible (and completes no pair) does not end the round by
itself: the admissible candidates compete again among themselves and "none" on the same
resamples, and one that wins WIN_FREQ of them is named (two that split them: "ambiguous"); with
more impact-only candidates (the impact bias beside release delay, drag, wind, grasp offset) an
inadmissible leader often wins only by splitting the others' share.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import product

import numpy as np

from sim_twin.diagnosis import noise as nz
from sim_twin.diagnosis import replay as rp
from sim_twin.diagnosis.scoring import Scorer
from sim_twin.twin.effects import Effect, EffectStack, PerJointEffect

COARSE_1D = 7
COARSE_2D = 4
BOOTSTRAP = 200
PENALTY_PER_PARAM = 1.0
WIN_FREQ = 0.75
AMBIGUOUS_FREQ = 0.15
MAX_EFFECTS = 3
BOUND_MARGIN = 0.02  # normalised distance from a prior bound that counts as "at the bound"
MAX_REFINE = 6
MIN_SHARE = 0.2  # a candidate must remove this share of the gap channels' chi-square excess
RESIDUAL_SHARE = 0.05  # after naming, a channel whose excess is below this share of the nominal one is explained
REFINE_STOP_CHI2 = 2.0  # stop refining when the best training chi-square improves by less than this
UNSTABLE_CHI2 = 1e9  # per throw, channel and phase, for a replay whose simulation diverged
IDENTIFIABLE_CHI2 = 9.0
"""A per-joint parameter is fitted only when its joint's channels prefer some value over the
nominal one by this much chi-square (a likelihood ratio of 3 sigma for one parameter); otherwise
it stays nominal (``not_identifiable``). Tested against the nominal, not as the range over the
sweep: a valve dead band on a joint that only gets small commands (the cabin turn in a 2D throw)
leaves its channels flat from the nominal 0.05 to the prior's 0.3 but far worse at 0, and a fit
on that plateau lands anywhere on it (seed-1 benchmark cases 7, 58, 61: at the prior bound, which
made the right candidate inadmissible)."""
POLISH_XTOL = 1.0 / 32  # polish: Brent's tolerance, a fraction of the grid's finest spacing
POLISH_ITER = 10  # polish: at most this many replays per parameter
ONE_SIDED_STEPS = 4  # per-joint sweeps: at most this many extra steps towards a joint's optimum (Evaluator._two_sided)
JOINT_PASSES = 2  # per-joint effects fitted jointly: block coordinate passes (Evaluator._joint_refine)
JOINT_STEPS = (-4.0, -2.0, -1.0, 0.0, 1.0, 2.0, 4.0)  # its grid around the current fit, in quarters of the coarse spacing


@dataclass
class Sweep:
    """One candidate's grid on top of a base set of effects.

    Attributes:
        cls: the effect class; names / lo / hi: fitted (deterministic) parameters.
        X: (G, k) normalised grid; S: (G, N, C, P) chi-square per grid point.
        joints: per-joint effects: (joint param name, channel indices) per joint; else None.
    """

    cls: type[Effect]
    names: list[str]
    lo: np.ndarray
    hi: np.ndarray
    X: np.ndarray
    S: np.ndarray
    joints: list[tuple[str, list[int]]] | None = None
    held_nominal: list[str] = field(default_factory=list)
    """Non-separable per-joint effects: the joints' parameters not fitted (kept nominal)."""
    joint_gain: dict[str, float] = field(default_factory=dict)
    """Non-separable per-joint effects: training chi-square removed by each joint's coarse fit."""
    verify_S: np.ndarray | None = None
    resolution: float = 1.0 / (COARSE_1D - 1)
    identifiable: list[bool] = field(default_factory=list)
    polished: list[str] = field(default_factory=list)
    """Parameters whose fit a bounded scalar minimisation on real replays refined (:meth:`Evaluator.polish`)."""
    joint_grids: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    """Per-joint effects fitted jointly (:meth:`Evaluator._joint_refine`): joint parameter name ->
    (X (G_j, 1), S (G_j, N, C, P)), that joint's own sweep with the other joints at their fits."""

    def grid_of(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(X, S) a per-joint parameter is fitted on: its own grid from the joint refinement, else the common sweep."""
        return self.joint_grids.get(name, (self.X, self.S))

    def theta(self, x: np.ndarray) -> dict[str, float]:
        return {n: float(lo + np.clip(v, 0, 1) * (hi - lo)) for n, lo, hi, v in zip(self.names, self.lo, self.hi, np.atleast_1d(x))}


def _basis(X: np.ndarray) -> np.ndarray:
    k = X.shape[1]
    cols = [np.ones(len(X))] + [X[:, i] for i in range(k)] + [X[:, i] ** 2 for i in range(k)]
    cols += [X[:, i] * X[:, j] for i in range(k) for j in range(i + 1, k)]
    return np.stack(cols, axis=1)


_NB_CACHE: dict = {}


def _hessian(coef: np.ndarray, k: int) -> np.ndarray:
    """Hessian (k, k) of the quadratic whose coefficients ``coef`` are in :func:`_basis` order
    (constant, k linear, k squares, then the k(k-1)/2 cross terms i < j)."""
    H = np.diag(2 * coef[1 + k:1 + 2 * k])
    idx = 1 + 2 * k
    for i in range(k):
        for j in range(i + 1, k):
            H[i, j] = H[j, i] = coef[idx]
            idx += 1
    return H


def local_fit(X: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum of a local quadratic through the grid points nearest the best one.

    Args:
        X: (G, k) normalised grid; T: (G,) loss.

    Returns:
        (x* (k,), w (G,)): the minimiser (kept inside the neighbourhood's box) and weights such
        that ``w @ L`` is the quadratic's value at x* for any loss L (G, ...) on the same grid;
        the best grid point (w one-hot) where the quadratic predicts a negative loss (T is a
        chi-square).
    """
    G, k = X.shape
    g = int(np.argmin(T))
    m = min(G, 3 if k == 1 else 9)
    key = (X.shape, X.tobytes()[:64], hash(X.tobytes()), g)
    if key not in _NB_CACHE:
        nb = np.argsort(np.linalg.norm(X - X[g], axis=1), kind="stable")[:m]
        _NB_CACHE[key] = (nb, np.linalg.pinv(_basis(X[nb])))
        if len(_NB_CACHE) > 4096:
            _NB_CACHE.pop(next(iter(_NB_CACHE)))
    nb, pinv = _NB_CACHE[key]
    coef = pinv @ T[nb]
    lo, hi = X[nb].min(axis=0), X[nb].max(axis=0)
    x = X[g].copy()
    if k == 1:
        if coef[2] > 1e-12:
            x = np.clip(np.array([-coef[1] / (2 * coef[2])]), lo, hi)
    else:
        H = _hessian(coef, k)
        # Newton step from the best point along the directions of positive curvature only: a
        # flat valley (parameters that trade off) moves nowhere along it instead of failing
        lam, V = np.linalg.eigh(H)
        grad = coef[1:1 + k] + H @ X[g]
        pos = lam > 1e-9 * max(np.abs(lam).max(), 1e-300)
        step = -V[:, pos] @ ((V[:, pos].T @ grad) / lam[pos]) if pos.any() else np.zeros(k)
        x = np.clip(X[g] + step, lo, hi)
    w = np.zeros(G)
    w[nb] = _basis(x[None])[0] @ pinv
    if w @ T < -1e-9 * np.abs(T[nb]).max():
        # a chi-square is never negative: the quadratic does not describe this neighbourhood (a
        # sharp minimum at a grid point, e.g. passive friction's nominal on a seed-1 tuning case
        # predicted -1591 and so "won" the resamples); the best grid point is the fit. The
        # tolerance is rounding: a quadratic whose minimum is 0 evaluates to about -1e-15 there
        x, w = X[g].copy(), np.eye(G)[g]
    return x, w


def quadratic_fails(X: np.ndarray, T: np.ndarray) -> bool:
    """True where :func:`local_fit` falls back to the best grid point: the local quadratic through
    the grid points nearest the best one predicts a negative chi-square at its minimum (the
    objective is not quadratic there: a kink or a sharp minimum between grid points)."""
    x, w = local_fit(X, T)
    g = int(np.argmin(T))
    return bool(w[g] == 1.0 and np.count_nonzero(w) == 1 and len(T) > 1)


def profile_interval(X: np.ndarray, T: np.ndarray, rise: float = 1.0) -> tuple[float, float] | None:
    """(lo, hi) where a 1-parameter chi-square T (G,) on X (G, 1) rises by ``rise`` above its
    minimum (the likelihood-profile interval), by linear interpolation between the evaluated points
    on either side of the best one; None unless T rises that far on both sides."""
    if X.shape[1] != 1:
        return None
    o = np.argsort(X[:, 0], kind="stable")
    x, t = X[o, 0], T[o]
    g = int(np.argmin(t))
    lim = t[g] + rise
    ends = []
    for idx in (range(g - 1, -1, -1), range(g + 1, len(t))):
        prev = g
        hit = None
        for i in idx:
            if t[i] >= lim:
                hit = x[prev] + (lim - t[prev]) * (x[i] - x[prev]) / (t[i] - t[prev])
                break
            prev = i
        if hit is None:
            return None
        ends.append(float(hit))
    return ends[0], ends[1]


def profile_sigma(X: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Likelihood-profile 1 sigma (normalised units, (k,)) of a chi-square T (G,) on the grid X
    (G, k): the local quadratic through the grid points nearest the best one (as
    :func:`local_fit`), covariance 2 H^-1 (chi-square rises by 1 at 1 sigma). A direction
    without positive curvature gives inf (the data do not bound it)."""
    G, k = X.shape
    g = int(np.argmin(T))
    nb = np.argsort(np.linalg.norm(X - X[g], axis=1), kind="stable")[: min(G, 3 if k == 1 else 9)]
    coef = np.linalg.pinv(_basis(X[nb])) @ T[nb]
    H = _hessian(coef, k)
    lam, V = np.linalg.eigh(H)
    if np.any(lam <= 1e-12 * max(np.abs(lam).max(), 1e-300)):
        return np.full(k, np.inf)
    return np.sqrt(np.diag(2.0 * (V / lam) @ V.T))


def scatter_sigma(X: np.ndarray, Tn: np.ndarray) -> float:
    """Between-throw 1 sigma (normalised units) of a 1-parameter fit from the scatter of the
    per-throw minima: each throw is one measurement m_n with variance 1 / a_n (its chi-square
    a_n (x - m_n)^2 + c), the all-throw fit is (to second order) their weighted mean, and its
    error is scaled by the measurements' consistency, the PDG scale factor (Particle Data Group,
    Review of Particle Physics, Introduction, "averaging procedures"):
    sigma = max(1, sqrt(chi2_m / (K - 1))) / sqrt(sum a_n), chi2_m = sum a_n (m_n - m)^2.

    Why: the chi-square treats each replay's start state as exact, but it is the mean of the
    first REST_ROWS noisy logged rows (:func:`replay.start_state`), a per-throw error that no
    noise term covers. For an encoder offset it shifts each throw's minimum by the start pose's
    noise (seed-1 case 9: per-throw minima scatter 1.2e-3 rad, so the mean is known to ~2e-4 rad,
    while each throw's chi-square is sharp and the Birge-scaled profile gives 5e-5: the misfit
    is diluted over all degrees of freedom). The bootstrap should see that scatter but does not
    where the local quadratic sits in a one-sided cluster of refined grid points (its fit is
    clipped to that cluster's box: spread 1e-5 rad). Here each throw's minimum is the vertex of
    the parabola through its best grid point and the nearest point on either side (bracketing);
    throws whose best point is at the grid's edge or whose parabola is not convex are left out.
    (The robust sandwich variance sum a_n^2 (m_n - m)^2 / (sum a_n)^2 was tried too: it also
    counts the 3-point parabolas' interpolation error, and on seed 1 it doubled the release
    delay's sigma against the bootstrap; this scale factor raised it by ~1.5x.)

    Args:
        X: (G, 1) normalised grid; Tn: (G, N) chi-square per grid point and throw.

    Returns:
        1 sigma in normalised units; 0.0 when fewer than 3 throws give a minimum or X is not 1-D.
    """
    if X.shape[1] != 1:
        return 0.0
    order = np.argsort(X[:, 0], kind="stable")
    xs = X[order, 0]
    est: list[float] = []
    curv: list[float] = []
    for n in range(Tn.shape[1]):
        t = Tn[order, n]
        g = int(np.argmin(t))
        if g == 0 or g == len(xs) - 1:
            continue
        a, b, _ = np.polyfit(xs[g - 1:g + 2], t[g - 1:g + 2], 2)
        if a > 0:
            est.append(-b / (2 * a))
            curv.append(a)
    if len(est) < 3:
        return 0.0
    e, w = np.array(est), np.array(curv)
    mean = w @ e / w.sum()
    scale2 = w @ (e - mean) ** 2 / (len(e) - 1)
    return float(np.sqrt(max(1.0, scale2) / w.sum()))


def _grid(k: int, nominal: np.ndarray, n1: int = COARSE_1D) -> np.ndarray:
    pts = np.linspace(0, 1, n1 if k == 1 else COARSE_2D)
    X = np.array(list(product(pts, repeat=k)), dtype=float)
    return np.unique(np.vstack([X, nominal[None]]).round(9), axis=0)


def _refine(x: np.ndarray, k: int, level: int) -> np.ndarray:
    """Points around x at half (level 1) or a quarter (level 2) of the coarse spacing."""
    h = (1.0 / (COARSE_1D - 1) if k == 1 else 1.0 / (COARSE_2D - 1)) / 2**level
    return np.clip(np.array([x + np.array(d) * h for d in product((-1, 0, 1), repeat=k)]), 0, 1)


class Evaluator:
    """Replays and scores candidate configurations over all throws (one base per round)."""

    def __init__(self, throws, scorer: Scorer, base: list[Effect], cache=None):
        self.throws, self.scorer, self.base = throws, scorer, list(base)
        # the nominal dynamics stay valid under a base that acts outside them (release, payload, flight)
        reuse = cache is not None and not rp.needs_dynamics(EffectStack(self.base))
        self.cache = cache if reuse else rp.simulate(throws, [EffectStack(self.base)], long=True)[0]
        reps = rp.replay_on(throws, EffectStack(self.base), self.cache)
        self.S_base = scorer.score(reps)
        self.M_base = scorer.signed(reps)  # (N, C) standardised mean residuals: the bias tests
        self.bias_margin = scorer.bias_margin  # (N, C) their immaterial mean
        self.replays = 0
        self._scored: dict[tuple, np.ndarray] = {}  # effect (class, parameters) -> its S (N, C, P)

    def score(self, effects: list[Effect]) -> np.ndarray:
        """S (K, N, C, P) of base + each effect (a replay that went unstable scores UNSTABLE_CHI2).
        Effects acting outside the dynamics reuse the base's joint motion (no MuJoCo stepping).
        An effect scored before on this base (same class, same parameter values: the sweeps of
        one candidate meet the same point, e.g. every joint's nominal) is not replayed again."""
        keys = [rp.effect_key(e) for e in effects]
        todo = [k for k in range(len(effects)) if keys[k] not in self._scored and keys[k] not in keys[:k]]
        stacks = {k: EffectStack(self.base + [effects[k]]) for k in todo}
        self.replays += len(stacks)
        dyn = [k for k in todo if rp.needs_dynamics(EffectStack([effects[k]]))]
        reps = dict(zip(dyn, rp.replay(self.throws, [stacks[k] for k in dyn]))) if dyn else {}
        for k in todo:
            S = self.scorer.score(reps[k] if k in reps else rp.replay_on(self.throws, stacks[k], self.cache))
            self._scored[keys[k]] = np.where(np.isfinite(S), S, UNSTABLE_CHI2)
        return np.stack([self._scored[key] for key in keys])

    def sweep(self, cls: type[Effect], train: np.ndarray) -> Sweep:
        """Grid sweep of ``cls`` (see module doc); ``train`` (N,) bool picks the throws whose fit
        centres the refinement."""
        det = [p for p in cls.params if not p.stochastic]
        pj = cls if issubclass(cls, PerJointEffect) else None  # not None: a per-joint effect
        if pj is not None and not pj.separable:
            return self._sweep_one_joint(pj, train)
        if pj is not None:
            p0 = det[0]
            names, lo, hi = [pj.joint_base], np.array([p0.lo]), np.array([p0.hi])
            nominal = np.array([(p0.nominal - p0.lo) / (p0.hi - p0.lo)])
        else:
            names = [p.name for p in det]
            lo, hi = np.array([p.lo for p in det]), np.array([p.hi for p in det])
            nominal = np.array([(p.nominal - p.lo) / (p.hi - p.lo) for p in det])
        k = len(names)
        sw = Sweep(cls, names, lo, hi, np.zeros((0, k)), np.zeros((0,) + self.S_base.shape))
        X = _grid(k, nominal)
        self._add(sw, X)
        if pj is not None:
            chans = {j: [nz.CH_INDEX[f"q.{j}"], nz.CH_INDEX[f"qd.{j}"]] for j in pj.joints}
            sw.joints = [(f"{pj.joint_base}_{j}", chans[j]) for j in pj.joints]
            w = train.astype(float)
            for level in range(1, 4):  # refine around the most informative joint's estimate
                x_j, _ = self.fit(sw, w)
                ranges = [np.ptp(np.einsum("n,gn->g", w, sw.S[:, :, ch].sum(axis=(2, 3)))) for _, ch in sw.joints]
                name = sw.joints[int(np.argmax(ranges))][0]
                self._add(sw, _refine(np.array([(x_j[name] - lo[0]) / (hi[0] - lo[0])]), 1, level))
                sw.resolution = 1.0 / (COARSE_1D - 1) / 2**level
            self._two_sided(sw, w)
            x_j, _ = self.fit(sw, w)
            sw.verify_S = self.score([cls(**{n: v for n, v in x_j.items()})])[0]
            self._joint_refine(sw, w, x_j)
        else:
            self._refine_all(sw, train)
        self.polish(sw)
        return sw

    def _refine_all(self, sw: Sweep, train: np.ndarray) -> None:
        """Refine a sweep fitted on all channels around its training optimum (module doc)."""
        k = sw.X.shape[1]
        for level in range(1, MAX_REFINE + 1):
            T = np.einsum("n,gn->g", train.astype(float), sw.S.sum(axis=(2, 3)))
            x, _ = local_fit(sw.X, T)
            self._add(sw, _refine(x, k, level))
            sw.resolution = (1.0 / (COARSE_1D - 1) if k == 1 else 1.0 / (COARSE_2D - 1)) / 2**level
            T_new = np.einsum("n,gn->g", train.astype(float), sw.S.sum(axis=(2, 3)))
            if level >= 3 and T.min() - T_new.min() < max(REFINE_STOP_CHI2, 1e-4 * T_new.min()):
                break

    def _sweep_one_joint(self, cls: type[PerJointEffect], train: np.ndarray) -> Sweep:
        """Sweep of a per-joint effect that is not separable (``cls.separable`` False).

        Every joint's parameter acts on the same shared channels (an encoder offset on any
        joint moves the true arm pose, hence the gripper swing and the impact), so no joint can
        be fitted from channels of its own. Each joint gets a coarse 1-D sweep over its prior
        with the other joints nominal, scored on ALL channels; the joint whose local fit lowers
        the training chi-square most is refined as a 1-D effect (:meth:`_refine_all`) and is the
        only one fitted (``Sweep.names``); the others stay nominal (``Sweep.held_nominal``). The
        choice is made once, on the training throws (not again per bootstrap resample). A second
        joint is not fitted: forward selection does not offer a named effect again, so what one
        joint cannot absorb of an offset on two joints stays a gap unless it falls below
        RESIDUAL_SHARE of the nominal excess.

        Returns:
            the chosen joint's Sweep (``joints`` None: fitted like a 1-parameter effect).
        """
        w = train.astype(float)
        sweeps = []
        for name in cls.joint_param_names():
            p = next(q for q in cls.params if q.name == name)
            x_nom = (p.nominal - p.lo) / (p.hi - p.lo)
            sw = Sweep(cls, [name], np.array([p.lo]), np.array([p.hi]), np.zeros((0, 1)), np.zeros((0,) + self.S_base.shape))
            self._add(sw, _grid(1, np.array([x_nom])))
            T = np.einsum("n,gn->g", w, sw.S.sum(axis=(2, 3)))
            _, g = local_fit(sw.X, T)
            T_nom = T[int(np.argmin(np.abs(sw.X[:, 0] - x_nom)))]
            sweeps.append((float(T_nom - g @ T), sw))
        gains = {sw.names[0]: gain for gain, sw in sweeps}
        sw = max(sweeps, key=lambda gs: gs[0])[1]
        sw.joint_gain = gains
        sw.held_nominal = [n for n in cls.joint_param_names() if n != sw.names[0]]
        self._refine_all(sw, train)
        self.polish(sw)
        return sw

    def _joint_refine(self, sw: Sweep, w: np.ndarray, x_j: dict[str, float]) -> None:
        """Per-joint effects on several joints at once: fit the joints jointly when the common
        sweep leaves a gap.

        The common sweep moves every joint alike and fits each joint from its own channels; a
        joint's channels also feel the other joints (the arm is one chain: the boom's speed loads
        the dipper, the telescope's length the boom), so with different values per joint (e.g. a
        valve asymmetry of +0.2 on the boom and -0.2 on the telescope) each joint's fit is biased
        by the others' common value and its channels keep a gap in the verification replay. Then
        each identifiable joint in turn (largest remaining excess first) gets a 1-D sweep of its
        own with the other joints at their current fits (block coordinate descent, JOINT_PASSES
        passes, the steps shrinking from JOINT_STEPS to half of them), fitted by the local
        quadratic on its own channels; that grid is kept for the joint's fit, bootstrap and
        profile (:meth:`Sweep.grid_of`). Nothing happens when no joint's channels keep a gap.
        """
        if sw.joints is None:  # cannot happen: only called from sweep() after it set sw.joints
            raise ValueError("_joint_refine needs a per-joint sweep (sw.joints set)")
        def gaps(S):
            return {name: nz.gap_test(S[:, ch].sum(), self.scorer.D[:, ch].sum()) for (name, ch), ok in zip(sw.joints, sw.identifiable) if ok}

        left = {n: z for n, (gap, z) in gaps(sw.verify_S).items() if gap}
        if not left or sum(sw.identifiable) < 2:
            return
        cur = dict(x_j)
        p0 = next(p for p in sw.cls.params if p.name == sw.joints[0][0])
        span = p0.hi - p0.lo
        h = 1.0 / (COARSE_1D - 1) / 4
        order = sorted((n for (n, _), ok in zip(sw.joints, sw.identifiable) if ok), key=lambda n: -left.get(n, 0.0))
        chans = dict(sw.joints)
        for npass in range(JOINT_PASSES):
            steps = np.array(JOINT_STEPS) / (2.0**npass)
            for name in order:
                x0 = (cur[name] - p0.lo) / span
                X = np.unique(np.clip(x0 + steps * h, 0.0, 1.0).round(9))[:, None]
                S = self.score([sw.cls(**{**cur, name: float(p0.lo + x * span)}) for x in X[:, 0]])
                sw.joint_grids[name] = (X, S)
                x, _ = local_fit(X, np.einsum("n,gn->g", w, S[:, :, chans[name]].sum(axis=(2, 3))))
                cur[name] = float(p0.lo + x[0] * span)
        sw.verify_S = self.score([sw.cls(**cur)])[0]

    def _two_sided(self, sw: Sweep, w: np.ndarray, steps: int = ONE_SIDED_STEPS) -> None:
        """Per-joint sweeps: give every identifiable joint grid points on both sides of its best one.

        The common sweep is refined around the most informative joint only. Another joint whose
        best grid point has its nearest neighbours all on one side would be fitted by a local
        quadratic clipped to that one-sided box, i.e. stuck at the grid point (an IMU pitch offset
        of -0.0213 rad fitted at -0.0167 with a bootstrap spread of 0, because the 2D roll channel,
        refined around 0, was the most informative). Such a joint gets points at the finest
        spacing stepping towards its optimum, at most ``steps`` times."""
        if sw.joints is None:  # cannot happen: only called from sweep() after it set sw.joints
            raise ValueError("_two_sided needs a per-joint sweep (sw.joints set)")
        h = sw.resolution
        for _, ch in sw.joints:
            for _ in range(steps):
                T = np.einsum("n,gn->g", w, sw.S[:, :, ch].sum(axis=(2, 3)))
                if T.max() - T.min() <= IDENTIFIABLE_CHI2 * max(w.sum() / len(w), 1e-9):
                    break
                g = int(np.argmin(T))
                xg = sw.X[g, 0]
                nb = sw.X[np.argsort(np.abs(sw.X[:, 0] - xg), kind="stable")[:3], 0]
                if xg <= 0.0 or xg >= 1.0 or nb.min() < xg < nb.max():
                    break
                self._add(sw, np.clip(np.array([[xg - h], [xg + h]]), 0, 1))

    def polish(self, sw: Sweep, force: bool = False) -> bool:
        """Fits that converge off the grid: where the local quadratic cannot describe the all-throw
        chi-square near its minimum (:func:`quadratic_fails`: it would fall back to a grid point),
        a bounded scalar minimisation on real replays (``scipy.optimize.minimize_scalar``,
        method "bounded", Brent's method on the bracket of the best grid point's neighbours, to
        POLISH_XTOL of the grid's finest spacing) adds its evaluations to the grid, so the fit,
        its bootstrap and its profile interval (:func:`profile_interval`) use them. 1-parameter
        sweeps on all channels; per-joint sweeps: each identifiable joint on its own channels,
        the other joints at their fits (its grid joins :attr:`Sweep.joint_grids`). Sweeps of two
        parameters are left to the quadratic. ``sw.polished`` lists the parameters polished.

        ``force``: polish every fitted parameter (forward selection does so for each effect it
        names: a kinked objective, a dead band's hockey stick, is fitted off its vertex by the
        quadratic even where the quadratic stays positive). Returns whether anything was polished."""
        from scipy.optimize import minimize_scalar

        ones = np.ones(sw.S.shape[1])
        if sw.joints is None:
            if sw.X.shape[1] != 1:
                return False
            if sw.names[0] in sw.polished or not (force or quadratic_fails(sw.X, sw.S.sum(axis=(1, 2, 3)))):
                return False
            xs = np.sort(sw.X[:, 0])
            g = float(sw.X[int(np.argmin(sw.S.sum(axis=(1, 2, 3)))), 0])
            lo, hi = max(xs[xs < g].max(initial=0.0), 0.0), min(xs[xs > g].min(initial=1.0), 1.0)

            def f1(x: float) -> float:
                self._add(sw, np.array([[x]]))
                i = int(np.argmin(np.abs(sw.X[:, 0] - x)))
                return float(sw.S[i].sum())

            minimize_scalar(f1, bounds=(lo, hi), method="bounded", options={"xatol": sw.resolution * POLISH_XTOL, "maxiter": POLISH_ITER})
            sw.polished.append(sw.names[0])
            return True
        params, _ = self.fit(sw, ones)
        idents = [ok for ok in sw.identifiable] if not sw.joint_grids else [n in sw.joint_grids for n, _ in sw.joints]
        todo = []
        for (name, ch), ok in zip(sw.joints, idents):
            if not ok:
                continue
            X, S = sw.grid_of(name)
            if name not in sw.polished and (force or quadratic_fails(X, S[:, :, ch].sum(axis=(1, 2, 3)))):
                todo.append((name, ch))
        if not todo:
            return False
        if not sw.joint_grids:  # from now on every identifiable joint is fitted on a grid of its own
            for (name, _), ok in zip(sw.joints, idents):
                if ok:
                    sw.joint_grids[name] = (sw.X.copy(), sw.S.copy())
        p0 = next(p for p in sw.cls.params if p.name == sw.joints[0][0])
        span = p0.hi - p0.lo
        for name, ch in todo:
            X, S = sw.joint_grids[name]
            T = S[:, :, ch].sum(axis=(1, 2, 3))
            xs = np.sort(X[:, 0])
            g = float(X[int(np.argmin(T)), 0])
            lo, hi = max(xs[xs < g].max(initial=0.0), 0.0), min(xs[xs > g].min(initial=1.0), 1.0)
            others = {n: v for n, v in params.items() if n != name}

            def fj(x: float, name: str = name, ch: list[int] = ch, others: dict = others) -> float:
                Sx = self.score([sw.cls(**{**others, name: float(p0.lo + x * span)})])
                Xg, Sg = sw.joint_grids[name]
                sw.joint_grids[name] = (np.vstack([Xg, [[x]]]), np.concatenate([Sg, Sx]))
                return float(Sx[0][:, ch].sum())

            minimize_scalar(fj, bounds=(lo, hi), method="bounded", options={"xatol": sw.resolution * POLISH_XTOL, "maxiter": POLISH_ITER})
            sw.polished.append(name)
            params, _ = self.fit(sw, ones)
        sw.verify_S = self.score([sw.cls(**params)])[0]
        return True

    def _add(self, sw: Sweep, X: np.ndarray) -> None:
        X = np.array([x for x in X if not np.any(np.all(np.abs(sw.X - x) < 1e-9, axis=1))]).reshape(-1, sw.X.shape[1])
        if not len(X):
            return
        S = self.score([sw.cls(**sw.theta(x)) for x in X])
        sw.X = np.vstack([sw.X, X])
        sw.S = np.concatenate([sw.S, S])

    def fit(self, sw: Sweep, w: np.ndarray) -> tuple[dict[str, float], np.ndarray]:
        """Fit on throw weights ``w`` (N,). Returns (parameters in physical units, per-throw
        S (N, C, P) at the fit: interpolated; per-joint effects: their own channels
        interpolated, the rest from the verification replay when there is one)."""
        if sw.joints is None:
            x, g = local_fit(sw.X, np.einsum("n,gn->g", w, sw.S.sum(axis=(2, 3))))
            return sw.theta(x), np.einsum("g,gncp->ncp", g, sw.S)
        S = (sw.verify_S if sw.verify_S is not None else sw.S[0]).copy()
        params = {}
        if not sw.joint_grids:
            sw.identifiable = []
        joint = bool(sw.joint_grids)
        for name, ch in sw.joints:
            p = next(p for p in sw.cls.params if p.name == name)
            if joint:  # fitted jointly: identifiability was decided on the common sweep
                if name not in sw.joint_grids:
                    params[name] = p.nominal
                    continue
                X, SG = sw.joint_grids[name]
                x, g = local_fit(X, np.einsum("n,gn->g", w, SG[:, :, ch].sum(axis=(2, 3))))
                params[name] = float(p.lo + x[0] * (p.hi - p.lo))
                S[:, ch] = np.einsum("g,gncp->ncp", g, SG[:, :, ch])
                continue
            T = np.einsum("n,gn->g", w, sw.S[:, :, ch].sum(axis=(2, 3)))
            x_nom = (p.nominal - p.lo) / (p.hi - p.lo)
            g_nom = int(np.argmin(np.abs(sw.X[:, 0] - x_nom)))
            ident = bool(T[g_nom] - T.min() > IDENTIFIABLE_CHI2 * max(w.sum() / len(w), 1e-9))
            sw.identifiable.append(ident)
            if not ident:
                params[name] = p.nominal
                S[:, ch] = sw.S[g_nom][:, ch]
                continue
            x, g = local_fit(sw.X, T)
            params[name] = float(p.lo + x[0] * (p.hi - p.lo))
            S[:, ch] = np.einsum("g,gncp->ncp", g, sw.S[:, :, ch])
        return params, S

    def normalised(self, sw: Sweep, params: dict[str, float]) -> dict[str, float]:
        """Fitted parameters on [0, 1] of their prior."""
        out = {}
        for p in sw.cls.params:
            if p.name in params and not p.stochastic:
                out[p.name] = (params[p.name] - p.lo) / (p.hi - p.lo)
        return out
