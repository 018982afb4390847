"""tests/benchmarks/training_twin_bias.py: its training-environment side and its twin side throw the
same start poses and give finite landings and releases (a smoke test of the benchmark's two sides,
not of its figures)."""

from __future__ import annotations

import math

import numpy as np
import pytest

jax = pytest.importorskip("jax")
pytest.importorskip("onnxruntime")
pytestmark = pytest.mark.torch  # the training extra (jax, mujoco-mjx)

from runtime.observation import PHYSICS_PERIOD_S  # noqa: E402
from sim_twin.evaluation.evaluate import target_on_axis, throw_seeds  # noqa: E402
from tests.benchmarks.training_twin_bias import (  # noqa: E402
    DEFAULT_CONFIG,
    DEFAULT_POLICY,
    EnvSide,
    nominal_env_config,
    paired,
    twin_profile,
    twin_start,
    twin_throws,
)

FIELDS = ("downrange_m", "ballistic_downrange_m", "release_cmd_s", "opening_s", "speed_mps", "elevation_deg", "height_m", "flight_s")


def test_both_sides_throw_the_same_starts_and_land():
    seeds = throw_seeds(0, 5, 2)  # the site matrix's 10 m cell, its first two start poses
    starts = [twin_start(s, twin_profile(False)) for s in seeds]
    poses, delays = np.array([q for q, _ in starts]), np.array([d for _, d in starts])
    targets = np.array([target_on_axis("2d", 10.0)] * len(seeds))

    twin = twin_throws(DEFAULT_POLICY, 10.0, seeds, None)
    side = EnvSide(DEFAULT_POLICY, nominal_env_config(DEFAULT_CONFIG, False))
    state, _ = side.reset(jax.random.split(jax.random.PRNGKey(0), len(seeds)), poses.astype(np.float32), targets.astype(np.float32))
    np.testing.assert_allclose(np.asarray(state.data.qpos), poses, atol=1e-6)  # the twin's start pose
    np.testing.assert_allclose(np.asarray(state.target), targets, atol=1e-5)
    env = side.throws(targets, poses, seeds, delays, "ceil")

    for rows in (twin, env):
        assert [r["seed"] for r in rows] == seeds
        for r in rows:
            assert r["landed"], r
            assert all(math.isfinite(r[k]) for k in FIELDS), r
            assert "wind_downrange_m" not in r  # still air: no wind shift
            # both open after the twin's drawn delay, at the first physics step at or after it
            steps = math.ceil(delays[seeds.index(r["seed"])] / PHYSICS_PERIOD_S - 1e-6)
            assert r["opening_s"] - r["release_cmd_s"] == pytest.approx(steps * PHYSICS_PERIOD_S, abs=1e-6)
    p = paired(twin, env)
    assert p["pairs"] == len(seeds) and math.isfinite(p["downrange_m"][0])


def test_the_environment_is_the_one_after_the_curriculum_stage_and_the_nominal_machine_is_calm():
    """A policy of the sites recipe finished training in the stage's ranges (friction x0.5-10, wind
    up to 5 m/s): the training distribution is those, the nominal machine throws in still air, and a
    landing in the wind is moved by the environment's own wind shift."""
    from tests.benchmarks.training_twin_bias import REPO

    cfg = REPO / "sim_twin" / "configs" / "throw_2d_sites.json"
    dist = nominal_env_config(cfg, False, nominal=False)["randomization"]
    assert dist["friction_scale"] == [0.5, 10.0] and dist["wind_mps"] == 5.0
    nominal = nominal_env_config(cfg, False)["randomization"]
    assert nominal["friction_scale"] == [1.0, 1.0] and nominal["wind_mps"] == 0.0
    assert "wind_mps" not in nominal_env_config(DEFAULT_CONFIG, False)["randomization"]  # a recipe without stage or wind: as it was

    seeds = throw_seeds(0, 5, 2)
    starts = [twin_start(s, twin_profile(False)) for s in seeds]
    poses = np.array([q for q, _ in starts])
    targets = np.array([target_on_axis("2d", 10.0)] * len(seeds))
    env_cfg = nominal_env_config(DEFAULT_CONFIG, False, nominal=False)
    env_cfg["randomization"] = {**env_cfg["randomization"], "wind_mps": 5.0}
    for w in EnvSide(DEFAULT_POLICY, env_cfg).throws(targets, poses, seeds):
        assert w["landed"] and w["wind_downrange_m"] != 0.0 and abs(w["wind_downrange_m"]) < 1.0
        assert -0.2 < w["wind_mean_downrange_m"] < 0.0  # on average a wind takes from a throw (quadratic drag)
        assert w["downrange_m"] == pytest.approx(w["ballistic_downrange_m"] + w["wind_downrange_m"], abs=0.02)


def test_the_winds_mean_loss_is_a_loss_growing_as_the_squared_wind_and_scaled_by_the_windy_share():
    """mean_wind_shift: zero without wind; negative (on average a wind takes from a throw, quadratic
    drag); to second order in the wind, so twice the largest speed about four times the loss; a
    quarter of the episodes windy a quarter of it."""
    from tests.benchmarks.training_twin_bias import mean_wind_shift

    release = (np.array([10.0, 0.0, 0.0]), np.array([2.8, 0.0, 2.5]), np.array([6.8, 0.0, 2.9]), 1.0)
    assert mean_wind_shift(*release, 0.0) == 0.0
    full = mean_wind_shift(*release, 5.0)
    assert -0.2 < full < 0.0
    assert 3.5 < full / mean_wind_shift(*release, 2.5) < 4.5
    assert mean_wind_shift(*release, 5.0, wind_fraction=0.25) == pytest.approx(full / 4)
