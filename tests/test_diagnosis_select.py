"""Model selection details on a synthetic chi-square model, without simulation.

* Forward selection's pair step (:func:`sim_twin.diagnosis.forward.pair_step`): a pendulum-like
  effect that explains the gripper swing but alone pushes the impact further off, and an
  impact-only effect that completes it. The pair is named only when it explains the gap
  everywhere; a knob that cannot complete it is refused.
* Per-joint sweeps (:meth:`select.Evaluator._two_sided`): a joint that is not the most
  informative one is still fitted between grid points, not stuck at one."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from sim_twin.diagnosis import forward as fw
from sim_twin.diagnosis import noise as nz
from sim_twin.diagnosis import select as sel
from sim_twin.diagnosis.verdict import verdict_of
from sim_twin.twin.effects import Effect, effect_class
from sim_twin.twin.effects.base import Param

N = 30
BLOCKS = 20  # swing blocks of the gripper pitch per throw (one degree of freedom each)
PITCH, IMPACT = nz.CH_INDEX["q.gripper_pitch"], nz.CH_INDEX["impact.downrange"]


class SwingMass(Effect):
    """Synthetic dynamics effect: moves the gripper pitch and (the other way) the impact."""

    name = "test_swing_mass"
    footprint = ("passive",)
    stage = "dynamics"
    params = (Param("m", "-", 0.0, 0.0, 1.0, "synthetic", "test"),)


class ImpactShift(Effect):
    """Synthetic payload effect: the same impact shift on every throw."""

    name = "test_impact_shift"
    stage = "payload"
    params = (Param("f", "-", 0.0, -1.0, 1.0, "synthetic", "test"),)


class ImpactKnob(Effect):
    """Synthetic flight effect with another per-throw signature (cannot mimic ImpactShift)."""

    name = "test_impact_knob"
    stage = "flight"
    params = (Param("k", "-", 0.0, -1.0, 1.0, "synthetic", "test"),)


class ImpactShiftAlike(Effect):
    """Synthetic flight effect that mimics ImpactShift up to a 5 % per-throw wobble."""

    name = "test_impact_shift_alike"
    stage = "flight"
    params = (Param("g", "-", 0.0, -1.0, 1.0, "synthetic", "test"),)


class World:
    """The synthetic machine: per-throw signatures, the truth and fixed noise (units of sigma)."""

    def __init__(self, m: float, f: float, outside: float = 0.0, seed: int = 3):
        rng = np.random.default_rng(seed)
        self.u = rng.uniform(1.0, 2.0, N)  # swing sensitivity
        self.v = rng.uniform(0.8, 1.2, N)  # impact sensitivity of the swing effect
        self.w = rng.uniform(0.2, 1.8, N)  # the knob's signature
        self.r = rng.uniform(-1.0, 1.0, N)  # an effect outside the candidates (impact only)
        self.s = rng.choice([-1.0, 1.0], N)  # ImpactShiftAlike's wobble
        self.pitch = 5.0 * self.u[:, None] * m + rng.normal(size=(N, BLOCKS))
        # the outside effect pushes the impact the other way than the swing effect, but with its own spread
        self.impact = self.impact_of(m, f, 0.0) + outside * (1.0 + 0.8 * self.r) + rng.normal(size=N)
        self.D = np.zeros((N, len(nz.CHANNELS), len(nz.PHASES)))
        self.D[:, PITCH, 0] = BLOCKS
        self.D[:, IMPACT, 2] = 1

    def impact_of(self, m: float, f: float, k: float) -> np.ndarray:
        return -8.0 * self.v * m + 10.0 * f + 10.0 * k * self.w

    def S(self, effects: list[Effect]) -> np.ndarray:
        vals = {}
        for e in effects:
            vals.update(e.values)
        m, f, k = vals.get("m", 0.0), vals.get("f", 0.0), vals.get("k", 0.0)
        alike = 10.0 * vals.get("g", 0.0) * (1.0 + 0.05 * self.s)
        S = np.zeros(self.D.shape)
        S[:, PITCH, 0] = ((self.pitch - 5.0 * self.u[:, None] * m) ** 2).sum(axis=1)
        S[:, IMPACT, 2] = (self.impact - self.impact_of(m, f, k) - alike) ** 2
        return S


class FakeEvaluator(sel.Evaluator):
    """:class:`select.Evaluator` whose "replays" are the synthetic world's chi-square."""

    def __init__(self, world: World, base: list[Effect]):
        self.world, self.base, self.replays = world, list(base), 0
        self.S_base = world.S(self.base)
        self.scorer = SimpleNamespace(D=world.D)  # the degrees of freedom the joint refinement tests against

    def score(self, effects: list[Effect]) -> np.ndarray:
        self.replays += len(effects)
        return np.stack([self.world.S(self.base + [e]) for e in effects])


