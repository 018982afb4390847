"""Storage faults at the runtime's outbox (runtime.outbox): a full disk loses no result and a
landed throw is delivered, not reported lost; results that servers keep refusing are set aside
after bounded, backed-off retries, not retried without end.

The disk is a real 2 MiB tmpfs filled up (root; the ``root`` marker), or ENOSPC injected at the
outbox's writes (fast tier)."""

from __future__ import annotations

import base64
import errno
import os
import subprocess
from pathlib import Path

import pytest

from runtime.estop_latch import EstopLatchFile
from runtime.outbox import UNDELIVERABLE, DeliveryRefused, Outbox
from runtime.protocol.messages import ResultAck, ThrowResult, decode


def _landed(throw_id: str, stamp_s: float, telemetry_bytes: int = 0) -> ThrowResult:
    tel = base64.b64encode(os.urandom(telemetry_bytes)).decode() if telemetry_bytes else None
    return ThrowResult(machine_id="m1", stamp_s=stamp_s, throw_id=throw_id, mode="2d", status="landed",
                       target_m=[8.0, 0.0, 0.0], impact_m=[7.9, 0.1, 0.0], duration_s=3.0, telemetry_mcap_b64=tel)


class Server:
    """A deliverer: away (None), refusing (DeliveryRefused) or storing (ResultAck stored)."""

    def __init__(self, mode: str = "up"):
        self.mode, self.stored, self.tries = mode, {}, 0

    def __call__(self, payload: bytes):
        self.tries += 1
        result = decode(ThrowResult, payload)
        if self.mode == "away":
            return None
        if self.mode == "faulted":  # answers, but its database cannot store it now
            return ResultAck(throw_id=result.throw_id, stored=False)
        if self.mode == "refusing":
            raise DeliveryRefused(f"result of throw {result.throw_id!r} refused: not a throw this server issued")
        self.stored[result.throw_id] = result
        return ResultAck(throw_id=result.throw_id, stored=True)


def test_enospc_holds_results_in_memory_delivers_them_and_writes_them_later(tmp_path, monkeypatch):
    full = [True]
    write = Outbox.write

    def filling(self, name, data):
        if full[0]:
            raise OSError(errno.ENOSPC, "No space left on device")
        return write(self, name, data)

    monkeypatch.setattr(Outbox, "write", filling)
    server = Server("away")
    box = Outbox(tmp_path, server, reserve_bytes=0)
    box.put(_landed("t1", 1.0))  # no exception: the control loop's result is not lost
    assert box.in_memory() == ["0000000001.000000-t1.json"] and box.pending() == []
    assert box.deliver_pending() == 0  # server away: still held
    full[0] = False
    box.deliver_pending()  # the disk takes writes again: written (the server is still away)
    assert box.in_memory() == [] and [p.name for p in box.pending()] == ["0000000001.000000-t1.json"]
    box.put(_landed("t2", 2.0))
    full[0] = True
    box.put(_landed("t3", 3.0))
    server.mode = "up"
    assert box.deliver_pending() == 3 and set(server.stored) == {"t1", "t2", "t3"}  # from disk and from memory
    assert box.in_memory() == [] and box.pending() == []


