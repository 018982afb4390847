"""Rewards as terms: one function per term, typed scales, sum = reward, every term logged."""

from __future__ import annotations

import json

import numpy as np
import pytest

jax = pytest.importorskip("jax")

import jax.numpy as jnp  # noqa: E402

from sim_twin.training.mjx_env import EnvConfig  # noqa: E402
from sim_twin.training.rewards import REWARD_TERMS, RewardInputs, RewardScales, reward_terms, total_reward  # noqa: E402
from sim_twin.training.config import CONFIG_DIR  # noqa: E402

SCALES = RewardScales.from_dict(json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]["rewards"])


def _inputs(rng, n):
    f = lambda lo, hi: jnp.asarray(rng.uniform(lo, hi, n), jnp.float32)  # noqa: E731
    b = lambda p: jnp.asarray(rng.random(n) < p)  # noqa: E731
    return RewardInputs(f(0, 12), f(0, 12), f(0, 12), f(0, 12), jnp.asarray(rng.normal(0, 1, (n, 4)), jnp.float32),
                        jnp.asarray(rng.normal(0, 1, (n, 4)), jnp.float32), b(0.5), b(0.2), b(0.3), f(0, 3), b(0.05),
                        f(0, 15), b(0.5), f(0, 10))


def test_terms_sum_to_reward_and_have_their_signs():
    x = _inputs(np.random.default_rng(0), 256)
    terms = jax.vmap(lambda xi: reward_terms(xi, SCALES))(x)
    assert set(terms) == set(REWARD_TERMS)
    total = jax.vmap(lambda xi: total_reward(reward_terms(xi, SCALES), SCALES.failure))(x)
    np.testing.assert_allclose(np.asarray(total), np.asarray(sum(terms.values())), rtol=1e-6, atol=1e-6)
    assert np.all(np.asarray(terms["act_diff"]) <= 0) and np.all(np.asarray(terms["failure"]) <= 0)
    landed_ok = np.asarray(x.landed & ~x.failed)
    assert np.all(np.asarray(terms["landing"])[~landed_ok] == 0) and np.all(np.asarray(terms["landing"])[landed_ok] > 0)
    # a term is its scale times its function: doubling one scale doubles that term only
    doubled = RewardScales(**{**SCALES.__dict__, "landing_fine": 2 * SCALES.landing_fine})
    t2 = jax.vmap(lambda xi: reward_terms(xi, doubled))(x)
    np.testing.assert_allclose(np.asarray(t2["landing_fine"]), 2 * np.asarray(terms["landing_fine"]), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(t2["landing"]), np.asarray(terms["landing"]))


def test_non_finite_reward_becomes_the_failure_reward():
    terms = {"a": jnp.asarray(jnp.nan), "b": jnp.asarray(1.0)}
    assert float(total_reward(terms, -5.0)) == -5.0


def test_typed_config_refuses_unknown_and_missing_settings():
    env = json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]
    cfg = EnvConfig.from_dict(env)
    assert isinstance(cfg.rewards, RewardScales) and cfg.forced_release.radius_m == env["forced_release"]["radius_m"]
    with pytest.raises(ValueError, match="unknown reward"):
        RewardScales.from_dict({**env["rewards"], "landng": 1.0})
    with pytest.raises(ValueError, match="incomplete"):
        RewardScales.from_dict({"delta_err": 1.0})
    with pytest.raises(ValueError, match="unknown forced_release"):
        EnvConfig.from_dict({**env, "forced_release": {"probabilty": 0.1}})
    with pytest.raises(ValueError, match="unknown env"):
        EnvConfig.from_dict({**env, "reward": {}})
    with pytest.raises(ValueError, match="mode"):
        EnvConfig.from_dict({**env, "mode": "4d"})
    assert cfg.far_targets.fraction == 0.0 and cfg.rewards.landing_precise == 0.0  # options, off by default
    with pytest.raises(ValueError, match="unknown far_targets"):
        EnvConfig.from_dict({**env, "far_targets": {"fractoin": 0.5}})
    with pytest.raises(ValueError, match="fraction"):
        EnvConfig.from_dict({**env, "far_targets": {"fraction": 1.5}})