def _select(world: World, classes=(SwingMass, ImpactShift, ImpactKnob)):
    train = np.zeros(N, bool)
    train[: int(0.7 * N)] = True
    return fw.select_effects(lambda base: FakeEvaluator(world, base), list(classes), world.D, train, seed=0)


def test_alone_the_swing_effect_is_refused_because_it_makes_the_impact_worse():
    world = World(m=0.6, f=0.5)
    ev = FakeEvaluator(world, [])
    gaps = fw.channel_gaps(ev.S_base, world.D)
    assert "q.gripper_pitch" in gaps
    fit = world.S([SwingMass(m=0.6)])[:, IMPACT].sum()
    assert fit - ev.S_base[:, IMPACT].sum() > nz.worse_tolerance(world.D[:, IMPACT].sum())


def test_pair_step_names_both_effects_when_together_they_explain_the_gap():
    rounds, named = _select(World(m=0.6, f=0.5))
    assert [type(e) for e in named] == [SwingMass, ImpactShift]
    assert rounds[0].decision == "named" and rounds[1].decision == "named"
    first = next(c for c in rounds[0].candidates if c.effect == rounds[0].named)
    assert not first.admissible and "worse" in first.reason and first.pair_with == ImpactShift.spec()
    knob = next(c for c in rounds[1].candidates if c.effect == ImpactKnob.spec())
    assert not knob.admissible and "leaves a gap" in knob.reason
    assert rounds[-1].decision == "no gap left"
    assert abs(named[0].m - 0.6) < 0.05 and abs(named[1].f - 0.5) < 0.05


def test_pair_step_refuses_when_no_candidate_completes_the_pair():
    # the outside effect's spread leaves the best pair an impact chi-square of 108 on 30 degrees
    # of freedom, beyond the 5 sigma quantile of the chi-square (86)
    world = World(m=0.6, f=0.0, outside=6.0)
    alone = world.S([SwingMass(m=0.6)])[:, IMPACT].sum() - world.S([])[:, IMPACT].sum()
    assert alone > nz.worse_tolerance(world.D[:, IMPACT].sum())  # the same refusal as above ...
    rounds, named = _select(world)
    assert named == []  # ... and neither the shift nor the knob completes the pair
    assert "not admissible" in rounds[-1].decision
    tried = {c.effect: c for c in rounds[-1].pair_tried}
    assert set(tried) == {ImpactShift.spec(), ImpactKnob.spec()}
    assert all(not c.admissible and "leaves a gap" in c.reason for c in tried.values())


def test_pair_step_with_two_second_effects_that_fit_alike_names_the_first_and_says_ambiguous():
    rounds, named = _select(World(m=0.6, f=0.5), (SwingMass, ImpactShift, ImpactKnob, ImpactShiftAlike))
    assert [type(e) for e in named] == [SwingMass]
    assert rounds[-1].decision == "ambiguous"
    assert {rounds[-1].named, rounds[-1].runner_up} == {ImpactShift.spec(), ImpactShiftAlike.spec()}
    between = [c for c in rounds[-1].candidates if c.effect in (rounds[-1].named, rounds[-1].runner_up)]
    assert all(c.admissible and c.wins < sel.WIN_FREQ for c in between)


class OffsetWorld:
    """IMU offsets seen directly in the gripper pitch and (far more sensitive, as a 2D log's
    roll channel with its noise floor) in the roll channel; truth pitch -0.0213, roll 0."""

    def __init__(self, pitch: float = -0.0213):
        self.pitch = pitch
        self.ch = {"offset_gripper_pitch": nz.CH_INDEX["q.gripper_pitch"], "offset_gripper_roll": nz.CH_INDEX["q.gripper_roll"]}
        self.scale = {"offset_gripper_pitch": 2e3, "offset_gripper_roll": 2e5}
        self.D = np.zeros((N, len(nz.CHANNELS), len(nz.PHASES)))
        self.D[:, list(self.ch.values()), 0] = BLOCKS

    def S(self, effects):
        S = np.array(self.D)
        for e in effects:
            for name, c in self.ch.items():
                truth = self.pitch if name == "offset_gripper_pitch" else 0.0
                S[:, c, 0] += self.scale[name] * (e.values[name] - truth) ** 2
        if not effects:
            S[:, self.ch["offset_gripper_pitch"], 0] += self.scale["offset_gripper_pitch"] * self.pitch ** 2
        return S


