"""Asymmetric actor-critic: the privileged observation group (sim_twin.training.privileged) and resuming a
policy-only-critic checkpoint with the widened critic (sim_twin.training.critic_surgery). CPU, tiny."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
jax = pytest.importorskip("jax")
jnp = jax.numpy
pytestmark = pytest.mark.torch

from runtime.observation import build_observation, observation_size  # noqa: E402
from sim_twin.training import critic_surgery  # noqa: E402
from sim_twin.training.mjx_env import EnvConfig, ThrowEnvCore  # noqa: E402
from sim_twin.training.privileged import PRIVILEGED_LAYOUT, PRIVILEGED_SIZE  # noqa: E402
from sim_twin.training.config import CONFIG_DIR  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CKPT_2D = REPO / "tests/data/policy_only_critic_2d.pt"
"""An rsl_rl checkpoint of a 2D policy trained with the policy-only critic (throw2d-robust-f, iteration 3585,
critic input 56; the run is in the lab notebook, policies/training/ARCHIVE.md)."""


def _cfg(mode: str) -> dict:
    return json.loads((CONFIG_DIR / f"throw_{mode}.json").read_text())


def _slices() -> dict[str, slice]:
    out, i = {}, 0
    for name, n in PRIVILEGED_LAYOUT:
        out[name] = slice(i, i + n)
        i += n
    return out


@pytest.mark.parametrize("mode", ["2d", "3d"])
def test_privileged_group_layout_and_range(mode):
    cfg = _cfg(mode)
    assert cfg["runner"]["obs_groups"] == {"actor": ["policy"], "critic": ["policy", "privileged"]}
    core = ThrowEnvCore(EnvConfig.from_dict(cfg["env"]))
    state, obs = jax.jit(jax.vmap(core.reset))(jax.random.split(jax.random.PRNGKey(11), 256))
    priv = np.asarray(jax.jit(jax.vmap(core.privileged))(state))
    assert priv.shape == (256, PRIVILEGED_SIZE) == (256, 31) and priv.dtype == np.float32
    assert np.all(np.abs(priv) <= 1.5)
    sl = _slices()
    # hydraulic actuation: the lag model's gain is unused -> 0; the randomised ones spread out
    assert np.all(priv[:, sl["gain"]] == 0.0)
    for name in ("valve_delay", "valve_lag", "dead_band", "velocity_scale", "friction_scale", "gripper_mass_scale",
                 "release_delay", "sensor_latency"):
        assert priv[:, sl[name]].std(axis=0).min() > 0.2, name
    assert np.all(priv[:, sl["passive_qd"]] == 0.0)  # episodes start at rest
    assert np.all(priv[:, sl["grasp_offset"]] == 0.0)  # the recipes hold the payload at the gripper centre
    # the policy observation is still runtime.observation's, from the measured history
    s0 = jax.tree_util.tree_map(lambda x: np.asarray(x[0], dtype=np.float64), state)
    ref = build_observation(np, mode, s0.q_hist, s0.qd_hist, s0.prev_action, s0.target, float(s0.opened))
    assert np.asarray(obs).shape == (256, observation_size(mode))
    np.testing.assert_allclose(np.asarray(obs[0]), ref, rtol=1e-5, atol=1e-5)


def test_unrandomised_parameters_read_zero():
    env = _cfg("2d")["env"]
    env["randomization"] = {"actuation": "lag"}  # defaults: only lag, gain, friction randomised
    core = ThrowEnvCore(EnvConfig.from_dict(env))
    state, _ = jax.jit(jax.vmap(core.reset))(jax.random.split(jax.random.PRNGKey(2), 32))
    priv = np.asarray(jax.vmap(core.privileged)(state))
    sl = _slices()
    for name in ("valve_delay", "dead_band", "velocity_scale", "gripper_mass_scale", "sensor_latency"):
        assert np.all(priv[:, sl[name]] == 0.0), name
    for name in ("gain", "valve_lag", "friction_scale", "release_delay"):
        assert priv[:, sl[name]].std() > 0.1, name


def test_friction_drawn_log_uniformly_and_read_in_log_space():
    env = _cfg("2d")["env"]
    env["randomization"] = {**env["randomization"], "friction_scale": [0.5, 10.0], "friction_sampling": "log_uniform"}
    core = ThrowEnvCore(EnvConfig.from_dict(env))
    state, _ = jax.jit(jax.vmap(core.reset))(jax.random.split(jax.random.PRNGKey(5), 4096))
    fric = np.asarray(state.fric)
    assert fric.min() >= 0.5 - 1e-6 and fric.max() <= 10.0 + 1e-5
    # log-uniform: the median is the geometric mean (2.24), where uniform would put it at 5.25
    assert abs(np.median(fric) - np.sqrt(0.5 * 10.0)) < 0.15
    assert abs(np.mean(fric <= 3.5) - np.log(7) / np.log(20)) < 0.03
    priv = np.asarray(jax.jit(jax.vmap(core.privileged))(state))[:, _slices()["friction_scale"]][:, 0]
    np.testing.assert_allclose(priv, (np.log(fric) - np.log(np.sqrt(5.0))) / (0.5 * np.log(20.0)), atol=1e-4)
    assert abs(priv.mean()) < 0.05 and priv.min() >= -1.0001 and priv.max() <= 1.0001


def test_grasp_offset_drawn_read_and_released_from():
    """A randomised grasp offset: drawn per episode in its ranges, read by the critic, and the
    payload leaves from that point of the gripper with its velocity (the CPU twin's grasp_point)."""
    from sim_twin.twin.effects.payload import grasp_point

    env = _cfg("3d")["env"]
    env["randomization"] = {**env["randomization"], "grasp_forward_m": [-0.2, 0.2], "grasp_up_m": [-0.15, 0.05]}
    core = ThrowEnvCore(EnvConfig.from_dict(env))
    assert core.grasp_on
    state, _ = jax.jit(jax.vmap(core.reset))(jax.random.split(jax.random.PRNGKey(7), 2048))
    g = np.asarray(state.grasp)
    assert g[:, 0].min() >= -0.2 and g[:, 0].max() <= 0.2 and g[:, 0].std() > 0.1 and np.all(g[:, 1] == 0.0)
    assert g[:, 2].min() >= -0.15 and g[:, 2].max() <= 0.05 + 1e-7 and abs(g[:, 2].mean() + 0.05) < 0.01
    priv = np.asarray(jax.jit(jax.vmap(core.privileged))(state))[:, _slices()["grasp_offset"]]
    np.testing.assert_allclose(priv[:, 0], g[:, 0] / 0.2, atol=1e-5)
    np.testing.assert_allclose(priv[:, 1], (g[:, 2] + 0.05) / 0.1, atol=1e-5)
    # the held payload of a moving state against the CPU twin's kinematics, float32 against float64
    rng = np.random.default_rng(3)
    for k in range(4):
        q = np.array([rng.uniform(-3, 3), rng.uniform(-0.5, 0.5), rng.uniform(-2, -1), rng.uniform(0, 1.5),
                      rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        qd = rng.uniform(-1.5, 1.5, 6)
        p, v = core._held_payload(jnp.asarray(q, jnp.float32), jnp.asarray(qd, jnp.float32), state.grasp[k])
        p_ref, v_ref = grasp_point(q, qd, g[k])
        np.testing.assert_allclose(np.asarray(p), p_ref, atol=2e-5)
        np.testing.assert_allclose(np.asarray(v), v_ref, atol=2e-5)
        # and it is not the gripper centre: the offset moves the release point by its length
        c, _ = grasp_point(q, qd)
        assert abs(np.linalg.norm(p_ref - c) - np.linalg.norm(g[k].astype(np.float64))) < 1e-9


def test_without_grasp_offset_the_payload_leaves_from_the_gripper_centre():
    from runtime.machine import forward_kinematics

    core = ThrowEnvCore(EnvConfig.from_dict(_cfg("2d")["env"]))
    assert not core.grasp_on
    q = jnp.asarray([0.3, 0.1, -1.4, 0.6, 0.2, 0.0], jnp.float32)
    qd = jnp.asarray([0.2, 0.5, -0.7, 0.3, 1.0, 0.1], jnp.float32)
    p, v = core._held_payload(q, qd, jnp.zeros(3))
    pts = forward_kinematics(jnp, q, qd)
    assert np.array_equal(np.asarray(p), np.asarray(pts.gripper_centre)) and np.array_equal(np.asarray(v), np.asarray(pts.gripper_centre_vel))


@pytest.mark.parametrize("bad, match", [({"grasp_up_m": [0.1, -0.1]}, "grasp_up_m must be a range"),
                                         ({"grasp_offset_m": [0.0, 0.1]}, "unknown entries")])
def test_grasp_offset_refuses_bad_input(bad, match):
    env = _cfg("2d")["env"]
    env["randomization"] = {**env["randomization"], **bad}
    with pytest.raises(ValueError, match=match):
        EnvConfig.from_dict(env)


@pytest.mark.parametrize("bad, match", [({"friction_sampling": "normal"}, "friction_sampling must be one of"),
                                         ({"friction_sampling": "log_uniform", "friction_scale": [0.0, 3.0]}, "must be > 0")])
def test_friction_sampling_refuses_bad_input(bad, match):
    env = _cfg("2d")["env"]
    env["randomization"] = {**env["randomization"], **bad}
    with pytest.raises(ValueError, match=match):
        EnvConfig.from_dict(env)


def _valve_draws(coupling: str | None) -> dict[str, np.ndarray]:
    env = _cfg("2d")["env"]
    if coupling is not None:
        env["randomization"] = {**env["randomization"], "valve_coupling": coupling}
    core = ThrowEnvCore(EnvConfig.from_dict(env))
    state, _ = jax.jit(jax.vmap(core.reset))(jax.random.split(jax.random.PRNGKey(7), 4096))
    return {k: np.asarray(getattr(state, k)) for k in ("valve_delay", "tau", "dead_band", "vscale")}


def test_valve_coupling_all_sets_dead_band_and_speed_from_the_machine_slowness():
    """With valve_coupling "all" a slow machine (long lag) also has a wide dead band and a low
    full-open speed, so the slow-hydraulics corner of the ranges is drawn; by default the two are
    independent of the lag, and the default draws are those of a config without the entry."""
    rand = _cfg("2d")["env"]["randomization"]
    coupled, default, absent = _valve_draws("all"), _valve_draws("delay_lag"), _valve_draws(None)
    for k in default:
        np.testing.assert_array_equal(default[k], absent[k])
    for draws in (coupled, default):  # within the ranges either way
        assert draws["dead_band"].min() >= rand["dead_band"][0] - 1e-6 and draws["dead_band"].max() <= rand["dead_band"][1] + 1e-6
        assert draws["vscale"].min() >= rand["velocity_scale"][0] - 1e-6 and draws["vscale"].max() <= rand["velocity_scale"][1] + 1e-6
    slow = lambda d: d["tau"].mean(axis=1)  # noqa: E731
    assert np.corrcoef(slow(coupled), coupled["dead_band"].mean(axis=1))[0, 1] > 0.8
    assert np.corrcoef(slow(coupled), coupled["vscale"].mean(axis=1))[0, 1] < -0.8
    assert abs(np.corrcoef(slow(default), default["dead_band"].mean(axis=1))[0, 1]) < 0.1
    assert abs(np.corrcoef(slow(default), default["vscale"].mean(axis=1))[0, 1]) < 0.1

    def corner(d):  # every joint near the slow-hydraulics profile (dead band 0.10, lag 0.30, speed x0.85)
        return np.mean(np.all((d["dead_band"] >= 0.09) & (d["tau"] >= 0.26) & (d["vscale"] <= 0.88), axis=1))

    assert corner(coupled) > 0.05 and corner(default) < 0.001


def test_valve_coupling_refuses_bad_input():
    env = _cfg("2d")["env"]
    env["randomization"] = {**env["randomization"], "valve_coupling": "everything"}
    with pytest.raises(ValueError, match="valve_coupling must be one of"):
        EnvConfig.from_dict(env)
    # "all" acts through the machine-wide slowness: without it (valve_spread >= 1, the default) it
    # would be silently inert
    for spread in ({"valve_spread": 1.0}, {}):
        rand = {k: v for k, v in env["randomization"].items() if k != "valve_spread"}
        env["randomization"] = {**rand, "valve_coupling": "all", **spread}
        with pytest.raises(ValueError, match="valve_spread >= 1 turns off"):
            EnvConfig.from_dict(env)


def _critic_value(critic_state: dict, obs, groups: list[str], runner_cfg: dict) -> torch.Tensor:
    from rsl_rl.models import MLPModel

    kw = copy.deepcopy(runner_cfg["critic"])
    kw.pop("class_name")
    model = MLPModel(obs, {"critic": groups}, "critic", 1, **kw)
    model.load_state_dict(critic_state)
    model.eval()
    with torch.no_grad():
        return model(obs)


def test_resume_old_checkpoint_widens_critic_then_trains_and_exports(tmp_path):
    from rsl_rl.runners import OnPolicyRunner

    from sim_twin.training.export import export_checkpoint
    from sim_twin.training.vec_env import MjxThrowVecEnv

    cfg = _cfg("2d")
    cfg["num_envs"] = 8
    old = torch.load(CKPT_2D, map_location="cpu", weights_only=False)
    env = MjxThrowVecEnv(EnvConfig.from_dict(cfg["env"]), 8, seed=3)
    runner = OnPolicyRunner(env, copy.deepcopy(cfg["runner"]), log_dir=None, device="cpu")
    notes = critic_surgery.resume(runner, CKPT_2D, "cpu")
    assert runner.current_learning_iteration == old["iter"]
    assert any("critic input 56 -> 87" in n for n in notes)
    saved = runner.alg.save()
    for k, v in old["actor_state_dict"].items():  # the actor is untouched but for its std's parameterisation
        if k == "distribution.std_param":
            lo, hi = cfg["runner"]["actor"]["distribution_cfg"]["std_range"]
            torch.testing.assert_close(saved["actor_state_dict"]["distribution.log_std_param"], torch.log(v.clamp(lo, hi)))
            continue
        assert torch.equal(saved["actor_state_dict"][k], v), k
    crit = saved["critic_state_dict"]
    assert torch.equal(crit["mlp.0.weight"][:, :56], old["critic_state_dict"]["mlp.0.weight"])
    assert torch.all(crit["mlp.0.weight"][:, 56:] == 0)
    assert torch.equal(crit["obs_normalizer.count"], old["critic_state_dict"]["obs_normalizer.count"])
    adam = saved["optimizer_state_dict"]["state"]
    first = [i for i, st in adam.items() if st["exp_avg"].shape == (256, 87)]
    assert len(first) == 1 and torch.all(adam[first[0]]["exp_avg_sq"][:, 56:] == 0)
    assert torch.equal(adam[first[0]]["exp_avg"][:, :56], old["optimizer_state_dict"]["state"][first[0]]["exp_avg"])

    obs = env.get_observations()
    v_old = _critic_value(old["critic_state_dict"], obs, ["policy"], cfg["runner"])
    v_new = _critic_value(crit, obs, ["policy", "privileged"], cfg["runner"])
    torch.testing.assert_close(v_new, v_old, rtol=1e-6, atol=1e-5)

    # the exported actor is the same ONNX policy as the original checkpoint's
    widened = tmp_path / "widened.pt"
    runner.save(str(widened))
    a = export_checkpoint(CKPT_2D, cfg, tmp_path / "old.onnx", "old")
    b = export_checkpoint(widened, cfg, tmp_path / "new.onnx", "new")
    import onnxruntime as ort

    probe = np.random.default_rng(0).normal(size=(16, observation_size("2d"))).astype(np.float32)
    out = [ort.InferenceSession(str(p)).run(None, {"obs": probe})[0] for p in (a, b)]
    np.testing.assert_array_equal(out[0], out[1])

    runner.learn(num_learning_iterations=1)  # training continues on the widened critic
    assert all(torch.isfinite(p).all() for p in runner.alg.critic.parameters())


def test_surgery_refuses_to_narrow_and_is_a_no_op_when_shapes_match():
    old = torch.load(CKPT_2D, map_location="cpu", weights_only=False)
    shapes = [v["exp_avg"].shape for _, v in sorted(old["optimizer_state_dict"]["state"].items())]
    same, notes = critic_surgery.widen_critic(old, old["critic_state_dict"], shapes)
    assert notes == [] and same["critic_state_dict"] is old["critic_state_dict"]
    narrow = {k: (v[:, :40] if k == "mlp.0.weight" or k.endswith(("_mean", "_var", "_std")) else v)
              for k, v in old["critic_state_dict"].items()}
    with pytest.raises(ValueError, match="cannot narrow"):
        critic_surgery.widen_critic(old, narrow, shapes)


def _deployed_cfg(mode: str) -> dict:
    """The training config of the deployed policy version (policies/throw{mode}.json)."""
    return json.loads((REPO / f"policies/throw{mode}.json").read_text())["training"]["config"]


def _reset_priv(env_cfg: dict, n: int = 4, seed: int = 5):
    core = ThrowEnvCore(EnvConfig.from_dict(env_cfg))
    state, obs = jax.vmap(core.reset)(jax.random.split(jax.random.PRNGKey(seed), n))
    return state, np.asarray(obs), np.asarray(jax.vmap(core.privileged)(state))


@pytest.mark.parametrize("mode", ["2d", "3d"])
def test_finetune_config_keeps_the_trained_normalisation(mode):
    """A site fine-tuning config (ranges narrowed to [v, v]) normalises the critic's inputs over
    the base config's ranges: v = 0.2 s valve delay reads (0.2 - mid) / half of [0.05, 0.22], not 0."""
    from sim_twin.adaptation.adapt import finetune_config
    from sim_twin.twin.profile import RealityProfile

    base = _deployed_cfg(mode)
    prof = RealityProfile.from_dict({"effects": [{"effect": "valve_delay", "params": {"delay_s": 0.2}}]})
    cfg, fixed, _ = finetune_config(base, prof)
    env, orig = cfg["env"], base["env"]["randomization"]
    assert env["randomization"]["valve_delay_s"] == [0.2, 0.2] and fixed["valve_delay_s"] == pytest.approx(0.2)
    assert env["privileged_ranges"]["valve_delay_s"] == orig["valve_delay_s"] == [0.05, 0.22]
    state, obs, priv = _reset_priv(env)
    sl = _slices()
    lo, hi = orig["valve_delay_s"]
    np.testing.assert_allclose(priv[:, sl["valve_delay"]], (0.2 - (lo + hi) / 2) / ((hi - lo) / 2), rtol=1e-5)
    assert abs((0.2 - 0.135) / 0.085 - priv[0, 0]) < 1e-5
    for name, key in (("dead_band", "dead_band"), ("valve_lag", "lag_s"), ("friction_scale", "friction_scale")):
        lo, hi = orig[key]
        np.testing.assert_allclose(priv[:, sl[name]], (fixed[key] - (lo + hi) / 2) / ((hi - lo) / 2), rtol=1e-5, atol=1e-6)
    half = 2 * orig["release_delay_std_s"] + orig["release_delay_shift_s"]
    x = np.asarray(state.delay_steps) * 0.01
    np.testing.assert_allclose(priv[:, sl["release_delay"]][:, 0], (x - orig["release_delay_mean_s"]) / half, rtol=1e-5)
    # without the kept ranges the same episodes' narrowed inputs read 0, and the policy observation is the same
    del env["privileged_ranges"]
    _, obs_plain, priv_plain = _reset_priv(env)
    assert np.all(priv_plain[:, sl["valve_delay"]] == 0.0)
    np.testing.assert_array_equal(obs_plain, obs)


def test_normal_config_privileged_values_unchanged():
    """No ``privileged_ranges`` (normal training), or ones equal to the randomisation: the
    randomisation ranges, bit for bit."""
    from sim_twin.training.privileged import Randomization, privileged_observation, trained_ranges

    env = _deployed_cfg("2d")["env"]
    state, obs, priv = _reset_priv(env)
    hydraulic = env["randomization"]["actuation"] == "hydraulic"
    direct = np.asarray(jax.vmap(lambda s: privileged_observation(Randomization.from_dict(env["randomization"]), hydraulic, s))(state))
    np.testing.assert_array_equal(priv, direct)
    _, obs_same, priv_same = _reset_priv({**env, "privileged_ranges": trained_ranges(env["randomization"])})
    np.testing.assert_array_equal(priv_same, priv)
    np.testing.assert_array_equal(obs_same, obs)
