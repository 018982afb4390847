"""Is the gap the same early and late in the log? The change test (sim_twin.diagnosis.stationarity),
its use by the diagnosis (split fits, the "drifting" verdict) and by the drift watch; and what a
verdict may call confirmed (a part of an answer as the whole), the impact-only member of a pair,
and "to within noise" only where every channel is."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim_twin.diagnosis import forward as fw
from sim_twin.diagnosis import stationarity as st
from sim_twin.diagnosis.verdict import confirmation, drift_of, verdict_of


# --- the change test ------------------------------------------------------------------------------
def test_noise_alone_rarely_changes_and_a_step_is_found_where_it_is():
    rng = np.random.default_rng(1)
    d = np.tile([7.5, 8.0, 8.5, 9.0, 9.5], 6)
    ps = np.array([st.change_point(rng.normal(size=30), d, permutations=499, seed=i)["p"] for i in range(200)])
    assert np.mean(ps < 0.01) <= 0.03 and np.mean(ps < 0.05) <= 0.09  # calibrated (permutation p)
    x = rng.normal(size=30)
    x[18:] += 2.5
    r = st.change_point(x, d)
    assert r["p"] < 1e-3 and abs(r["change_at"] - 18) <= 2 and r["shape"] == "step"
    assert r["step"] == pytest.approx(r["mean_after"] - r["mean_before"]) and 1.5 < r["step"] < 3.5


def test_a_ramp_is_reported_with_its_rate():
    rng = np.random.default_rng(2)
    x = 0.15 * np.arange(40) + rng.normal(size=40)
    r = st.change_point(x)
    assert r["p"] < 1e-3 and r["shape"] == "ramp"
    assert abs(r["slope_per_throw"] - 0.15) < 3 * r["slope_se"]


def test_a_constant_effect_that_grows_with_distance_is_no_change_when_the_targets_move():
    """A release delay moves far throws more: targets near early and far late in the log must not
    look like a drift once the distance is regressed out (and do without it)."""
    rng = np.random.default_rng(3)
    d = np.r_[np.full(15, 7.5), np.full(15, 9.5)]
    x = 1.5 * (d - 7.5) + rng.normal(size=30)
    assert st.change_point(x)["p"] < 1e-3
    assert st.change_point(x, d)["p"] > 0.05


def test_holm_over_series_and_bad_input():
    rng = np.random.default_rng(4)
    step = rng.normal(size=30)
    step[15:] += 3.0
    rows = st.test_series({"a": rng.normal(size=30), "b": step, "c": rng.normal(size=30)})
    assert rows["b"]["drifting"] and not rows["a"]["drifting"] and not rows["c"]["drifting"]
    assert rows["b"]["p_holm"] >= rows["b"]["p"]
    assert st.change_point(np.ones(30))["p"] == 1.0 and st.change_point(np.arange(6.0))["change_at"] is None
    with pytest.raises(ValueError, match="finite 1-D"):
        st.change_point([1.0, np.nan] * 8)
    with pytest.raises(ValueError, match="one row per throw"):
        st.change_point(np.arange(12.0), np.arange(5.0))


# --- split fits and the drifting verdict ----------------------------------------------------------
def _synthetic(drift: float):
    """The synthetic machine of test_diagnosis_select with the swing effect changing half-way."""
    from tests.test_diagnosis_select import BLOCKS, PITCH, FakeEvaluator, ImpactKnob, ImpactShift, N, SwingMass, World

    world = World(m=0.4, f=0.0)
    m = np.r_[np.full(N // 2, 0.4 - drift), np.full(N - N // 2, 0.4 + drift)]
    world.pitch = 5.0 * world.u[:, None] * m[:, None] + np.random.default_rng(9).normal(size=(N, BLOCKS))
    train = np.zeros(N, bool)
    train[: int(0.7 * N)] = True
    rounds, named = fw.select_effects(lambda base: FakeEvaluator(world, base), [SwingMass, ImpactShift, ImpactKnob], world.D, train, seed=0)
    return rounds, named, PITCH


def test_a_swing_effect_that_changes_half_way_is_drifting_not_a_constant():
    rounds, named, _ = _synthetic(0.15)
    c = next(c for c in rounds[0].candidates if c.effect == rounds[0].named)
    sp = c.evidence["split"]
    assert sp["drifting"] and sp["early"]["m"] < 0.35 and sp["late"]["m"] > 0.45 and sp["z"]["m"] > fw.Z_SPLIT
    drift = drift_of(None, None, [c], [f"t{i}" for i in range(30)])
    assert drift["drifting"] and c.effect in drift["split"]
    v = verdict_of({"gap": True, "carriers": ["q.gripper_pitch"], "phases": {}}, rounds, named, None, drift)
    assert v["answer"] == "drifting" and v["effects"] == [] and "first 15 throws" in v["text"] and "Not fitted as a constant" in v["text"]


def test_a_constant_swing_effect_has_agreeing_halves_and_is_named():
    rounds, named, _ = _synthetic(0.0)
    c = next(c for c in rounds[0].candidates if c.effect == rounds[0].named)
    assert not c.evidence["split"]["drifting"] and abs(c.evidence["split"]["z"]["m"]) < 3
    drift = drift_of(None, None, [c], [f"t{i}" for i in range(30)])
    v = verdict_of({"gap": True, "carriers": ["q.gripper_pitch"], "phases": {}}, rounds, named, None, drift)
    assert v["answer"] == "named" and v["confirmed"] == [c.effect]


def test_a_drift_whose_halves_cancel_is_drifting_not_no_gap():
    """The where stage's change test: no chi-square gap and no mean bias, yet a change."""
    rng = np.random.default_rng(6)
    x = rng.normal(size=30) * 0.5
    x[:15] += 1.2
    x[15:] -= 1.2
    nominal = st.test_series({"impact.downrange": x, "impact.crossrange": rng.normal(size=30)})
    drift = drift_of(nominal, None, [], [f"t{i:02d}" for i in range(30)])
    v = verdict_of({"gap": False, "carriers": [], "phases": {}}, [], [], None, drift)
    assert v["answer"] == "drifting" and v["where"] == ["impact.downrange"] and v["since"] == "t15"
    assert "impact.downrange changes since throw t15" in v["text"]