def test_every_committed_config_loads_and_a_wrong_randomization_entry_is_refused():
    """A typo in a randomisation entry would otherwise fall back to its default silently."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    configs = [*CONFIG_DIR.glob("*.json"), *(root / "policies" / "training").glob("*/config.json")]
    assert len(configs) >= 4
    for path in configs:
        EnvConfig.from_dict(json.loads(path.read_text())["env"])
    env = json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]
    rand = env["randomization"]
    for bad, match in (({**rand, "lag_S": [0.1, 0.2]}, r"unknown entries \['lag_S'\]"),
                       ({**rand, "lag_s": [0.3, 0.1]}, r"lag_s must be a range \[lo, hi\]"),
                       ({**rand, "dead_band": 0.05}, "dead_band must be a range"),
                       ({**rand, "release_delay_std_s": -0.01}, "release_delay_std_s must be a number >= 0"),
                       ({**rand, "actuation": "valve"}, "actuation must be 'lag' or 'hydraulic'"),
                       ({**rand, "obs_noise": {"q": 0.1}}, "obs_noise must map")):
        with pytest.raises(ValueError, match=match):
            EnvConfig.from_dict({**env, "randomization": bad})
    with pytest.raises(ValueError, match=r"env.privileged_ranges: unknown entries \['obs_noise'\]"):
        EnvConfig.from_dict({**env, "privileged_ranges": {"obs_noise": {}}})


def test_randomization_is_typed_with_defaults_and_privileged_overrides():
    """The environment reads typed fields, not the config mapping: entries the config gives,
    defaults for the rest, and ``privileged_ranges`` replacing only the ranges it names."""
    from sim_twin.training.privileged import RANDOMIZATION_DEFAULTS, Randomization

    env = json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]
    rand = EnvConfig.from_dict(env).randomization
    assert isinstance(rand, Randomization) and rand.hydraulic
    assert rand.valve_delay_s == tuple(env["randomization"]["valve_delay_s"])
    assert rand.obs_noise.q_passive == env["randomization"]["obs_noise"]["q_passive"]
    bare = EnvConfig.from_dict({**env, "randomization": {}}).randomization
    assert bare == Randomization() and not bare.hydraulic
    assert bare.range("lag_s") == RANDOMIZATION_DEFAULTS["lag_s"] and bare.velocity_noise == 0.02
    with pytest.raises(KeyError, match="not a randomisation range"):
        bare.range("gain_error")
    narrowed = rand.with_ranges({"valve_delay_s": [0.1, 0.1], "gain_error": 0.2})
    assert narrowed.valve_delay_s == (0.1, 0.1) and narrowed.gain_error == 0.2
    assert narrowed.lag_s == rand.lag_s and rand.valve_delay_s != (0.1, 0.1)  # the original is unchanged
    assert rand.with_ranges({}) is rand
    with pytest.raises(ValueError, match="env.privileged_ranges.lag_s must be a range"):
        rand.with_ranges({"lag_s": [0.3, 0.1]})


def test_far_targets_weight_the_target_distance():
    """With far_targets.fraction f, a fraction f of episodes draws from the far range on top of the
    uniform draw over target_range_m (the 2D target lies on the arm's plane, so |target| = distance)."""
    from sim_twin.training.mjx_env import ThrowEnvCore

    env = json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]
    keys = jax.random.split(jax.random.PRNGKey(0), 4000)
    for fraction, expect in ((0.0, (10.7 - 9.0) / 5.7), (0.5, 0.5 + 0.5 * (10.7 - 9.0) / 5.7)):
        core = ThrowEnvCore(EnvConfig.from_dict({**env, "far_targets": {"fraction": fraction, "range_m": [9.0, 10.7]}}))
        dist = np.linalg.norm(np.asarray(jax.vmap(lambda k: core._sample_target(k, 0.0))(keys))[:, :2], axis=1)
        assert dist.min() >= 5.0 - 1e-4 and dist.max() <= 10.7 + 1e-4
        assert np.mean(dist >= 9.0) == pytest.approx(expect, abs=0.03)


