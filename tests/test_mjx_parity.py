"""The MJX training environment and the runtime share one observation definition: for the same
state they must produce the same observation vector (to float32 precision), and the MJX physics
must follow the CPU MuJoCo twin for the same commands."""

from __future__ import annotations

import dataclasses
import json

import mujoco
import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytestmark = pytest.mark.torch  # the training extra (jax, mujoco-mjx)
jnp = jax.numpy

from runtime.machine import forward_kinematics  # noqa: E402
from runtime.observation import build_observation, observation_size  # noqa: E402
from sim_twin.training.config import CONFIG_DIR  # noqa: E402
from sim_twin.training.mjx_env import EnvConfig, ThrowEnvCore  # noqa: E402
from sim_twin.twin.model import load_model  # noqa: E402


@pytest.fixture(scope="module", params=["2d", "3d"])
def env_and_state(request):
    cfg = EnvConfig.from_dict(json.loads((CONFIG_DIR / f"throw_{request.param}.json").read_text())["env"])
    core = ThrowEnvCore(cfg)
    state, _ = jax.jit(core.reset)(jax.random.PRNGKey(3))
    step = jax.jit(core.step)
    rng = np.random.default_rng(0)
    for _ in range(6):  # move away from rest so velocities and history are non-trivial
        action = jnp.asarray(np.append(rng.uniform(-1, 1, core.num_act - 1), -1.0), dtype=jnp.float32)
        state, obs, *_ = step(state, action)
    return core, state, obs, step


def test_observation_parity_mjx_vs_runtime(env_and_state):
    core, state, obs_mjx, _ = env_and_state
    as64 = {k: np.asarray(getattr(state, k), dtype=np.float64) for k in ("q_hist", "qd_hist", "prev_action", "target")}
    obs_rt = build_observation(np, core.mode, as64["q_hist"], as64["qd_hist"], as64["prev_action"], as64["target"], float(state.opened))
    assert obs_rt.shape == (observation_size(core.mode),) == np.asarray(obs_mjx).shape
    np.testing.assert_allclose(np.asarray(obs_mjx), obs_rt, rtol=2e-5, atol=2e-4)
    assert np.abs(as64["qd_hist"]).max() > 1e-3  # the state really moved


def test_runtime_kinematics_match_mujoco_site(env_and_state):
    _, state, _, _ = env_and_state
    model = load_model()
    data = mujoco.MjData(model)
    data.qpos[:] = np.asarray(state.data.qpos, dtype=float)
    data.qvel[:] = np.asarray(state.data.qvel, dtype=float)
    mujoco.mj_forward(model, data)
    site = model.site("gripper_centre").id
    vel6 = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_SITE, site, vel6, 0)
    pts = forward_kinematics(np, data.qpos.copy(), data.qvel.copy())
    np.testing.assert_allclose(pts.gripper_centre, data.site_xpos[site], atol=1e-9)
    np.testing.assert_allclose(pts.gripper_centre_vel, vel6[3:], atol=1e-9)


def test_mjx_physics_follows_cpu_twin():
    """Same MJCF, same servo setpoints and passive friction: MJX (float32) and MuJoCo (float64)
    stay within a few mrad over one second of a swing."""
    from mujoco import mjx

    from sim_twin.twin.model import passive_inertia
    from sim_twin.twin.physics import passive_friction_force

    model = load_model()
    data = mujoco.MjData(model)
    data.qpos[:] = [0.0, -0.7, 1.6, 0.8, -0.9, 0.0]
    mujoco.mj_forward(model, data)
    mx = mjx.put_model(model)
    dx = mjx.put_data(model, data)
    inertia = passive_inertia()
    setpoint = np.array([0.0, -0.4, 0.5, 0.6])

    @jax.jit
    def mjx_step(d):
        f = passive_friction_force(jnp, d.qvel[4:6], jnp.asarray(inertia, dtype=jnp.float32))
        d = d.replace(ctrl=jnp.asarray(setpoint, dtype=jnp.float32), qfrc_applied=jnp.zeros(6).at[4:6].set(f))
        return mjx.step(mx, d)

    for _ in range(100):
        data.ctrl[:] = setpoint
        data.qfrc_applied[4:6] = passive_friction_force(np, data.qvel[4:6], inertia)
        mujoco.mj_step(model, data)
        dx = mjx_step(dx)
    assert np.abs(data.qpos[4]) > 0.1  # the gripper swung
    np.testing.assert_allclose(np.asarray(dx.qpos), data.qpos, atol=5e-3)


