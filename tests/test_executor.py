"""ThrowExecutor driven in a plain loop with the simulated machine (as evaluation and previews
do), plus its refusal and failure paths."""

from __future__ import annotations

import base64

import numpy as np
import pytest

from runtime.controller import JointVelocityController
from runtime.executor import ExecutorConfig, ThrowExecutor
from runtime.machine import JOINT_UPPER
from runtime.observation import SUBSTEPS, observation_size
from runtime.policy import PolicyError, PolicyRunner
from runtime.protocol.messages import MachineState, SimReset, ThrowRequest
from runtime.telemetry import read_metadata, read_telemetry
from runtime.throw_geometry import ARM_PLANE_OFFSET_M, impact_errors
from sim_twin.twin.twin_machine import TwinMachine, run_throw
from sim_twin.twin.simulated_machine import SimulatedMachine
from tests.fixtures import write_test_policy

TARGET_2D = [8.0, ARM_PLANE_OFFSET_M, 0.0]  # cabin_turn 0: the arm's plane is y = -0.292 m
NO_CHECK = ExecutorConfig(release_check_radius_m=None)
"""The test policies are not throwers: the release check (tests/test_release_check.py) would hold them."""


@pytest.fixture(scope="module")
def releasing_2d(tmp_path_factory) -> PolicyRunner:
    return PolicyRunner.load(write_test_policy(tmp_path_factory.mktemp("p2"), "2d", release_after_bias=2.0))


@pytest.fixture(scope="module")
def releasing_3d(tmp_path_factory) -> PolicyRunner:
    return PolicyRunner.load(write_test_policy(tmp_path_factory.mktemp("p3"), "3d", release_after_bias=2.0))


@pytest.fixture(scope="module")
def holding_2d(tmp_path_factory) -> PolicyRunner:
    return PolicyRunner.load(write_test_policy(tmp_path_factory.mktemp("h2"), "2d", release_after_bias=-2.0))


def _request(mode="2d", target=TARGET_2D, throw_id="t1"):
    return ThrowRequest(throw_id=throw_id, machine_id="m1", mode=mode, target_m=target)


def _twin(seed=1):
    return TwinMachine(SimulatedMachine(seed=seed), "m1")


class RecordingPolicy:
    """Wraps a PolicyRunner and keeps the observations it was given."""

    def __init__(self, runner, fail_at: int | None = None):
        self.runner, self.fail_at, self.observations = runner, fail_at, []
        self.mode, self.version, self.sha256, self.target_range_m = runner.mode, runner.version, runner.sha256, runner.target_range_m
        self.aim_target, self.history_steps = runner.aim_target, runner.history_steps

    def act(self, obs):
        self.observations.append(np.array(obs))
        if self.fail_at is not None and len(self.observations) > self.fail_at:
            raise PolicyError("boom")
        return self.runner.act(obs)


def test_full_2d_throw_lands_with_impact_and_telemetry(releasing_2d):
    twin = _twin()
    ex = ThrowExecutor({"2d": releasing_2d}, JointVelocityController(), NO_CHECK)
    outcome, events = run_throw(twin, ex, _request())
    assert [e.phase for e in events] == ["preparing", "swinging", "released", "landed"]
    assert outcome.status == "landed" and outcome.failure_reason is None
    assert twin.reset_count == 0  # a loaded simulated machine throws from where it stands
    down, cross = impact_errors(TARGET_2D, outcome.impact_m)
    assert outcome.downrange_error_m == pytest.approx(down) and outcome.crossrange_error_m == pytest.approx(cross)
    assert outcome.impact_m[2] == 0.0 and abs(outcome.crossrange_error_m) < 0.3  # planar throw
    assert outcome.release_stamp_s < outcome.opening_stamp_s < outcome.end_stamp_s
    assert 0.2 < outcome.opening_stamp_s - outcome.release_stamp_s < 0.35  # the gripper's opening delay
    assert not ex.busy

    tel = outcome.telemetry
    stamps = np.array([r["t_s"] for r in tel.rows])
    np.testing.assert_allclose(np.diff(stamps), 0.01, atol=1e-9)  # 100 Hz
    opens = [False] + [r["command_open"] for r in tel.rows]  # the gripper was closed before the throw
    assert sum(1 for a, b in zip(opens, opens[1:]) if b and not a) == 1  # opened exactly once

    msg = outcome.to_message("m1")
    data = read_telemetry(base64.b64decode(msg.telemetry_mcap_b64))
    assert len(data["t_s"]) == len(tel) and data["q"].shape == (len(tel), 6)
    assert data["gripper_open"][-1] and data["gripper_cmd"][-1]
    assert list(data["event_phase"]) == ["preparing", "swinging", "released", "landed"]
    assert read_metadata(base64.b64decode(msg.telemetry_mcap_b64))["policy_version"] == releasing_2d.version
    assert msg.policy_version == releasing_2d.version and msg.status == "landed"
    np.testing.assert_allclose(msg.impact_m, outcome.impact_m)


