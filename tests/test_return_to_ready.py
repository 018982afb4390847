"""Recovery "return to the ready pose" in the runtime (RuntimeService + runtime.recovery), driven
over wire messages against the simulated machine (the Harness of test_runtime_node): signed
commands only, refusals while E-STOP is latched or a throw runs, E-STOP stops it, and from poses
outside the envelope the machine ends in the ready pose and becomes ready."""

from __future__ import annotations

import numpy as np
import pytest

from runtime.machine import hanging_pitch
from runtime.protocol.messages import AbortRequest, EstopReset, ReturnToReady, ReturnToReadyAck, RuntimeInfo, decode, encode
from runtime.recovery import POSITION_TOL, READY_POSE, ReturnToReady as Recovery
from runtime.controller import JointVelocityController
from tests.test_runtime_node import EPOCH, KEY, Harness, _signed, _throw_payload
from tests.fixtures import write_test_policy


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory):
    return write_test_policy(tmp_path_factory.mktemp("pol"), "2d", release_after_bias=2.0)


def _pose(h: Harness, q_active) -> None:
    """Put the simulated machine (loaded, at rest) at ``q_active`` (4,), gripper hanging plumb."""
    h.twin.sim.reset(q_active=np.asarray(q_active, dtype=float))


def _ask(h: Harness, signed: bool = True, **kw) -> ReturnToReadyAck:
    req = ReturnToReady(machine_id="m1")
    return decode(ReturnToReadyAck, h.service.handle_return_to_ready(_signed(req, **kw) if signed else encode(req)))


def _info(h: Harness) -> RuntimeInfo:
    return decode(RuntimeInfo, h.service.handle_info())


@pytest.mark.parametrize("q_active, reason", [
    ([0.3, -0.5, 1.6, 1.8], "joint at end: telescope"),          # telescope at its end
    ([0.3, 0.35, 1.2, 1.5], "pose outside the envelope: ground"),  # gripper at the ground
])
def test_from_a_pose_off_the_envelope_the_machine_returns_and_becomes_ready(policy_path, q_active, reason):
    h = Harness(policy_path)
    _pose(h, q_active)
    h.tick(5)
    info = _info(h)
    assert not info.ready and info.not_ready_reason == reason and info.recovery == "return_to_ready"
    assert "unsigned" in _ask(h, signed=False).reason  # the chain's rule: signed commands only
    assert "stale" in _ask(h, now_unix_s=1.0).reason
    assert not h.service.returning
    ack = _ask(h)
    assert ack.accepted, ack.reason
    h.tick(2)
    info = _info(h)
    assert info.returning and not info.ready and info.not_ready_reason.startswith("returning to the ready pose")
    assert "returning" in decode_ack_reason(h)  # a throw is refused meanwhile
    progress = []
    for _ in range(60):  # at most 30 s of machine time
        h.tick(50)
        progress.append(_info(h).return_progress)
        if not h.service.returning:
            break
    info = _info(h)
    assert info.return_result == "reached the ready pose", (info, progress)
    q = np.asarray(h.twin.state().q)
    assert q[0] == pytest.approx(q_active[0], abs=0.02)  # the cabin kept its angle
    assert np.all(np.abs(q[1:4] - READY_POSE) < POSITION_TOL)
    assert progress == sorted(progress) or max(np.diff(progress)) > 0  # progress reported on the way
    h.tick(100)  # the gripper settles
    info = _info(h)
    assert info.ready and info.not_ready_reason is None and info.recovery is None
    ack = decode_ack(h, "t9", cabin_rad=q_active[0])
    assert ack.accepted, ack.reason  # and it throws from there


def decode_ack(h: Harness, throw_id: str = "t9", cabin_rad: float = 0.0):
    """The ThrowAck of a signed 2D throw at 8 m along the throwing line of ``cabin_rad``."""
    from runtime.protocol.messages import ThrowAck
    from runtime.throw_geometry import ARM_PLANE_OFFSET_M

    c, s = np.cos(cabin_rad), np.sin(cabin_rad)
    target = [8.0 * c - ARM_PLANE_OFFSET_M * s, 8.0 * s + ARM_PLANE_OFFSET_M * c, 0.0]
    return decode(ThrowAck, h.service.handle_throw(_throw_payload(throw_id, target=target)))