def test_per_joint_fit_of_a_less_informative_joint_is_between_grid_points():
    world = OffsetWorld()
    ev = FakeEvaluator(world, [])
    sw = ev.sweep(effect_class("imu_offset"), np.ones(N, bool))
    params, _ = ev.fit(sw, np.ones(N))
    assert abs(params["offset_gripper_pitch"] + 0.0213) < 2e-4  # was -0.0167: a grid point, clipped one-sided box
    assert abs(params["offset_gripper_roll"]) < 1e-3


class SharedOffsetWorld:
    """Encoder offsets (a non-separable per-joint effect): every joint's offset moves the same
    shared channels, the gripper pitch and the impact, each joint with its own per-throw
    signature (the boom's half like the dipper's); truth: dipper offset only."""

    def __init__(self, dipper: float = 0.03, seed: int = 4):
        rng = np.random.default_rng(seed)
        self.a = {j: rng.uniform(-1.0, 1.0, N) for j in ("cabin_turn", "boom", "dipper", "telescope")}  # pitch per rad
        self.b = {j: rng.uniform(-1.0, 1.0, N) for j in self.a}  # impact per rad
        self.a["boom"], self.b["boom"] = 0.5 * (self.a["boom"] + self.a["dipper"]), 0.5 * (self.b["boom"] + self.b["dipper"])
        self.truth = {"offset_dipper": dipper}
        self.pitch = 2000.0 * self.a["dipper"][:, None] * dipper + rng.normal(size=(N, BLOCKS))
        self.impact = 800.0 * self.b["dipper"] * dipper + rng.normal(size=N)
        self.D = np.zeros((N, len(nz.CHANNELS), len(nz.PHASES)))
        self.D[:, PITCH, 0] = BLOCKS
        self.D[:, IMPACT, 2] = 1

    def S(self, effects: list[Effect]) -> np.ndarray:
        vals = {}
        for e in effects:
            vals.update(e.values)
        o = {j: vals.get(f"offset_{j}", 0.0) for j in self.a}
        S = np.zeros(self.D.shape)
        S[:, PITCH, 0] = ((self.pitch - 2000.0 * sum(self.a[j] * o[j] for j in o)[:, None]) ** 2).sum(axis=1)
        S[:, IMPACT, 2] = (self.impact - 800.0 * sum(self.b[j] * o[j] for j in o)) ** 2
        return S


def test_non_separable_sweep_fits_the_joint_that_explains_the_shared_channels():
    cls = effect_class("encoder_offset")
    assert not cls.separable and {"passive", "impact"} <= set(cls.groups())
    world = SharedOffsetWorld(dipper=0.03)
    ev = FakeEvaluator(world, [])
    gaps = fw.channel_gaps(ev.S_base, world.D)
    assert fw.gated(cls, gaps) is None  # the gap is in the swing and the impact, not in the encoders
    sw = ev.sweep(cls, np.ones(N, bool))
    assert sw.names == ["offset_dipper"] and max(sw.joint_gain, key=sw.joint_gain.get) == "offset_dipper"
    assert sorted(sw.held_nominal) == ["offset_boom", "offset_cabin_turn", "offset_telescope"]
    assert sw.joint_gain["offset_boom"] > 0.2 * sw.joint_gain["offset_dipper"]  # the boom alone would explain part of it
    train = np.zeros(N, bool)
    train[: int(0.7 * N)] = True
    cand, _, _ = fw.evaluate_candidate(ev, sw, world.D, train, fw.bootstrap_weights(N, 0)[:40])
    assert abs(cand.params["offset_dipper"] - 0.03) < 0.03 * 0.02 and set(cand.sigma) == {"offset_dipper"}
    assert 0 < cand.sigma["offset_dipper"] < 1e-3 and cand.k == 1
    assert {cand.params[n] for n in sw.held_nominal} == {0.0} and sorted(cand.not_identifiable) == sorted(sw.held_nominal)
    assert cand.joint_gain == sw.joint_gain
    rounds, named = fw.select_effects(lambda base: FakeEvaluator(world, base), [cls, effect_class("imu_offset")], world.D, train, seed=0)
    assert [type(e) for e in named] == [cls] and rounds[0].decision == "named"
    assert abs(named[0].offset_dipper - 0.03) < 6e-4 and named[0].offset_boom == 0.0


