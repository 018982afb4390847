"""The mean against the sampled actor (tests/benchmarks/training_release_noise.py) on a kept run,
throw2d-scratch-b1 (the candidate recipe without forced release): played with the actor's mean, an
episode releases exactly when its mean's flag crosses 0.9; with PPO's noise the played action is not
the mean; and both settings see the same episodes (targets from one PRNG key)."""

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("jax")
pytestmark = pytest.mark.torch  # the training extra (jax, mujoco-mjx, rsl_rl)

from runtime.observation import RELEASE_THRESHOLD  # noqa: E402
from tests.benchmarks.training_release_noise import release_episodes, summarise  # noqa: E402
from tests.benchmarks.training_style_probe import play, probe_actor  # noqa: E402
from tests.benchmarks.training_throw_style import RunSource  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ENVS = 24


@pytest.fixture(scope="module")
def run():
    src = RunSource(str(ROOT / "policies" / "training" / "throw2d-scratch-b1"))
    cfg = json.loads(src.read("config.json"))
    with tempfile.TemporaryDirectory() as tmp:
        onnx_path, _ = probe_actor(src, cfg, Path(tmp))
        yield onnx_path, cfg["env"]


def test_the_mean_releases_exactly_where_its_flag_crosses_the_threshold(run):
    onnx_path, env = run
    mean = release_episodes(onnx_path, env, ENVS, 0.0)
    sampled = release_episodes(onnx_path, env, ENVS, 0.05)
    np.testing.assert_array_equal(mean["target_m"], sampled["target_m"])  # the same episodes
    assert mean["released"].any()
    # the flag before (and at) the release: above the threshold where the mean released, never where it did not
    assert np.all(mean["flag_max"][mean["released"]] > RELEASE_THRESHOLD)
    assert np.all(mean["flag_max"][~mean["released"]] <= RELEASE_THRESHOLD)
    assert np.all((mean["release_s"][mean["released"]] > 0) & (mean["release_s"][mean["released"]] <= 10.0))
    assert np.all(np.isnan(mean["release_s"][~mean["released"]]))
    bands = summarise(mean)
    assert bands[-1]["band"] == "all" and bands[-1]["episodes"] == ENVS
    assert sum(b["episodes"] for b in bands[:-1]) == ENVS
    assert bands[-1]["released"] == pytest.approx(mean["released"].mean())


def test_the_sampled_actor_plays_the_mean_plus_noise(run):
    onnx_path, env = run
    env = {**env, "forced_release": {**env.get("forced_release", {}), "probability": 0.0}}
    info = next(play(onnx_path, env, 8, key=3, action_std=0.05))[3]
    assert 0.02 < (info["action"] - info["action_mean"]).std() < 0.08
    info = next(play(onnx_path, env, 8, key=3))[3]
    np.testing.assert_array_equal(info["action"], info["action_mean"])