def decode_ack_reason(h: Harness) -> str:
    return decode_ack(h, "t-during").reason or ""


def test_refused_while_estopped_and_stopped_by_estop(policy_path):
    h = Harness(policy_path)
    _pose(h, [0.0, -0.5, 1.6, 1.8])
    h.tick(5)
    h.service.handle_abort(encode(AbortRequest(machine_id="m1", reason="test stop")))
    ack = _ask(h)
    assert not ack.accepted and ack.reason.startswith("E-STOP latched")
    h.service.handle_estop_reset(_signed(EstopReset(machine_id="m1")))
    assert _ask(h).accepted
    h.tick(100)
    assert h.service.returning
    h.service.handle_abort(encode(AbortRequest(machine_id="m1", reason="person in the area")))
    assert not h.service.returning and _info(h).return_result == "stopped: E-STOP: person in the area"
    h.tick(40)  # valves neutral from the abort on
    assert np.all(h.valve_u == 0.0)


def test_refused_while_a_throw_runs_and_without_a_key(policy_path):
    h = Harness(policy_path)
    h.tick(2)
    assert decode_ack(h, "t1").accepted
    ack = _ask(h)
    assert not ack.accepted and ack.reason == "a throw runs: t1"
    keyless = Harness(policy_path, verifier=None)
    keyless.tick(2)
    assert _ask(keyless).reason == "no command key configured"
    wrong = ReturnToReady(machine_id="m2")
    assert "serves" in decode(ReturnToReadyAck, h.service.handle_return_to_ready(_signed(wrong))).reason
    assert "malformed" in decode(ReturnToReadyAck, h.service.handle_return_to_ready(b"{")).reason


def test_recovery_stops_when_the_way_back_hits_new_trouble_and_rejects_bad_input():
    with pytest.raises(ValueError):
        Recovery([0.0, np.nan, 1.0, 0.5, 0.0, 0.0], 0.0, JointVelocityController())
    q = np.array([0.0, -1.0, 1.2, 1.8, 0.0, 0.0])  # telescope at its end, gripper 3.6 m up
    q[4] = hanging_pitch(q)
    rec = Recovery(q, 0.0, JointVelocityController())
    low = np.array([0.0, 0.35, 1.2, 1.5, 0.0, 0.0])  # gripper in the ground: not so at the start
    low[4] = hanging_pitch(low)
    out = rec.tick(low, np.zeros(6), 0.01)
    assert not rec.status.active and rec.status.result == "failed: the way back would hit the ground"
    assert np.all(out.valve_u == 0.0)
    rec = Recovery(q, 0.0, JointVelocityController())
    rec.tick(q, np.zeros(6), 0.01)
    rec.tick(q, np.zeros(6), 6.0)  # not moving at all
    assert rec.status.result == "failed: no progress for 5 s"
    assert KEY and EPOCH  # the harness' key and epoch sign the commands above


def test_route_needs_an_operator_and_audits_an_undelivered_request(client):
    from server.db.models import Machine
    from tests.conftest import add_user, login

    r = client.post("/api/machines/m1/return-to-ready")
    assert r.status_code == 404 and "unknown machine" in r.json()["detail"], r.text  # never registered
    with client.app.state.sessions.begin() as db:  # a known machine whose runtime is not running
        db.add(Machine(id="m1", simulated=True))
    r = client.post("/api/machines/m1/return-to-ready")
    assert r.status_code == 503 and "offline" in r.json()["detail"], r.text  # no runtime of m1 here
    entry = client.get("/api/audit", params={"action": "return_to_ready"}).json()[0]
    assert entry["subject"] == "m1" and entry["detail"]["delivered"] is False
    add_user(client.app.state.sessions, "vic", "viewer-pass-1", "viewer")
    client.cookies.clear()
    assert client.post("/api/machines/m1/return-to-ready").status_code == 401
    login(client, "vic", "viewer-pass-1")
    assert client.post("/api/machines/m1/return-to-ready").status_code == 403