def test_local_fit_never_predicts_a_negative_chi_square():
    """A sharp minimum at a grid point (passive friction's neighbourhood on a seed-1 tuning case,
    chi-square / 1000): the 2-D quadratic through the neighbours dips to -0.9 at (0.029, 0.034);
    the best grid point is the fit, not that impossible negative chi-square."""
    X = np.array([[0.015, 0.0333], [0.0, 0.0337], [0.0394, 0.0337], [0.0, 0.0], [0.0394, 0.0], [0.0, 0.0743], [0.0, 0.0754], [0.0394, 0.0754]])
    T = np.array([229.0, 676.0, 374.0, 3836.0, 488.0, 589.0, 624.0, 2403.0])
    x, w = sel.local_fit(X, T)
    assert np.allclose(x, X[0]) and w @ T == T[0]
    g = np.linspace(0, 1, 5)[:, None]  # a parabola: its vertex, between the grid points, as before
    x1, w1 = sel.local_fit(g, 100.0 * (g[:, 0] - 0.4) ** 2)
    assert abs(x1[0] - 0.4) < 1e-9 and abs(w1 @ (100.0 * (g[:, 0] - 0.4) ** 2)) < 1e-9


def test_scatter_sigma_covers_per_throw_start_errors():
    """Per-throw minima scattered well beyond each throw's chi-square curvature (a noisy replay
    start state, select.scatter_sigma): the between-throw sigma is the scatter's error of the
    mean, not the profile's (9e-5 here); consistent throws give the profile's error of the mean.
    The grid is refined into a one-sided cluster right of the optimum, as in seed-1 case 9."""
    rng = np.random.default_rng(3)
    X = np.sort(np.concatenate([np.linspace(0, 1, 7), [0.63, 0.6302, 0.6305, 0.61]]))[:, None]
    a = 4e6  # per-throw curvature: profile sigma of one throw 5e-4, of the mean 5e-4 / sqrt(N)
    for spread, want in ((0.01, 0.01 / np.sqrt(N)), (0.0, 1 / np.sqrt(a * N))):
        m = 0.62 + spread * rng.standard_normal(N)
        Tn = a * (X - m[None]) ** 2
        got = sel.scatter_sigma(X, Tn)
        assert 0.6 * want <= got <= 1.5 * want + 1e-9, (spread, got, want)
    assert sel.scatter_sigma(np.zeros((5, 2)), np.zeros((5, N))) == 0.0


def _where_stub(carriers):
    return {"gap": True, "carriers": carriers, "phases": {}}


def test_an_effect_seen_only_in_the_impact_is_consistent_not_named():
    world = World(m=0.0, f=0.5)
    rounds, named = _select(world)
    assert [type(e) for e in named] == [ImpactShift]
    c = next(c for c in rounds[0].candidates if c.effect == rounds[0].named)
    assert c.evidence["impact_only"] and c.evidence["impact_drop"] > 100 and c.evidence["confirmed_by"] == []
    v = verdict_of(_where_stub(["impact.downrange"]), rounds, named)
    assert v["answer"] == "consistent" and v["confirmed"] == [] and "not confirmed" in v["text"]
    note = v["not_confirmed"][0]
    assert note["effect"] == ImpactShift.spec() and "impact_bias" in note["alternatives"]
    assert any("survey mark" in m for m in note["measurements"]) and any("another distance" in m for m in note["measurements"])
    assert any("off-centre" in o for o in note["outside"])


def test_a_swing_channel_confirms_an_effect_and_the_impact_only_partner_stays_unconfirmed():
    world = World(m=0.6, f=0.5)
    rounds, named = _select(world)
    assert {type(e) for e in named} == {SwingMass, ImpactShift}
    v = verdict_of(_where_stub(["q.gripper_pitch", "impact.downrange"]), rounds, named)
    assert v["answer"] == "consistent" and v["confirmed"] == [SwingMass.spec()]
    assert [n["effect"] for n in v["not_confirmed"]] == [ImpactShift.spec()]
    swing = next(n for n in v["evidence"]["named"] if n["effect"] == SwingMass.spec())
    assert swing["identifiability"]["confirmed_by"] == ["passive"] and "q.gripper_pitch" in swing["identifiability"]["changes"]