def test_3d_throw_off_the_arm_plane_lands(releasing_3d):
    ex = ThrowExecutor({"3d": releasing_3d}, config=NO_CHECK)
    outcome, events = run_throw(_twin(2), ex, _request("3d", [6.0, 5.0, 0.0]))
    assert outcome.status == "landed", outcome.failure_reason
    assert outcome.impact_m is not None


def test_swinging_runs_the_policy_at_12_5_hz_from_a_filled_history(releasing_2d):
    policy = RecordingPolicy(releasing_2d)
    ex = ThrowExecutor({"2d": policy}, config=NO_CHECK)
    outcome, _ = run_throw(_twin(), ex, _request())
    swing_ticks = sum(1 for r in outcome.telemetry.rows if r["phase"] in ("swinging", "released"))
    assert len(policy.observations) == -(-swing_ticks // SUBSTEPS)  # every 8th tick, incl. after release
    first = policy.observations[0]
    assert first.shape == (observation_size("2d"),)
    q_hist = first[:20].reshape(4, 5)
    np.testing.assert_allclose(q_hist, np.repeat(q_hist[:1], 4, axis=0))  # filled with the start state
    np.testing.assert_array_equal(first[40:44], 0.0)  # previous action starts at zeros
    assert policy.observations[1][43] > 0.9  # then it is the previous raw action (release entry)


def test_no_release_fails_after_the_timeout(holding_2d):
    ex = ThrowExecutor({"2d": holding_2d}, config=ExecutorConfig(release_timeout_s=1.0))
    outcome, events = run_throw(_twin(), ex, _request())
    assert outcome.status == "failed" and "no release" in outcome.failure_reason
    assert events[-1].phase == "failed"
    assert 1.0 < outcome.duration_s < 1.2


def test_no_impact_fails_after_the_timeout(releasing_2d):
    twin, ex = _twin(), ThrowExecutor({"2d": releasing_2d}, config=ExecutorConfig(impact_timeout_s=0.5, release_check_radius_m=None))
    assert ex.start(_request(), twin.state()) is None
    for _ in range(200):  # never report the impact
        out = ex.tick(twin.state())
        if out.finished:
            break
        twin.step(out.valve_u, out.gripper_open)
    assert out.finished.status == "failed" and "no impact" in out.finished.failure_reason
    np.testing.assert_array_equal(out.valve_u, 0.0)


@pytest.mark.parametrize(
    "target, why",
    [([20.0, -0.3, 0.0], "beyond"), ([2.0, -0.3, 0.0], "too close"), ([0.0, 8.0, 0.0], "2D throwing plane"), ([8.0, -0.3, 3.0], "ground")],
)
def test_unservable_targets_are_refused(releasing_2d, target, why):
    ex = ThrowExecutor({"2d": releasing_2d}, config=NO_CHECK)
    reason = ex.start(_request(target=target), _twin().state())
    assert reason is not None and why in reason
    assert not ex.busy


def test_refusals_busy_missing_policy_and_no_state(releasing_2d):
    twin, ex = _twin(), ThrowExecutor({"2d": releasing_2d}, config=NO_CHECK)
    assert "no 3d policy" in ex.start(_request("3d", [6.0, 5.0, 0.0]), twin.state())
    assert "no machine state" in ex.start(_request(), None)
    assert ex.start(_request(), twin.state()) is None
    assert "busy" in ex.start(_request(throw_id="t2"), twin.state())
    assert ex.throw_id == "t1"


def test_second_throw_reloads_the_simulated_machine_once(releasing_2d):
    twin = _twin()
    ex = ThrowExecutor({"2d": releasing_2d}, JointVelocityController(), NO_CHECK)
    first, _ = run_throw(twin, ex, _request())
    assert first.status == "landed" and not twin.state().payload_attached
    second, events = run_throw(twin, ex, _request(throw_id="t2"))
    assert second.status == "landed"
    assert twin.reset_count == 1  # the payload was gone: exactly one reset (new payload)
    swing = next(e.stamp_s for e in events if e.phase == "swinging")
    assert swing > first.end_stamp_s


def test_policy_filed_under_the_wrong_mode_is_rejected(releasing_2d):
    with pytest.raises(ValueError):
        ThrowExecutor({"3d": releasing_2d})


def _unload(twin):
    """Open the gripper until the payload is gone (as after a throw)."""
    for _ in range(60):
        twin.step(np.zeros(4), True)
    assert not twin.state().payload_attached


def test_preparing_waits_for_a_loaded_machine_then_times_out(releasing_2d):
    twin, ex = _twin(), ThrowExecutor({"2d": releasing_2d}, config=ExecutorConfig(prepare_timeout_s=0.5, release_check_radius_m=None))
    _unload(twin)
    assert ex.start(_request(), twin.state()) is None
    out = ex.tick(twin.state())
    assert not out.gripper_open and ex.phase == "preparing"
    for _ in range(60):  # nobody loads a payload: stays preparing, valves neutral, then fails
        twin.step(out.valve_u, out.gripper_open)
        out = ex.tick(twin.state())
        np.testing.assert_array_equal(out.valve_u, 0.0)
        if out.finished:
            break
    assert out.finished.status == "failed" and "not ready" in out.finished.failure_reason


def test_preparing_swings_once_the_machine_is_loaded(releasing_2d):
    twin, ex = _twin(), ThrowExecutor({"2d": releasing_2d}, config=NO_CHECK)
    _unload(twin)
    assert ex.start(_request(), twin.state()) is None
    for _ in range(20):
        twin.step(ex.tick(twin.state()).valve_u, False)
    assert ex.phase == "preparing"
    twin.apply_reset(SimReset(machine_id="m1", stamp_s=0.0))  # the machine (operator) loads one
    ex.tick(twin.state())
    assert ex.phase in ("swinging", "released")


def _swinging(ex, twin):
    assert ex.start(_request(), twin.state()) is None
    out = ex.tick(twin.state())
    assert ex.phase in ("swinging", "released")
    return out


def test_clearance_violation_fails_with_neutral_valves(holding_2d):
    twin, ex = _twin(), ThrowExecutor({"2d": holding_2d})
    _swinging(ex, twin)
    st = twin.state()
    q = list(st.q)
    q[3] = JOINT_UPPER[3]  # telescope at its limit
    out = ex.tick(st.model_copy(update={"q": q, "stamp_s": st.stamp_s + 0.01}))
    assert out.finished.status == "failed" and "joint limit" in out.finished.failure_reason
    np.testing.assert_array_equal(out.valve_u, 0.0)


def test_nan_state_fails_the_throw(holding_2d):
    twin, ex = _twin(), ThrowExecutor({"2d": holding_2d})
    _swinging(ex, twin)
    st = twin.state()
    bad = MachineState.model_construct(**{**st.model_dump(), "qd": [np.nan] * 6, "stamp_s": st.stamp_s + 0.01})
    out = ex.tick(bad)
    assert out.finished.status == "failed" and "non-finite" in out.finished.failure_reason
    np.testing.assert_array_equal(out.valve_u, 0.0)


def _until_finished(ex, twin, ticks: int = 20):
    """Tick the executor against the twin until the throw ends (at most ``ticks``); the last output."""
    for _ in range(ticks):
        out = ex.tick(twin.state())
        if out.finished:
            break
        twin.step(out.valve_u, out.gripper_open)
    return out


def test_policy_error_mid_throw_fails(holding_2d):
    twin, ex = _twin(), ThrowExecutor({"2d": RecordingPolicy(holding_2d, fail_at=1)})
    _swinging(ex, twin)
    out = _until_finished(ex, twin)
    assert out.finished.status == "failed" and "policy error" in out.finished.failure_reason


def test_non_finite_action_marks_the_version_unhealthy_on_this_machine(holding_2d):
    """A NaN action fails the throw and marks the version unhealthy: the next throw with it is
    refused with the reason."""

    class NanAfter(RecordingPolicy):
        def act(self, obs):
            self.observations.append(np.array(obs))
            return np.full(4, np.nan, np.float32) if len(self.observations) > 1 else self.runner.act(obs)

    twin = _twin()
    bad = NanAfter(holding_2d)
    ex = ThrowExecutor({"2d": bad})
    _swinging(ex, twin)
    out = _until_finished(ex, twin)
    assert out.finished.status == "failed" and "non-finite" in out.finished.failure_reason
    np.testing.assert_array_equal(out.valve_u, 0.0)
    refusal = ex.start(_request(throw_id="t2"), twin.state())
    assert refusal and "marked unhealthy on this machine" in refusal and "t1" in refusal
    assert set(ex.unhealthy) == {holding_2d.sha256}


def test_abort_mid_swing(holding_2d):
    twin, ex = _twin(), ThrowExecutor({"2d": holding_2d})
    out = _swinging(ex, twin)
    for _ in range(30):
        twin.step(out.valve_u, out.gripper_open)
        out = ex.tick(twin.state())
    out = ex.abort("operator abort")
    assert out.finished.status == "aborted" and out.finished.failure_reason == "operator abort"
    assert [e.phase for e in out.events] == ["aborted"]
    np.testing.assert_array_equal(out.valve_u, 0.0)
    assert not ex.busy
    assert ex.abort().finished is None  # idle: nothing to abort
    np.testing.assert_array_equal(ex.tick(twin.state()).valve_u, 0.0)  # idle ticks are neutral


def test_impact_ignored_unless_released(holding_2d, releasing_2d):
    twin, ex = _twin(), ThrowExecutor({"2d": releasing_2d}, config=NO_CHECK)
    outcome, _ = run_throw(twin, ex, _request())
    assert ex.on_impact(outcome.impact).finished is None  # idle
    ex2 = ThrowExecutor({"2d": holding_2d})
    _swinging(ex2, _twin())
    assert ex2.on_impact(outcome.impact).finished is None and ex2.phase == "swinging"
