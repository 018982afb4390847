"""The diagnosis replay's batching gives the numbers of one replay at a time: a (throw,
configuration) pair's trajectory does not depend on the other pairs in the batch (pairs leave the
batch when done, the valve chain is computed before the stepping), the shared nominal motion's
measurement is reused only for the same measuring effects, and an effect scored twice on one base
is replayed once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim_twin.diagnosis import dataset, replay, scoring, select
from sim_twin.diagnosis.reallog import RealLogSpec
from sim_twin.twin.effects import EffectStack, effect_class

POLICY = Path(__file__).parent.parent / "policies" / "throw2d.onnx"


@pytest.fixture(scope="module")
def throws(tmp_path_factory) -> list:
    d = tmp_path_factory.mktemp("batch")
    dataset.generate(d, {"name": "nominal"}, 4, POLICY, seed=3, workers=1, real_log=RealLogSpec(missing_impact_fraction=0.0))
    return dataset.load(d)[0]


def _stacks() -> list[EffectStack]:
    fx = [("valve_asymmetry", {"asymmetry_boom": 0.2, "asymmetry_dipper": -0.3}), ("valve_delay", {"delay_s_boom": 0.137}),
          ("stiction", {"breakaway_fraction": 0.2}), ("hanging_mass", {"gripper_mass_kg": 1200.0}), ("passive_friction", {"viscous_per_s": 0.7})]
    return [EffectStack()] + [EffectStack([effect_class(n)(**p)]) for n, p in fx]


def test_batched_pairs_equal_each_pair_replayed_alone(throws):
    stacks = _stacks()
    batch = replay.simulate(throws, stacks)
    for k, stack in enumerate(stacks):
        for n, th in enumerate(throws):
            q, qd = replay.simulate([th], [stack])[0][0]  # alone: a batch of one pair
            np.testing.assert_array_equal(batch[k][n][0], q)
            np.testing.assert_array_equal(batch[k][n][1], qd)


def test_shared_motion_measurement_is_reused_only_for_the_same_measuring_effects(throws):
    cache = replay.simulate(throws, [EffectStack()], long=True)[0]
    a = replay.replay_on(throws, EffectStack([effect_class("release_delay")(mean_s=0.3)]), cache)
    b = replay.replay_on(throws, EffectStack([effect_class("impact_bias")(bias_x_m=0.1)]), cache)
    c = replay.replay_on(throws, EffectStack([effect_class("imu_passive")(latency_s=0.05)]), cache)
    fresh = replay.replay(throws, [EffectStack([effect_class("release_delay")(mean_s=0.3)])])[0]  # its own replay, measured alone
    for n in range(len(throws)):
        assert a[n].meas_q is b[n].meas_q  # same motion, same sensing: one measurement
        L = len(fresh[n].q)  # the measurement is causal: the longer shared motion's first L rows
        np.testing.assert_array_equal(a[n].meas_q[:L], fresh[n].meas_q)
        np.testing.assert_array_equal(a[n].meas_qd[:L], fresh[n].meas_qd)
        assert not np.array_equal(c[n].meas_q[:, 4:6], a[n].meas_q[:, 4:6])  # a latency changes the passive joints' reading


def test_effect_key_tells_values_apart_exactly():
    cls = effect_class("impact_bias")
    assert replay.effect_key(cls(bias_x_m=0.1)) == replay.effect_key(cls(bias_x_m=0.1))
    assert replay.effect_key(cls(bias_x_m=0.0)) != replay.effect_key(cls(bias_x_m=-0.0))
    assert replay.effect_key(cls(bias_x_m=0.1)) != replay.effect_key(cls(bias_x_m=0.1 + 1e-15))


def test_an_effect_scored_twice_on_one_base_is_replayed_once(throws):
    nominal = replay.replay(throws, [EffectStack()])[0]
    scorer = scoring.Scorer(throws, scoring.estimate_noise(throws, nominal))
    ev = select.Evaluator(throws, scorer, [])
    e = effect_class("valve_lag")(lag_s_boom=0.25)
    S = ev.score([e, effect_class("valve_lag")(lag_s_boom=0.25), effect_class("valve_lag")(lag_s_boom=0.3)])
    assert ev.replays == 2
    np.testing.assert_array_equal(S[0], S[1])
    S2 = ev.score([e])
    assert ev.replays == 2 and np.array_equal(S2[0], S[0])
    fresh = select.Evaluator(throws, scorer, []).score([e])
    np.testing.assert_array_equal(fresh[0], S[0])