def test_the_bias_test_finds_a_small_mean_shift_that_the_chi_square_excess_misses():
    rng = np.random.default_rng(5)
    D = np.zeros((N, len(nz.CHANNELS), len(nz.PHASES)))
    D[:, IMPACT, 2] = 1
    D[:, PITCH, 0] = BLOCKS
    M = rng.normal(size=(N, len(nz.CHANNELS)))
    M[:, IMPACT] += 0.9  # ~5 sigma / sqrt(N) on the mean; the chi-square gains only ~N * 0.8
    S = np.zeros(D.shape)
    S[:, IMPACT, 2] = M[:, IMPACT] ** 2
    S[:, PITCH, 0] = BLOCKS
    assert "impact.downrange" not in fw.channel_gaps(S, D)  # the excess test alone: "no gap"
    gaps = fw.channel_gaps(S, D, None, M)
    assert gaps["impact.downrange"]["kind"] == "bias" and "q.gripper_pitch" not in gaps
    tests = nz.bias_tests(M, D)
    assert set(tests) == {"impact.downrange", "q.gripper_pitch"}  # channels without data are not tested
    assert tests["impact.downrange"]["p_holm"] == pytest.approx(min(1.0, 2 * tests["impact.downrange"]["p"]))  # Holm, 2 tests
    # noise only: no bias
    M0 = rng.normal(size=(N, len(nz.CHANNELS)))
    assert not any(t["bias"] for t in nz.bias_tests(M0, D).values())


def test_detectable_mean_is_the_bonferroni_quantile_plus_the_power_quantile_over_root_n():
    assert nz.detectable_mean(1.0, 30, 1) == pytest.approx((2.5758 + 0.8416) / np.sqrt(30), rel=1e-3)
    assert nz.detectable_mean(2.0, 120, 14) == pytest.approx(2 * nz.detectable_mean(1.0, 120, 14))
    assert nz.detectable_mean(1.0, 120, 14) == pytest.approx(nz.detectable_mean(1.0, 30, 14) / 2)


def test_workers_are_checked():
    assert fw.resolve_workers(3) == 3 and fw.resolve_workers(None) >= 1
    with pytest.raises(ValueError, match="workers must be >= 1"):
        fw.resolve_workers(0)


def test_a_trajectory_bias_within_the_margin_is_not_a_gap_and_one_beyond_it_is():
    """Minimum-effect bias test: the margin shifts the null (|E M| <= margin); without a margin it
    is the plain two-sided t-test; a bad margin is a clear error."""
    rng = np.random.default_rng(3)
    D = np.zeros((N, len(nz.CHANNELS), len(nz.PHASES)))
    D[:, PITCH, 0] = BLOCKS
    D[:, IMPACT, 2] = 1
    M = rng.normal(size=(N, len(nz.CHANNELS)))
    M[:, PITCH] += 1.5  # significant (t ~ 1.5 sqrt(N)) but within a margin of 2
    margin = np.zeros_like(M)
    margin[:, PITCH] = 2.0
    plain, material = nz.bias_tests(M, D), nz.bias_tests(M, D, margin=margin)
    assert plain["q.gripper_pitch"]["bias"] and not material["q.gripper_pitch"]["bias"]
    assert material["q.gripper_pitch"]["t_material"] < 0 < plain["q.gripper_pitch"]["t"]
    assert material["impact.downrange"]["p"] == pytest.approx(plain["impact.downrange"]["p"])  # no margin there: the same test
    M[:, PITCH] += 3.0  # now well beyond the margin
    assert nz.bias_tests(M, D, margin=margin)["q.gripper_pitch"]["bias"]
    with pytest.raises(ValueError, match="margin"):
        nz.bias_tests(M, D, margin=-margin)
    with pytest.raises(ValueError, match="margin"):
        nz.bias_tests(M, D, margin=margin[:, :3])
    assert nz.detectable_mean(1.0, 30, 1, margin=0.5) == pytest.approx(0.5 + nz.detectable_mean(1.0, 30, 1))