def test_mjx_env_closed_valves_hold_the_load(env_and_state):
    """Zero velocity references for 4 s of physics (no command noise): the training env's arm
    holds as the simulated machine's does (tests/test_hydraulics.py); without the cylinder hold
    the boom sagged ~7 mrad and the telescope ~15 mm."""
    core, state, _, _ = env_and_state
    if core.mode != "2d":
        pytest.skip("one mode suffices: the actuation is the same (compiling it costs ~20 s)")
    run = jax.jit(lambda s: jax.lax.fori_loop(0, 400, lambda _, st: core._substep(st, jnp.zeros(4)), s))
    settled = run(state)
    q0 = np.asarray(settled.data.qpos[:4])
    q1 = np.asarray(run(settled).data.qpos[:4])
    assert np.abs(q1 - q0).max() < 1e-3, q1 - q0



def _per_env_autoreset(core, s, action):
    """Reference: one environment's step, then its reset when the episode ended (the per-env form
    MuJoCo Warp cannot trace under vmap)."""
    s1, obs, rew, term, tout, info = core.step(s, action)
    done = term | tout
    key, k_reset = jax.random.split(s1.key)
    s_new, obs_new = core.reset(k_reset)
    s_out = jax.tree_util.tree_map(lambda n, o: jnp.where(done, n, o), s_new, s1.replace(key=key))
    return s_out, jnp.where(done, obs_new, obs), rew, done, tout, info


@pytest.mark.parametrize(("reset_slots", "n_left"), [(None, [2, 0, 2, 1]), (0.5, [2, 0, 2, 1]), (0.5, [2, 2, 2, 1]), (0.25, [0, 0, 1, 2])])
def test_batch_autoreset_equals_the_vmapped_autoreset(reset_slots, n_left):
    """step_autoreset_batch (the form MuJoCo Warp can trace) gives what the vmapped per-env
    autoreset gives: finished episodes replaced by fresh ones drawn with the same keys, whether
    the whole batch is reset (``reset_slots`` None) or only the finished environments gathered
    into a fraction of it (0.5 of 4: two slots; two finish, then three finish and it falls back to
    the whole batch; 0.25: one slot, one finishes). Checked on a small stand-in environment (the
    method only calls ``step`` and ``reset``), which keeps the test free of compiling the physics."""
    @jax.tree_util.register_dataclass
    @dataclasses.dataclass(frozen=True)
    class ToyState:  # what step_autoreset_batch asks of a state: a pytree with a key and replace()
        key: jax.Array
        x: jax.Array
        n: jax.Array

        def replace(self, **kw):
            return dataclasses.replace(self, **kw)

    class Toy:
        def __init__(self, slots):
            self.reset_slots = slots

        def reset(self, key):
            x = jax.random.uniform(key, (3,))
            return ToyState(key=key, x=x, n=jnp.zeros((), jnp.int32)), x * 2

        def step(self, s, a):
            n = s.n + 1
            x = s.x + a
            s1 = s.replace(x=x, n=n)
            return s1, x, jnp.sum(x), n >= 3, jnp.asarray(False), {"n": n}

        step_autoreset_batch = ThrowEnvCore.step_autoreset_batch

    toy = Toy(reset_slots)
    state, _ = jax.vmap(toy.reset)(jax.random.split(jax.random.PRNGKey(5), 4))
    state = state.replace(n=jnp.asarray(n_left, jnp.int32))
    action = jnp.ones((4, 3))
    a = jax.jit(jax.vmap(lambda s, act: _per_env_autoreset(toy, s, act)))(state, action)
    b = jax.jit(toy.step_autoreset_batch)(state, action)
    assert np.asarray(b[3]).tolist() == [n == 2 for n in n_left]
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert np.asarray(b[0].n).tolist() == [0 if n == 2 else n + 1 for n in n_left]


def test_reset_slots_outside_a_fraction_are_refused():
    with pytest.raises(ValueError, match="reset_slots"):
        ThrowEnvCore(EnvConfig.from_dict(json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]), reset_slots=1.5)