def test_vec_env_logs_every_term_and_their_sum_is_the_mean_reward():
    import torch

    from sim_twin.training.vec_env import MjxThrowVecEnv

    env = MjxThrowVecEnv(EnvConfig.from_dict(json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]), 6, seed=2)
    g = torch.Generator().manual_seed(0)
    for _ in range(4):
        _, rew, _, extras = env.step(torch.rand(6, env.num_actions, generator=g) * 2 - 1)
        log = extras["log"]
        assert {f"Reward/{k}" for k in REWARD_TERMS} <= set(log)
        total = sum(float(log[f"Reward/{k}"]) for k in REWARD_TERMS)
        assert total == pytest.approx(float(rew.mean()), rel=1e-5, abs=1e-5)
    means = env.read_term_means()
    assert set(means) == {f"reward_{k}" for k in REWARD_TERMS}


def test_a_diverged_environment_is_left_out_of_the_logged_term_means_and_counted():
    """A state gone non-finite (here one environment's joint positions set to NaN) fails with the
    failure reward; its NaN distance terms stay out of the logged means (which were NaN at
    iterations 75-125 of the 2D runs from scratch) and it is counted as diverged."""
    import torch

    from sim_twin.training.vec_env import MjxThrowVecEnv

    env = MjxThrowVecEnv(EnvConfig.from_dict(json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]), 4, seed=5)
    data = env.state.data
    env.state = env.state.replace(data=data.replace(qpos=data.qpos.at[0].set(jnp.nan)))
    _, rew, dones, extras = env.step(torch.zeros(4, env.num_actions))
    log = {k: float(v) for k, v in extras["log"].items()}
    assert bool(dones[0]) and float(rew[0]) == pytest.approx(SCALES.failure)
    assert all(np.isfinite(log[f"Reward/{k}"]) for k in REWARD_TERMS), log
    assert log["Throw/diverged_per_done"] == pytest.approx(1.0 / float(dones.sum()))
    assert all(np.isfinite(v) for v in env.read_term_means().values())
    # the next step starts every environment afresh or carries on: nothing diverged
    _, _, _, extras = env.step(torch.zeros(4, env.num_actions))
    assert float(extras["log"]["Throw/diverged_per_done"]) == 0.0


@pytest.mark.parametrize("scale", [0.0, -5.0])
def test_an_episode_that_never_releases_ends_as_a_failure_when_the_recipe_punishes_it(scale):
    """At the time limit without a release command: with no_release < 0 the episode terminates with
    that reward (no bootstrap); with 0 it is a time-out, as before."""
    import torch

    from sim_twin.training.vec_env import MjxThrowVecEnv

    env_d = json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]
    env_d = {**env_d, "episode_length_s": 0.4, "forced_release": {**env_d["forced_release"], "probability": 0.0},
             "rewards": {**env_d["rewards"], "no_release": scale}}
    env = MjxThrowVecEnv(EnvConfig.from_dict(env_d), 4, seed=3)
    assert EnvConfig.from_dict(env_d).max_steps == 5
    hold = torch.zeros(4, env.num_actions)  # zero velocity, release output below its threshold
    for _ in range(4):
        _, _, dones, extras = env.step(hold)
        assert not dones.any()
    _, rew, dones, extras = env.step(hold)
    assert dones.all()
    log = extras["log"]
    if scale:
        assert not extras["time_outs"].any()
        assert float(log["Reward/no_release"]) == pytest.approx(scale)
    else:
        assert extras["time_outs"].all() and float(log["Reward/no_release"]) == 0.0


