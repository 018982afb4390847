"""The runtime's durable E-STOP latch (runtime.estop_latch), its E-STOP put path (keys.estop ->
AbortAck on keys.estop_ack) and READY only when a throw can really start, driven through
RuntimeService over wire messages (the Harness of tests/test_runtime_node.py: a simulated machine
that reloads its payload 1 s after a landing as the plant does)."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import pytest

from runtime.estop_latch import FILE_NAME, EstopLatchFile
from runtime.protocol import keys
from runtime.protocol.messages import AbortAck, AbortRequest, EstopReset, EstopResetAck, ThrowAck, decode, encode
from runtime.service import RuntimeService
from tests.fixtures import write_test_policy
from tests.test_runtime_node import Harness, _signed, _throw_payload


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory) -> Path:
    return write_test_policy(tmp_path_factory.mktemp("pol"), "2d", release_after_bias=2.0)


def _restarted(h: Harness, latch: EstopLatchFile) -> RuntimeService:
    """A new RuntimeService on the same machine and latch directory (what a restart leaves)."""
    return RuntimeService("m1", h.service.executor, h.service.send, h.results.append, verifier=h.service.verifier,
                          clock=h.service.clock, latch=EstopLatchFile(latch.dir, "m1"))


def test_latch_is_on_disk_before_the_ack_and_survives_a_restart_until_a_signed_reset(policy_path, tmp_path):
    h = Harness(policy_path)
    latch = EstopLatchFile(tmp_path / "state", "m1")
    h.service = _restarted(h, latch)
    h.tick()
    written = []

    def send(key, data):  # the ack must not leave before the latch is on disk
        if key == keys.estop_ack("m1"):
            written.append((latch.dir / FILE_NAME).is_file())
        h.sent.append((key, data))

    h.service.send = send
    h.service.on_estop(encode(AbortRequest(machine_id="m1", reason="person in the zone", request_id="ab12")))
    ack = h.of(keys.estop_ack("m1"), AbortAck)[-1]
    assert ack.request_id == "ab12" and ack.latch_persisted and written == [True]
    assert json.loads((latch.dir / FILE_NAME).read_text())["reason"] == "person in the zone"

    h.service = _restarted(h, latch)  # kill -9 and restart: the latch comes back from disk
    h.tick()
    info = h.service.info()
    assert info.estop_latched and info.estop_reason == "person in the zone" and not info.ready
    refused = decode(ThrowAck, h.service.handle_throw(_throw_payload("t1")))
    assert not refused.accepted and refused.reason == "E-STOP latched: person in the zone"
    unsigned = decode(EstopResetAck, h.service.handle_estop_reset(encode(EstopReset(machine_id="m1"))))
    assert not unsigned.reset and (latch.dir / FILE_NAME).is_file()
    assert decode(EstopResetAck, h.service.handle_estop_reset(_signed(EstopReset(machine_id="m1")))).reset
    assert not (latch.dir / FILE_NAME).exists()
    h.service = _restarted(h, latch)
    assert not h.service.info().estop_latched


@pytest.mark.parametrize("content", [b"{not json", b'{"machine_id": "m9", "reason": "x"}'])
def test_a_damaged_or_foreign_latch_file_starts_latched(tmp_path, content):
    (tmp_path / FILE_NAME).write_bytes(content)
    reason = EstopLatchFile(tmp_path, "m1").load()
    assert reason is not None and "reset to release" in reason


def test_a_latch_that_cannot_be_written_is_reported_and_still_holds(policy_path, tmp_path, monkeypatch):
    h = Harness(policy_path)
    latch = EstopLatchFile(tmp_path / "state", "m1")
    h.service = _restarted(h, latch)
    h.tick()

    def disk_full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(h.service.latch, "write", disk_full)
    ack = decode(AbortAck, h.service.handle_abort(b""))
    assert not ack.latch_persisted and h.service.info().estop_latched
    assert "E-STOP latched" in decode(ThrowAck, h.service.handle_throw(_throw_payload("t1"))).reason


def test_ready_only_when_the_next_payload_is_loaded(policy_path):
    """After a landing the plant reloads 1 s later: the runtime is not READY meanwhile (the
    first preview would be made from the old state) and READY again once loaded and at rest."""
    h = Harness(policy_path)
    h.tick()
    assert h.service.info().ready
    assert decode(ThrowAck, h.service.handle_throw(_throw_payload("t1"))).accepted
    for _ in range(400):
        h.tick()
        if h.results:
            break
    assert h.results[-1].status == "landed"
    reasons = []
    for _ in range(300):
        h.tick()
        info = h.service.info()
        if info.ready:
            break
        reasons.append(info.not_ready_reason)
    assert info.ready, reasons[-3:]
    assert "no payload loaded" in reasons
    state = h.service.latest_state
    assert state.payload_attached and not state.gripper_open
    refused_early = [r for r in reasons if r == "no payload loaded"]
    assert len(refused_early) >= 50  # about 1 s of 100 Hz states without a payload