def test_refused_results_are_retried_with_backoff_then_kept_as_undeliverable(tmp_path):
    now = [0.0]
    server = Server("refusing")
    box = Outbox(tmp_path, server, retry_interval_s=2.0, reserve_bytes=0, max_refusals=3, clock=lambda: now[0])
    box.put(_landed("t9", 9.0))
    gaps, last = [], None
    for step in range(400):  # 200 s of the delivery thread's rounds
        now[0] = step * 0.5
        before = server.tries
        box.deliver_pending(due_only=True)
        if server.tries > before:
            gaps.append(now[0] - last if last is not None else 0.0)
            last = now[0]
    assert server.tries == 3, "retried without end"
    assert gaps[1:] == [2.0, 4.0]  # backed off
    assert box.pending() == [] and box.undeliverable == 1
    kept = tmp_path / UNDELIVERABLE / "0000000009.000000-t9.json"
    assert decode(ThrowResult, kept.read_bytes()).status == "landed"  # kept, not lost
    assert Outbox(tmp_path, Server()).undeliverable == 1  # counted again after a restart
    # an unanswered result (server away) is retried on, every 2 s, so a restarted server has it at once
    away = Server("away")
    box2 = Outbox(tmp_path / "b", away, retry_interval_s=2.0, reserve_bytes=0, clock=lambda: now[0])
    box2.put(_landed("t10", 10.0))
    for step in range(600):  # 5 min
        now[0] = 1000.0 + step * 0.5
        box2.deliver_pending(due_only=True)
    assert 148 <= away.tries <= 151 and len(box2.pending()) == 1
    # a server that answers but cannot store now (stored=False: its disk or database failing) is
    # waited for the same way: the result is not set aside
    faulted = Server("faulted")
    box3 = Outbox(tmp_path / "c", faulted, retry_interval_s=2.0, reserve_bytes=0, max_refusals=3, clock=lambda: now[0])
    box3.put(_landed("t11", 11.0))
    for step in range(600):
        now[0] = 3000.0 + step * 0.5
        box3.deliver_pending(due_only=True)
    assert faulted.tries > 3 and len(box3.pending()) == 1 and box3.undeliverable == 0


@pytest.fixture
def small_disk(tmp_path):
    """A 2 MiB tmpfs (root), unmounted after the test."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], check=True)
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def _fill(directory: Path, name: str = "filler") -> Path:
    filler = directory / name
    with open(filler, "wb") as f:
        try:
            while True:
                f.write(b"\0" * 65536)
                f.flush()
        except OSError as e:
            assert e.errno == errno.ENOSPC
    return filler


@pytest.mark.root
def test_a_full_disk_loses_no_landed_throw(small_disk):
    server = Server("away")
    box = Outbox(small_disk / "outbox", server, reserve_bytes=600_000)
    assert box.reserve_path.stat().st_size == 600_000
    filler = _fill(small_disk)
    box.put(_landed("r1", 1.0, 300_000))  # written from the reserve (base64: 400 kB)
    assert [p.name for p in box.pending()] == ["0000000001.000000-r1.json"] and not box.reserve_path.exists()
    box.put(_landed("r2", 2.0, 300_000))  # no room left at all: held in memory
    assert box.in_memory() == ["0000000002.000000-r2.json"]
    assert box.deliver_pending() == 0
    server.mode = "up"
    assert box.deliver_pending() == 2 and set(server.stored) == {"r1", "r2"}
    assert server.stored["r2"].status == "landed" and len(server.stored["r2"].telemetry_mcap_b64) == 400_000
    server.mode = "away"
    more = _fill(small_disk, "filler2")  # the delivered files' space is taken again
    box.put(_landed("r3", 3.0, 300_000))
    assert box.in_memory() == ["0000000003.000000-r3.json"]
    filler.unlink()  # space again: the next round writes it and makes the reserve again
    box.deliver_pending()
    assert box.in_memory() == [] and [p.name for p in box.pending()] == ["0000000003.000000-r3.json"]
    assert box.reserve_path.stat().st_size == 600_000
    more.unlink()
    restarted = Outbox(small_disk / "outbox", Server())
    assert restarted.deliver_pending() == 1


@pytest.mark.root
def test_an_estop_latch_reaches_a_full_disk(small_disk):
    """The runtime's E-STOP latch (runtime.estop_latch) is written from its reserved space when
    the disk is full, so a runtime restarted then still comes up latched."""
    latch = EstopLatchFile(small_disk / "state", "m1")
    filler = _fill(small_disk)
    latch.write("operator E-STOP (disk full)")
    assert EstopLatchFile(small_disk / "state", "m1").load() == "operator E-STOP (disk full)"
    filler.unlink()
    latch.clear()
    assert latch.load() is None and latch.reserve.exists()  # the reserve is held again