# --- confirmed means the same for a part as for the whole -----------------------------------------
def _cand(effect: str, **kw) -> fw.Candidate:
    base = dict(effect=effect, params={"p": 0.5}, sigma={"p": 0.01}, k=1, at_bound=[], worse={}, not_identifiable=[], params_train={"p": 0.5},
                chi2_before=0.0, chi2_after=0.0, test_excess_before=0.0, test_excess_after=0.0, wins=0.95, beats_none=1.0, admissible=True)
    ev = kw.pop("evidence", {})
    return fw.Candidate(**{**base, **kw}, evidence={"changes": {}, "confirmed_by": ["active"], "impact_only": False, "wins_all": kw.get("wins", 0.95), **ev})


def _res(**gaps) -> dict:
    chans = ["q.boom", "qd.boom", "q.dipper", "impact.downrange"]
    return {ch: {"chi2": 400.0 * (gaps.get(ch.replace(".", "_"), 1.0)), "dof": 400.0, "gap": ch.replace(".", "_") in gaps, "z": 0.0} for ch in chans}


def test_an_effect_that_leaves_a_gap_in_its_own_channels_is_only_partly_consistent():
    """An outside effect in the boom's mechanics mimicked by a valve effect on every joint: the
    valve effect explains the dipper but the boom keeps a gap, so it is not confirmed."""
    valve = _cand("valve_lag", evidence={"changes": {"q.boom": 900.0, "q.dipper": 300.0, "impact.downrange": 40.0}})
    rounds = [fw.Round(gaps=["q.boom", "q.dipper"], candidates=[valve], decision="named", named="valve_lag"),
              fw.Round(gaps=["q.boom"], candidates=[], decision="best candidate stiction not admissible", residual=_res(q_boom=3.0))]
    v = verdict_of({"gap": True, "carriers": ["q.boom", "q.dipper"], "phases": {}}, rounds, [])
    assert v["answer"] == "unexplained" and v["confirmed"] == []
    assert v["partly_consistent"][0]["effect"] == "valve_lag" and "q.boom" in v["partly_consistent"][0]["why"][0]
    assert "partly consistent with valve_lag" in v["text"] and "(confirmed)" not in v["text"]


def test_a_part_is_confirmed_only_under_the_named_rules():
    ok = _cand("valve_lag", evidence={"changes": {"q.dipper": 300.0}})
    assert confirmation(ok, ["q.boom"]) == []
    assert "wins only 60%" in confirmation(_cand("a", wins=0.6, evidence={"wins_all": 0.6}), [])[0]
    assert "prior bound" in confirmation(_cand("a", at_bound=["p"]), [])[0]
    assert "worse" in confirmation(_cand("a", worse={"q.boom": 50.0}), [])[0]
    assert "no joint" in confirmation(_cand("a", evidence={"impact_only": True, "confirmed_by": []}), [])[0]
    split = {"drifting": True, "early": {"p": 0.2}, "late": {"p": 0.8}, "z": {"p": 6.0}, "halves": 15}
    assert "early and the late half" in confirmation(_cand("a", evidence={"split": split}), [])[0]
    moving = confirmation(_cand("a", evidence={"changes": {"q.dipper": 300.0}}), [], {"after_fit": ["q.dipper"]})
    assert "changes during the log" in moving[0]


