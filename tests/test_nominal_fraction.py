"""A share of training episodes on the nominal machine (``env.randomization.nominal_fraction``):
those episodes get sim_twin.training.mjx_env.nominal_machine's parameters, the others the draw they
would have had without the option, and 0 draws nothing (docs/training.md, "Four more seeds, and the
far-target overshoot")."""

import copy
import json

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytestmark = pytest.mark.torch  # the training extra (jax, mujoco-mjx)

from runtime.observation import PHYSICS_PERIOD_S  # noqa: E402
from sim_twin.training.config import CONFIG_DIR  # noqa: E402
from sim_twin.training.mjx_env import EnvConfig, ThrowEnvCore, nominal_machine  # noqa: E402
from sim_twin.training.privileged import check_randomization  # noqa: E402

FIELDS = ("fric", "gripper_scale", "gain", "tau", "dead_band", "vscale", "valve_delay", "sensor_lag", "grasp", "delay_steps")
N = 256


def _resets(fraction: float | None):
    env = json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]
    rand = copy.deepcopy(env["randomization"])
    rand["grasp_forward_m"], rand["grasp_up_m"] = [-0.05, 0.05], [-0.05, 0.05]  # a drawn grasp to tell apart
    if fraction is not None:
        rand["nominal_fraction"] = fraction
    core = ThrowEnvCore(EnvConfig.from_dict({**env, "randomization": rand}))
    state, _ = jax.jit(jax.vmap(core.reset))(jax.random.split(jax.random.PRNGKey(7), N))
    return {k: np.asarray(getattr(state, k)) for k in FIELDS}


@pytest.fixture(scope="module")
def draws():
    return {f: _resets(f) for f in (None, 0.0, 0.5, 1.0)}


def _is_nominal(s: dict) -> np.ndarray:
    """(N,) which episodes carry nominal_machine's parameters."""
    nom = nominal_machine()
    lag = [round(nom["encoder_latency_s"] / PHYSICS_PERIOD_S), round(nom["imu_latency_s"] / PHYSICS_PERIOD_S)]
    return ((s["fric"] == 1.0) & (s["gripper_scale"] == 1.0) & np.all(s["gain"] == 1.0, axis=1)
            & np.all(np.isclose(s["tau"], nom["lag_s"]), axis=1) & np.all(np.isclose(s["dead_band"], nom["dead_band"]), axis=1)
            & np.all(s["vscale"] == 1.0, axis=1) & np.all(s["valve_delay"] == round(nom["valve_delay_s"] / PHYSICS_PERIOD_S), axis=1)
            & np.all(s["sensor_lag"] == lag, axis=1) & np.all(s["grasp"] == 0.0, axis=1))


def test_zero_draws_nothing_and_one_makes_every_episode_nominal(draws):
    for k in FIELDS:
        np.testing.assert_array_equal(draws[0.0][k], draws[None][k], err_msg=k)  # key for key
    assert not _is_nominal(draws[None]).any()
    assert _is_nominal(draws[1.0]).all()


def test_a_share_of_episodes_is_nominal_and_the_rest_keep_their_draw(draws):
    on = _is_nominal(draws[0.5])
    assert 0.4 * N < on.sum() < 0.6 * N
    for k in FIELDS:
        np.testing.assert_array_equal(draws[0.5][k][~on], draws[None][k][~on], err_msg=k)
    # the release delay keeps its per-throw jitter but loses the episode shift where nominal
    assert np.unique(draws[1.0]["delay_steps"]).size > 1


@pytest.mark.parametrize("bad", [-0.1, 1.5, "half", True, None])
def test_a_fraction_outside_zero_to_one_is_refused(bad):
    with pytest.raises(ValueError, match="nominal_fraction must be a number in"):
        check_randomization({"nominal_fraction": bad})
