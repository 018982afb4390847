"""A policy's observation history length is its own (runtime.observation, ``env.history_steps``):
the manifest's observation_layout declares it, the runtime refuses a layout or a graph that does
not fit it, and the executor keeps exactly as many control steps of joint history as the loaded
policy reads, newest first, shifted one row per 12.5 Hz control step."""

from __future__ import annotations

import json

import numpy as np
import pytest

from runtime.executor import ExecutorConfig, ThrowExecutor
from runtime.observation import (
    HISTORY_STEPS,
    MAX_HISTORY_STEPS,
    history_steps_of_layout,
    observation_layout,
    observation_size,
)
from runtime.policy import PolicyError, PolicyRunner
from runtime.protocol.messages import ThrowRequest
from runtime.throw_geometry import ARM_PLANE_OFFSET_M
from sim_twin.twin.simulated_machine import SimulatedMachine
from sim_twin.twin.twin_machine import TwinMachine, run_throw
from tests.fixtures import write_test_policy
from tests.test_executor import RecordingPolicy


@pytest.mark.parametrize(("mode", "steps", "size"), [("2d", 4, 56), ("3d", 4, 65), ("2d", 8, 96), ("3d", 8, 113), ("2d", 1, 26)])
def test_the_observation_size_follows_the_history_length(mode, steps, size):
    assert observation_size(mode, steps) == size
    assert history_steps_of_layout(mode, [list(b) for b in observation_layout(mode, steps)]) == steps


@pytest.mark.parametrize("steps", [0, MAX_HISTORY_STEPS + 1])
def test_a_history_length_outside_its_bounds_is_refused(steps):
    with pytest.raises(ValueError, match="history_steps must be"):
        observation_layout("2d", steps)


@pytest.mark.parametrize(
    ("layout", "why"),
    [
        ([["joint_pos_history", 42], ["joint_vel_history", 42]], "not 1..25 steps of 5 joints"),  # 8.4 steps
        ([["joint_pos_history", 40], ["joint_vel_history", 20]], "is not this runtime's for 8 history steps"),
        ([], "no joint_pos_history block"),
        ("garbage", "no joint_pos_history block"),
    ],
)
def test_a_layout_that_is_no_history_length_is_refused_with_the_reason(layout, why):
    with pytest.raises(ValueError, match=why):
        history_steps_of_layout("2d", layout)


def test_the_runtime_refuses_a_manifest_whose_history_does_not_fit_its_graph(tmp_path):
    path = write_test_policy(tmp_path, "2d", history_steps=8)
    manifest = json.loads(path.with_suffix(".json").read_text())
    assert PolicyRunner.load(path).history_steps == 8
    # the graph reads 96 values; a manifest that declares the paper's 4 steps (56) does not fit it
    manifest.update(observation_layout=[list(b) for b in observation_layout("2d")], observation_size=56)
    path.with_suffix(".json").write_text(json.dumps(manifest))
    with pytest.raises(PolicyError, match=r"policy input has 96 features, mode 2d with 4 history steps needs 56 \(it fits 8 history steps"):
        PolicyRunner.load(path)
    manifest.update(observation_layout=[["joint_pos_history", 40]], observation_size=96)
    path.with_suffix(".json").write_text(json.dumps(manifest))
    with pytest.raises(PolicyError, match="observation_layout does not match this runtime"):
        PolicyRunner.load(path)


@pytest.mark.parametrize("steps", [HISTORY_STEPS, 8])
def test_the_executor_keeps_as_many_history_steps_as_the_policy_reads(tmp_path, steps):
    """A throw with a policy of ``steps`` history steps: every observation has that policy's size,
    the first is filled with the swing's start state, and each later one's history is the previous
    one's shifted by a row with the newest measurement in front."""
    runner = PolicyRunner.load(write_test_policy(tmp_path, "2d", release_after_bias=2.0, history_steps=steps))
    policy = RecordingPolicy(runner)
    ex = ThrowExecutor({"2d": policy}, config=ExecutorConfig(release_check_radius_m=None))
    request = ThrowRequest(throw_id="t1", machine_id="m1", mode="2d", target_m=[8.0, ARM_PLANE_OFFSET_M, 0.0])
    outcome, _ = run_throw(TwinMachine(SimulatedMachine(seed=1), "m1"), ex, request)
    assert outcome.status == "landed"
    obs = np.stack(policy.observations)
    assert obs.shape[1] == observation_size("2d", steps) and len(obs) >= 3
    q_hist = obs[:, : 5 * steps].reshape(len(obs), steps, 5)
    qd_hist = obs[:, 5 * steps : 10 * steps].reshape(len(obs), steps, 5)
    np.testing.assert_allclose(q_hist[0], np.repeat(q_hist[0, :1], steps, axis=0))
    for k in range(1, len(obs)):
        np.testing.assert_array_equal(q_hist[k, 1:], q_hist[k - 1, :-1])
        np.testing.assert_array_equal(qd_hist[k, 1:], qd_hist[k - 1, :-1])
    assert not np.allclose(q_hist[-1, 0], q_hist[-1, -1])  # the arm moved within the window