def test_the_impact_only_member_of_a_pair_is_listed_as_consistent_beside_the_confirmed_one():
    friction = _cand("passive_friction", evidence={"changes": {"q.gripper_pitch": 500.0}, "confirmed_by": ["passive"]})
    delay = _cand("release_delay", wins=0.6, beats_none=0.9, admissible=True, evidence={"impact_only": True, "confirmed_by": []})
    drag = _cand("payload_drag", wins=0.3, beats_none=0.8, admissible=True, evidence={"impact_only": True, "confirmed_by": []})
    rounds = [fw.Round(gaps=["impact.downrange", "q.gripper_pitch"], candidates=[friction], decision="named", named="passive_friction"),
              fw.Round(gaps=["impact.downrange"], candidates=[delay, drag], decision="best candidate release_delay wins only 60% of resamples")]
    v = verdict_of({"gap": True, "carriers": ["q.gripper_pitch", "impact.downrange"], "phases": {}}, rounds, [])
    assert v["answer"] == "consistent" and v["confirmed"] == ["passive_friction"]
    note = v["not_confirmed"][0]
    assert note["effect"] == "release_delay" and "payload_drag" in note["alternatives"] and "impact_bias" in note["alternatives"]
    assert "consistent with release_delay" in v["text"]


def test_to_within_noise_only_where_every_channel_is():
    lag = _cand("valve_dead_band", evidence={"changes": {"q.boom": 9000.0}})
    where = {"gap": True, "carriers": ["q.boom"], "phases": {}}
    rounds = [fw.Round(gaps=["q.boom"], candidates=[lag], decision="named", named="valve_dead_band"),
              fw.Round(gaps=[], decision="no gap left", residual=_res(q_boom=21.0))]
    v = verdict_of(where, rounds, [])
    assert v["answer"] == "named" and "to within noise" not in v["text"] and "q.boom (chi-square 21.0 times" in v["text"]
    assert v["rest_beyond_noise"] == ["q.boom"]
    rounds[1].residual = _res()
    assert "to within noise" in verdict_of(where, rounds, [])["text"]


# --- the drift watch uses the same test -----------------------------------------------------------
def test_the_drift_watch_locates_the_change_with_the_diagnosis_test():
    from server.analysis.drift import BASELINE_THROWS, Cusum

    rng = np.random.default_rng(7)
    cu = Cusum()
    alarm = None
    for i in range(BASELINE_THROWS + 60):
        e = rng.normal(0.0, 0.05, 2)
        if i >= BASELINE_THROWS + 10:
            e[0] -= 0.12  # 2.4 sigma short from throw 40 on
        alarm = cu.update(f"t{i:03d}", e)
        if alarm:
            break
    assert alarm is not None and alarm["direction"] == "short"
    ch = alarm["change"]
    assert ch["p"] < 0.05 and ch["used"] and abs(ch["change_at"] - (BASELINE_THROWS + 10)) <= 3
    assert ch["since_throw"] == alarm["throw_ids"][0] and ch["step_m"] < -0.08