def test_joint_limit_constraints_do_not_change_training_trajectories():
    """The training model drops the MJCF's joint-limit constraints (ThrowEnvCore's joint_limits):
    an episode fails within 1 mrad / 1 mm of a range and the cylinders stop at the same ends. Random
    commands, and full commands that drive the boom, dipper and telescope towards each end, give the
    same states with and without the constraints up to each episode's first failure, and the driven
    joints come close to their ends (the controller's limit ramp slows them there)."""
    from runtime.machine import JOINT_LOWER, JOINT_UPPER

    cfg = EnvConfig.from_dict(json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"])
    n_random, steps = 10, 60
    driven = [(j, sign) for j in (0, 1, 2) for sign in (1.0, -1.0)]  # action j drives active joint j + 1
    n = n_random + len(driven)
    keys = jax.random.split(jax.random.PRNGKey(11), n)
    rand = np.clip(0.9 * np.asarray(jax.random.normal(jax.random.PRNGKey(12), (steps, n_random, 4))), -1.0, 1.0)
    push = np.zeros((steps, len(driven), 4))
    for i, (j, sign) in enumerate(driven):
        push[:, i, j] = sign
    actions = jnp.asarray(np.concatenate([rand, push], axis=1), jnp.float32).at[..., -1].set(-1.0)  # never release
    runs = []
    for limits in (True, False):
        core = ThrowEnvCore(cfg, joint_limits=limits)
        assert core.joint_limits is limits
        state, _ = jax.jit(jax.vmap(core.reset))(keys)
        step = jax.jit(jax.vmap(core.step))
        qs, failed = [], []
        for a in actions:
            state, _, _, _, _, info = step(state, a)
            qs.append(np.asarray(state.data.qpos))
            failed.append(np.asarray(info["failed"]))
        runs.append((np.stack(qs), np.stack(failed)))
    (q_on, failed_on), (q_off, _) = runs
    for i in range(n):  # up to and including the first failure (after it the episode is over)
        end = int(np.argmax(failed_on[:, i])) + 1 if failed_on[:, i].any() else steps
        np.testing.assert_allclose(q_off[:end, i], q_on[:end, i], atol=1e-6)
    travel = q_on[:, :n_random, 1:4].max(axis=(0, 1)) - q_on[:, :n_random, 1:4].min(axis=(0, 1))
    assert (travel > 0.2).all()  # boom, dipper and telescope really moved
    lo, hi = np.asarray(JOINT_LOWER[1:4]), np.asarray(JOINT_UPPER[1:4])
    margin = np.minimum(q_on[:, n_random:, 1:4] - lo, hi - q_on[:, n_random:, 1:4]).min(axis=(0, 1))
    assert (margin < 0.1).sum() >= 2, margin  # the pushes took joints to near their ends


def test_a_graph_mode_is_checked_and_only_passed_to_the_warp_implementation():
    from sim_twin.training.mjx_env import _graph_mode_arg

    assert _graph_mode_arg("jax", "WARP") == {} and _graph_mode_arg("warp", None) == {}
    with pytest.raises(ValueError, match="unknown graph_mode 'BOGUS'"):
        _graph_mode_arg("warp", "BOGUS")


def test_a_longer_history_recipe_trains_exports_and_loads_with_its_own_observation(tmp_path):
    """sim_twin/configs/throw_2d_history.json (8 control steps of joint history): the environment's
    observations are the runtime's for the same state (96 values), its history shifts one row per
    control step, one PPO iteration runs on it, and the export declares 8 steps in its manifest's
    observation_layout, which the runtime reads back."""
    import copy

    import torch
    from rsl_rl.runners import OnPolicyRunner

    from runtime.policy import PolicyRunner
    from sim_twin.training.export import export_checkpoint
    from sim_twin.training.vec_env import MjxThrowVecEnv

    cfg = json.loads((CONFIG_DIR / "throw_2d_history.json").read_text())
    env_cfg = EnvConfig.from_dict(cfg["env"])
    core = ThrowEnvCore(env_cfg)
    state, obs = jax.jit(core.reset)(jax.random.PRNGKey(5))
    assert core.num_obs == 96 and obs.shape == (96,)
    step, rng, previous = jax.jit(core.step), np.random.default_rng(1), state
    for _ in range(10):
        action = jnp.asarray(np.append(rng.uniform(-1, 1, core.num_act - 1), -1.0), dtype=jnp.float32)
        previous, (state, obs, *_) = state, step(state, action)
        np.testing.assert_array_equal(np.asarray(state.q_hist[1:]), np.asarray(previous.q_hist[:-1]))
        np.testing.assert_array_equal(np.asarray(state.qd_hist[1:]), np.asarray(previous.qd_hist[:-1]))
    as64 = {k: np.asarray(getattr(state, k), dtype=np.float64) for k in ("q_hist", "qd_hist", "prev_action", "target")}
    obs_rt = build_observation(np, "2d", as64["q_hist"], as64["qd_hist"], as64["prev_action"], as64["target"], float(state.opened))
    assert obs_rt.shape == (96,)
    np.testing.assert_allclose(np.asarray(obs), obs_rt, rtol=2e-5, atol=2e-4)
    assert np.ptp(as64["q_hist"][:, 1:], axis=0).max() > 1e-3  # eight different steps, not one repeated

    cfg["num_envs"] = 8
    cfg["runner"]["torch_compile_mode"] = None  # the recipe compiles for the GPU; minutes of CPU here for nothing tested
    vec = MjxThrowVecEnv(env_cfg, 8, seed=3)
    runner = OnPolicyRunner(vec, copy.deepcopy(cfg["runner"]), log_dir=None, device="cpu")
    runner.learn(num_learning_iterations=1)
    assert all(torch.isfinite(p).all() for p in runner.alg.actor.parameters())
    runner.save(str(tmp_path / "model.pt"))
    path = export_checkpoint(tmp_path / "model.pt", cfg, tmp_path / "h8.onnx", "h8")
    manifest = json.loads(path.with_suffix(".json").read_text())
    assert manifest["observation_size"] == 96 and manifest["observation_layout"][0] == ["joint_pos_history", 40]
    assert PolicyRunner.load(path).history_steps == 8
