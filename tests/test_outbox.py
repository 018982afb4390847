"""Durable outbox: stored before delivery, removed only on a matching stored ack, retried,
survives a restart."""

from __future__ import annotations

import threading
import time

import pytest

from runtime.outbox import Outbox
from runtime.protocol.messages import ResultAck, ThrowResult, decode


def _result(throw_id: str = "t1", stamp_s: float = 12.5) -> ThrowResult:
    return ThrowResult(machine_id="m1", stamp_s=stamp_s, throw_id=throw_id, mode="2d", status="failed", failure_reason="x", target_m=[8.0, 0.0, 0.0], duration_s=1.0)


class FakeServer:
    def __init__(self, mode="ack"):
        self.mode, self.received = mode, []

    def __call__(self, payload: bytes):
        msg = decode(ThrowResult, payload)
        self.received.append(msg.throw_id)
        if self.mode == "down":
            return None
        if self.mode == "raise":
            raise TimeoutError("no route")
        if self.mode == "not-stored":
            return ResultAck(throw_id=msg.throw_id, stored=False)
        if self.mode == "wrong-id":
            return ResultAck(throw_id="other", stored=True)
        return ResultAck(throw_id=msg.throw_id, stored=True)


def test_delivered_results_are_removed(tmp_path):
    server = FakeServer()
    box = Outbox(tmp_path, server)
    box.put(_result("t1", 1.0))
    box.put(_result("t/2 *", 2.0))  # unsafe characters do not escape the directory
    assert len(box.pending()) == 2 and all(p.parent == tmp_path for p in box.pending())
    assert box.deliver_pending() == 2
    assert server.received == ["t1", "t/2 *"]  # oldest first
    assert box.pending() == []


@pytest.mark.parametrize("mode", ["down", "raise", "not-stored", "wrong-id"])
def test_undelivered_results_stay(tmp_path, mode):
    box = Outbox(tmp_path, FakeServer(mode))
    box.put(_result())
    assert box.deliver_pending() == 0
    assert len(box.pending()) == 1


def test_results_survive_a_restart(tmp_path):
    Outbox(tmp_path, FakeServer("down")).put(_result("kept"))
    server = FakeServer()
    assert Outbox(tmp_path, server).deliver_pending() == 1
    assert server.received == ["kept"]


def test_corrupt_files_are_set_aside(tmp_path):
    (tmp_path / "0001-bad.json").write_text("{not json")
    box = Outbox(tmp_path, FakeServer())
    box.put(_result())
    assert box.deliver_pending() == 1
    assert (tmp_path / "0001-bad.bad").exists() and box.pending() == []


def test_background_thread_retries_until_acked(tmp_path):
    server = FakeServer("down")
    box = Outbox(tmp_path, server, retry_interval_s=0.05)
    box.start()
    try:
        box.put(_result())
        deadline = time.monotonic() + 5
        while len(server.received) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(server.received) >= 3 and len(box.pending()) == 1  # retried, still kept
        server.mode = "ack"
        while box.pending() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert box.pending() == []
    finally:
        box.stop()
    assert not any(t.name == "outbox" for t in threading.enumerate())