# --- end to end: a generated log whose valve lag changes half-way ---------------------------------
@pytest.mark.slow
def test_a_generated_log_whose_valve_lag_changes_is_drifting(tmp_path: Path):
    from sim_twin.diagnosis import dataset
    from sim_twin.diagnosis.benchmark import POLICIES
    from sim_twin.diagnosis.diagnose import diagnose
    from sim_twin.diagnosis.reallog import RealLogSpec

    n = 24
    per = [{"name": "wearing", "effects": [{"effect": "valve_lag", "params": {"lag_s_boom": 0.12 if i < n // 2 else 0.32}}]} for i in range(n)]
    dataset.generate(tmp_path / "d", {}, n, POLICIES["2d"], seed=8, real_log=RealLogSpec(missing_impact_fraction=0.0), per_throw=per)
    rep = diagnose(tmp_path / "d", None, plots=False, workers=1)
    v = rep["verdict"]
    assert v["answer"] == "drifting" and v["effects"] == [] and rep["how_far"] is None
    ids = [t for t in rep["train"] + rep["test"]]
    assert v["since"] in ids
    order = sorted(ids)
    assert abs(order.index(v["since"]) - n // 2) <= 3


# --- fits that converge off the grid --------------------------------------------------------------
class _KinkWorld:
    """A chi-square with a kink at the truth, steep below it and shallow above (a dead band's
    hockey stick): the local quadratic through the grid predicts a negative chi-square there."""

    def __init__(self, param: str, truth: float, span: float, channel: str = "q.gripper_pitch"):
        from sim_twin.diagnosis import noise as nz

        self.param, self.truth, self.span = param, truth, span
        self.c = nz.CH_INDEX[channel]
        self.D = np.zeros((30, len(nz.CHANNELS), len(nz.PHASES)))
        self.D[:, self.c, 0] = 20
        self.w = np.random.default_rng(2).uniform(0.8, 1.2, 30)

    def S(self, effects):
        vals = {}
        for e in effects:
            vals.update(e.values)
        S = np.zeros(self.D.shape)
        v = vals.get(self.param, None)
        d = (v - self.truth) / self.span if v is not None else 0.05
        S[:, self.c, 0] = 0.1 + self.w * (8000.0 * max(-d, 0.0) + 200.0 * max(d, 0.0))
        return S


class _KinkEffect(__import__("sim_twin.twin.effects", fromlist=["Effect"]).Effect):
    name = "test_kink"
    footprint = ("passive",)
    stage = "dynamics"
    params = (__import__("sim_twin.twin.effects.base", fromlist=["Param"]).Param("k", "-", 0.0, 0.0, 1.0, "synthetic", "test"),)


def test_a_kinked_objective_is_fitted_off_the_grid_by_a_bounded_optimiser():
    from sim_twin.diagnosis import select as sel
    from tests.test_diagnosis_select import FakeEvaluator

    world = _KinkWorld("k", 0.37, 1.0)
    ev = FakeEvaluator(world, [])
    sw = ev.sweep(_KinkEffect, np.ones(30, bool))
    before, _ = ev.fit(sw, np.ones(30))
    assert abs(before["k"] - 0.37) > 0.02  # the local quadratic misses a hockey stick's vertex
    assert ev.polish(sw, force=True) and sw.polished == ["k"]
    params, _ = ev.fit(sw, np.ones(30))
    grid = np.linspace(0, 1, sel.COARSE_1D)
    assert abs(params["k"] - 0.37) < 2e-3 and np.min(np.abs(grid - params["k"])) > 0.01  # off the coarse grid
    cand, _, _ = fw.evaluate_candidate(ev, sw, world.D, np.ones(30, bool), fw.bootstrap_weights(30, 0)[:20])
    iv = sel.profile_interval(sw.X, sw.S.sum(axis=(1, 2, 3)))
    assert iv is not None and iv[1] - iv[0] < 1e-3  # the chi-square rises by 1 within a few 1e-4
    assert cand.sigma["k"] >= (iv[1] - iv[0]) / 2 and abs(cand.params["k"] - 0.37) < 2 * cand.sigma["k"]  # with the optimiser's tolerance


def test_a_per_joint_dead_band_between_grid_points_is_polished_on_its_own_channels():
    from sim_twin.twin.effects import effect_class
    from tests.test_diagnosis_select import FakeEvaluator

    cls = effect_class("valve_dead_band")
    p = next(q for q in cls.params if q.name == "dead_band_boom")
    world = _KinkWorld("dead_band_boom", 0.18, p.hi - p.lo, channel="q.boom")
    ev = FakeEvaluator(world, [])
    sw = ev.sweep(cls, np.ones(30, bool))
    params, _ = ev.fit(sw, np.ones(30))
    assert "dead_band_boom" in sw.polished and abs(params["dead_band_boom"] - 0.18) < 0.003
    assert abs(params["dead_band_boom"] - 0.2) > 0.01  # not the grid point 0.200 the quadratic fell back to


# --- power: sizes from simulation, not one linear step --------------------------------------------
def test_a_stated_size_holds_at_twice_it_on_the_simulated_sizes():
    from sim_twin.diagnosis.power import _smallest_reliable

    d = [0.02, 0.04, 0.08, 0.12, 0.16, 0.24]
    # a release delay: its mean impact shift grows, shrinks and changes sign (found at 0.04 and 0.24 only)
    assert _smallest_reliable(d, [False, True, False, False, False, True], [0] * 6) == (pytest.approx(0.20), 0)
    # every size found from 0.08 on: between the last miss and the first find
    size, _ = _smallest_reliable(d, [False, False, True, True, True, True], [1] * 6)
    assert size == pytest.approx(0.06) and 2 * size >= 0.08
    # found at every size: the one-step linear size, where every simulated size up to twice it is found
    assert _smallest_reliable(d, [True] * 6, [2] * 6, linear=0.005)[0] == pytest.approx(0.005)
    # a linear size whose double was not found is not stated
    assert _smallest_reliable(d, [True, False, True, True, True, True], [2] * 6, linear=0.02)[0] == pytest.approx(0.06)
    assert _smallest_reliable(d, [False] * 6, [0] * 6) == (None, None)
