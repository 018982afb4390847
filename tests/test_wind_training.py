"""Wind in the training environment (``randomization.wind_mps``): the first-order landing shift
(sim_twin.twin.effects.site.wind_landing_shift) against the twin's RK4 flight under the ``wind``
effect, its JAX form against its NumPy form, the per-episode draw, and the environment's landing
under it (docs/training.md, "What the site's air takes from a throw")."""

import json

import numpy as np
import pytest

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402

from runtime.ballistics import PAYLOAD_RADIUS_M, ballistic_impact_time, ballistic_position  # noqa: E402
from sim_twin.training.config import CONFIG_DIR  # noqa: E402
from sim_twin.training.mjx_env import EnvConfig, ThrowEnvCore  # noqa: E402
from sim_twin.twin.effects.payload import integrate_flight  # noqa: E402
from sim_twin.twin.effects.site import Wind, wind_landing_shift  # noqa: E402


def _releases(n: int, seed: int = 0):
    """Releases as the far throws make them (reports/training_release_flight_2d.md: 2-5 m/s, -20 to
    50 degrees, 1.4-2.5 m high, 6-7 m out) and winds up to 5 m/s in any direction."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        speed, el = rng.uniform(2.0, 5.0), np.radians(rng.uniform(-20.0, 50.0))
        az = rng.uniform(-0.3, 0.3)
        p0 = np.array([6.5 * np.cos(az), 6.5 * np.sin(az), rng.uniform(1.4, 2.5)])
        v0 = speed * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        w = rng.uniform(0.0, 5.0) * np.array([np.cos(a := rng.uniform(-np.pi, np.pi)), np.sin(a)])
        yield p0, v0, w


def test_the_first_order_shift_is_the_twins_rk4_flight_under_the_wind_within_ten_per_cent():
    worst = 0.0
    for p0, v0, w in _releases(100):
        _, _, _, _, hit_w = integrate_flight(p0, v0, Wind(wind_x_mps=w[0], wind_y_mps=w[1]).flight_accel)
        _, _, _, _, hit_0 = integrate_flight(p0, v0, None)
        true = (hit_w - hit_0)[:2]
        est = wind_landing_shift(np, p0, v0, ballistic_impact_time(np, p0, v0, PAYLOAD_RADIUS_M), w)
        assert np.linalg.norm(est - true) <= 0.10 * np.linalg.norm(true) + 0.005, (p0, v0, w, true, est)
        worst = max(worst, np.linalg.norm(true))
    assert worst > 0.3  # the cases include winds that move the landing by tens of centimetres
    p0, v0, _ = next(_releases(1))
    assert np.all(wind_landing_shift(np, p0, v0, 1.0, np.zeros(2)) == 0.0)  # no wind, no shift


def test_the_jax_shift_is_the_numpy_one():
    for p0, v0, w in _releases(10, seed=1):
        t = ballistic_impact_time(np, p0, v0, PAYLOAD_RADIUS_M)
        ref = wind_landing_shift(np, p0, v0, t, w)
        got = jax.jit(lambda a, b, c, d: wind_landing_shift(jnp, a, b, c, d))(
            *(jnp.asarray(x, jnp.float32) for x in (p0, v0, t, w)))
        np.testing.assert_allclose(np.asarray(got), ref, atol=2e-4)


def _env(wind_mps: float, **more) -> ThrowEnvCore:
    env = json.loads((CONFIG_DIR / "throw_2d.json").read_text())["env"]
    env = {**env, "forced_release": {**env["forced_release"], "probability": 0.0},
           "randomization": {**env["randomization"], "wind_mps": wind_mps, **more}}
    return ThrowEnvCore(EnvConfig.from_dict(env))


def test_episodes_draw_winds_up_to_the_largest_speed_in_every_direction_and_none_without():
    keys = jax.random.split(jax.random.PRNGKey(0), 256)
    winds = np.asarray(jax.vmap(_env(5.0)._sample_wind)(keys))  # what reset draws into EnvState.wind
    speed = np.linalg.norm(winds, axis=1)
    assert speed.max() <= 5.0 + 1e-5 and speed.min() < 0.5 and speed.max() > 4.5
    assert np.all(np.bincount(np.digitize(np.arctan2(winds[:, 1], winds[:, 0]), np.linspace(-np.pi, np.pi, 5)[1:-1]), minlength=4) > 30)
    calm = np.asarray(jax.vmap(_env(0.0)._sample_wind)(keys[:8]))
    assert np.all(calm == 0.0)
    with pytest.raises(ValueError, match="wind_mps"):
        _env(-1.0)


def test_a_share_of_windy_episodes_leaves_the_others_in_still_air():
    """``wind_fraction`` 0.25: about a quarter of the episodes draw a wind, and the same winds as with
    every episode windy (the same key, the speed kept or zeroed); outside [0, 1] it is refused."""
    keys = jax.random.split(jax.random.PRNGKey(1), 2000)
    every = np.asarray(jax.vmap(_env(5.0)._sample_wind)(keys))
    share = np.asarray(jax.vmap(_env(5.0, wind_fraction=0.25)._sample_wind)(keys))
    windy = np.linalg.norm(share, axis=1) > 0.0
    assert 0.21 < windy.mean() < 0.29  # 500 expected of 2000; 4 binomial standard deviations is 0.039
    np.testing.assert_allclose(share[windy], every[windy])
    for bad in (-0.1, 1.5, True, "half"):
        with pytest.raises(ValueError, match="wind_fraction must be a number in"):
            _env(5.0, wind_fraction=bad)


def test_the_environment_lands_the_payload_where_the_wind_moves_it():
    """A throw in the training environment with a 5 m/s wind: the landing error it reports is the
    drag-free landing moved by the shift of the episode's wind, not the drag-free one."""
    core = _env(5.0)
    reset = jax.jit(core.reset)
    state = next(s for s in (reset(jax.random.PRNGKey(k))[0] for k in range(50)) if float(jnp.linalg.norm(s.wind)) > 3.0)
    step = jax.jit(core.step)
    for k in range(60):  # dipper and telescope out at 0.6 of full speed, release commanded at step 8
        state, _, _, terminated, _, info = step(state, jnp.asarray([0.0, 0.6, 0.6, 1.0 if k >= 8 else -1.0], jnp.float32))
        if bool(terminated):
            break
    assert bool(info["landed"])
    p0, v0, t, w, target = (np.asarray(x, float) for x in (state.ball_p0, state.ball_v0, state.t_flight, state.wind, state.target))
    free = ballistic_position(np, p0, v0, t)[:2]
    shift = wind_landing_shift(np, p0, v0, t, w)
    assert np.linalg.norm(shift) > 0.02
    assert float(info["impact_err_m"]) == pytest.approx(np.linalg.norm(free + shift - target[:2]), abs=2e-3)
    assert abs(float(info["impact_err_m"]) - np.linalg.norm(free - target[:2])) > 0.01