def test_release_slope_is_how_fast_the_landing_point_moves_at_the_opening():
    """The environment's release_slope is the held payload's landing-point speed at the physics step
    the gripper opened (10 ms finite difference): it agrees with the landing point's movement over
    the control step of the opening (80 ms), and the release_slope term pays weight x slope on the
    landing step only."""
    from sim_twin.training.mjx_env import ThrowEnvCore

    env_d = json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]
    env_d = {**env_d, "forced_release": {**env_d["forced_release"], "probability": 0.0},
             "rewards": {**env_d["rewards"], "release_slope": -0.5}}
    core = ThrowEnvCore(EnvConfig.from_dict(env_d))
    step = jax.jit(core.step)
    state, _ = jax.jit(core.reset)(jax.random.PRNGKey(5))
    points, terms, opened_at = [], [], None
    for k in range(60):  # dipper and telescope out at 0.6 of full speed, release commanded at step 8
        was_open = bool(state.opened)
        points.append(np.asarray(state.held_impact))
        state, _, _, terminated, _, info = step(state, jnp.asarray([0.0, 0.6, 0.6, 1.0 if k >= 8 else -1.0], jnp.float32))
        terms.append(float(info["reward_terms"]["release_slope"]))
        opened_at = k if bool(state.opened) and not was_open else opened_at
        if bool(terminated):
            break
    assert bool(info["landed"]) and opened_at is not None
    slope = float(state.release_slope)
    coarse = np.linalg.norm(points[opened_at + 1] - points[opened_at]) / 0.08
    assert slope > 0.05 and slope == pytest.approx(coarse, rel=0.25)
    assert terms[-1] == pytest.approx(-0.5 * slope, rel=1e-5) and not any(terms[:-1])


def test_hold_costs_every_step_that_ends_before_the_release_command():
    """The ``hold`` cost: -hold for a step whose end finds no release commanded, 0 once it has been
    (by the policy or the forced release); off (0) in the committed recipes."""
    x = _inputs(np.random.default_rng(1), 256)
    assert SCALES.hold == 0.0
    assert np.all(np.asarray(jax.vmap(lambda xi: reward_terms(xi, SCALES))(x)["hold"]) == 0)
    scales = RewardScales(**{**SCALES.__dict__, "hold": 0.01})
    hold = np.asarray(jax.vmap(lambda xi: reward_terms(xi, scales))(x)["hold"])
    released = np.asarray(x.released)
    assert released.any() and (~released).any()
    np.testing.assert_allclose(hold[~released], -0.01, rtol=1e-6)
    assert np.all(hold[released] == 0)


def test_hold_after_a_grace_charges_only_the_steps_that_end_after_it():
    """With ``hold_after_s`` g the cost falls on unreleased steps whose end is later than g; a step
    ending at g itself is free, and a released one stays free whenever it ends."""
    x = _inputs(np.random.default_rng(2), 512)
    scales = RewardScales(**{**SCALES.__dict__, "hold": 0.01, "hold_after_s": 4.0})
    hold = np.asarray(jax.vmap(lambda xi: reward_terms(xi, scales))(x)["hold"])
    released, late = np.asarray(x.released), np.asarray(x.elapsed_s) > 4.0
    assert (late & ~released).any() and (~late & ~released).any()
    np.testing.assert_allclose(hold[late & ~released], -0.01, rtol=1e-6)
    assert np.all(hold[~late | released] == 0)
    edge = x._replace(elapsed_s=jnp.full_like(x.elapsed_s, 4.0), released=jnp.zeros_like(x.released))
    assert np.all(np.asarray(jax.vmap(lambda xi: reward_terms(xi, scales))(edge)["hold"]) == 0)
    with pytest.raises(ValueError, match="unknown reward"):
        RewardScales.from_dict({**SCALES.__dict__, "hold_after": 4.0})


def test_the_environment_charges_hold_until_the_policy_commands_the_release():
    """In the MJX environment a step whose action keeps the flag under 0.9 pays -hold, the step that
    raises it and every later one nothing: the cost is on the policy's release command, not on the
    opening after the release delay."""
    paid = _hold_paid(0.0, "kkrkk")
    np.testing.assert_allclose(paid, [-0.01, -0.01, 0.0, 0.0, 0.0], atol=1e-7)


def _hold_paid(hold_after_s: float, actions: str) -> list[float]:
    """The ``hold`` term of each step of one MJX episode (the candidate 2D recipe, ``hold`` 0.01 after
    ``hold_after_s``) played with ``actions`` (:func:`_term_paid`)."""
    return _term_paid("hold", {"hold": 0.01, "hold_after_s": hold_after_s}, actions)