class DeadBandWorld:
    """A valve dead band per joint: the boom's channels follow its dead band (truth 0.15), the
    cabin turn only gets small commands, so its channels are the same for any dead band from the
    nominal 0.05 up and worse only below it (a plateau, as in a 2D throw)."""

    def __init__(self, boom: float = 0.15, seed: int = 5):
        rng = np.random.default_rng(seed)
        self.boom, self.cabin = rng.normal(size=(N, BLOCKS)), rng.normal(size=(N, BLOCKS))
        self.truth = boom
        self.D = np.zeros((N, len(nz.CHANNELS), len(nz.PHASES)))
        self.ch = {j: [nz.CH_INDEX[f"q.{j}"], nz.CH_INDEX[f"qd.{j}"]] for j in ("cabin_turn", "boom")}
        for j in self.ch:
            self.D[:, self.ch[j][0], 0] = BLOCKS

    def S(self, effects: list[Effect]) -> np.ndarray:
        vals = {}
        for e in effects:
            vals.update(e.values)
        db = {j: vals.get(f"dead_band_{j}", 0.05) for j in self.ch}
        S = np.zeros(self.D.shape)
        S[:, self.ch["boom"][0], 0] = ((self.boom + 40.0 * (db["boom"] - self.truth)) ** 2).sum(axis=1)
        S[:, self.ch["cabin_turn"][0], 0] = ((self.cabin + 40.0 * max(0.05 - db["cabin_turn"], 0.0)) ** 2).sum(axis=1)
        return S


def test_a_joint_whose_channels_prefer_no_value_over_the_nominal_stays_nominal():
    world = DeadBandWorld()
    ev = FakeEvaluator(world, [])
    sw = ev.sweep(effect_class("valve_dead_band"), np.ones(N, bool))
    params, _ = ev.fit(sw, np.ones(N))
    T = sw.S[:, :, world.ch["cabin_turn"]].sum(axis=(1, 2, 3))
    assert T.max() - T.min() > 100 * sel.IDENTIFIABLE_CHI2  # the sweep does move the cabin's channels (below the nominal)
    assert params["dead_band_cabin_turn"] == 0.05 and params["dead_band_dipper"] == 0.05  # held: the data prefer no other value
    assert abs(params["dead_band_boom"] - 0.15) < 0.005
    rng = np.random.default_rng(0)
    W = np.stack([np.bincount(rng.integers(0, N, N), minlength=N) for _ in range(20)]).astype(float)  # bootstrap resamples
    cand, _, _ = fw.evaluate_candidate(ev, sw, world.D, np.ones(N, bool), W)
    assert "dead_band_cabin_turn" in cand.not_identifiable and "dead_band_cabin_turn" not in cand.sigma and not cand.at_bound


def test_the_excess_test_uses_the_chi_square_tail_not_the_normal_approximation():
    """Few degrees of freedom (the impact channels: one per throw): a chi-square of 26 is skewed,
    so D + 5 sqrt(2 D) = 62 is reached by noise alone with probability ~9e-5, not 2.9e-7; the
    gap needs the exact 5 sigma quantile (~79). Many degrees of freedom: the 50 % rule decides."""
    from scipy.stats import chi2, norm

    assert nz.P_GAP == pytest.approx(norm.sf(nz.Z_GAP))
    q = chi2.isf(nz.P_GAP, 26)
    assert 78 < q < 80
    assert nz.gap_test(62.5, 26)[1] > nz.Z_GAP  # beyond 5 "sigma" of the normal approximation ...
    assert not nz.gap_test(62.5, 26)[0]  # ... yet no gap: P(chi2_26 >= 62.5) ~ 8e-5
    assert not nz.gap_test(q - 0.5, 26)[0] and nz.gap_test(q + 0.5, 26)[0]
    assert not nz.gap_test(1.49 * 410, 410)[0] and nz.gap_test(1.51 * 410, 410)[0]  # R_GAP decides at 410
    assert nz.gap_test(5.0, 0) == (False, 0.0) and not nz.gap_test(0.0, 26)[0]
    # a 30-throw impact channel with the declared noise: the false-alarm rate is the intended one
    rng = np.random.default_rng(3)
    S = rng.chisquare(26, size=200_000)
    assert np.mean([nz.gap_test(s, 26)[0] for s in S[S > 60]]) * np.mean(S > 60) < 5e-6