def _term_paid(term: str, rewards: dict[str, float], actions: str) -> list[float]:
    """The reward term ``term`` of each step of one MJX episode of the candidate 2D recipe with its
    ``rewards`` updated, played with ``actions``: ``k`` keeps the release flag at -1, ``r`` raises it
    to 1; no step may end the episode."""
    from sim_twin.training.mjx_env import ThrowEnvCore

    env = json.loads((CONFIG_DIR / "throw_2d_candidate.json").read_text())["env"]
    env = {**env, "rewards": {**env["rewards"], **rewards}}
    core = ThrowEnvCore(EnvConfig.from_dict(env))
    state, _ = jax.jit(core.reset)(jax.random.PRNGKey(5))
    step = jax.jit(core.step)
    flag = {"k": -1.0, "r": 1.0}
    paid = []
    for a in actions:
        state, _, _, ended, _, info = step(state, jnp.asarray([0.0, 0.0, 0.0, flag[a]]))
        paid.append(float(info["reward_terms"][term]))
        assert not bool(ended)
    return paid


def test_the_environment_counts_the_grace_in_control_periods():
    """``elapsed_s`` is the control steps so far times the 0.08 s control period: with a grace of
    0.2 s the first two held steps (ending at 0.08 and 0.16 s) are free, the third (0.24 s) and the
    fourth pay, and the release command ends the cost."""
    paid = _hold_paid(0.2, "kkkkrk")
    np.testing.assert_allclose(paid, [0.0, 0.0, -0.01, -0.01, 0.0, 0.0], atol=1e-7)


def test_early_release_costs_the_released_steps_up_to_its_time_and_nothing_after():
    """The ``early_release`` cost: -early_release for a step that ends with the release commanded at an
    episode time up to ``early_release_s`` (inclusive), 0 before the command and after that time; off (0)
    in the committed recipes."""
    x = _inputs(np.random.default_rng(3), 512)
    assert SCALES.early_release == 0.0
    assert np.all(np.asarray(jax.vmap(lambda xi: reward_terms(xi, SCALES))(x)["early_release"]) == 0)
    scales = RewardScales(**{**SCALES.__dict__, "early_release": 0.5, "early_release_s": 2.0})
    cost = np.asarray(jax.vmap(lambda xi: reward_terms(xi, scales))(x)["early_release"])
    released, early = np.asarray(x.released), np.asarray(x.elapsed_s) <= 2.0
    assert (released & early).any() and (released & ~early).any() and (~released & early).any()
    np.testing.assert_allclose(cost[released & early], -0.5, rtol=1e-6)
    assert np.all(cost[~released | ~early] == 0)
    edge = x._replace(elapsed_s=jnp.full_like(x.elapsed_s, 2.0), released=jnp.ones_like(x.released))
    np.testing.assert_allclose(np.asarray(jax.vmap(lambda xi: reward_terms(xi, scales))(edge)["early_release"]), -0.5, rtol=1e-6)


def test_the_environment_charges_an_early_release_from_its_command_to_its_time():
    """In the MJX environment the cost starts at the step whose action raises the flag and falls on every
    step that ends by ``early_release_s`` (0.2 s: the steps ending at 0.08 and 0.16 s; the release at
    the second), so an earlier release pays for more steps; a release after that time pays nothing."""
    paid = _term_paid("early_release", {"early_release": 0.5, "early_release_s": 0.2}, "krkk")
    np.testing.assert_allclose(paid, [0.0, -0.5, 0.0, 0.0], atol=1e-7)
    paid = _term_paid("early_release", {"early_release": 0.5, "early_release_s": 0.2}, "rkkk")
    np.testing.assert_allclose(paid, [-0.5, -0.5, 0.0, 0.0], atol=1e-7)
    late = _term_paid("early_release", {"early_release": 0.5, "early_release_s": 0.2}, "kkkr")
    np.testing.assert_allclose(late, [0.0, 0.0, 0.0, 0.0], atol=1e-7)
