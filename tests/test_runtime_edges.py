"""Clean edges of the runtime (runtime.service): E-STOP puts still queued at a slowed runtime
never re-latch it after a confirmed reset, and no throw is accepted before the runtime's
warm-up (policies, release check, telemetry writer run once) has ended."""

from __future__ import annotations

from pathlib import Path

import pytest

from runtime.command_auth import CommandVerifier, sign
from runtime.executor import ExecutorConfig, ThrowExecutor
from runtime.policy import PolicyRunner
from runtime.protocol import keys
from runtime.protocol.messages import (
    AbortAck,
    AbortRequest,
    EstopReset,
    EstopResetAck,
    RuntimeInfo,
    ThrowAck,
    ThrowRequest,
    decode,
    encode,
)
from runtime.service import WARMING, RuntimeService
from runtime.throw_geometry import ARM_PLANE_OFFSET_M
from sim_twin.twin.simulated_machine import SimulatedMachine
from sim_twin.twin.twin_machine import TwinMachine
from tests.fixtures import write_test_policy

KEY = bytes(range(32))
EPOCH = 1_700_000_000_000
TARGET = [8.0, ARM_PLANE_OFFSET_M, 0.0]


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory) -> Path:
    return write_test_policy(tmp_path_factory.mktemp("pol"), "2d")


def _service(policy: Path, **kw) -> tuple[RuntimeService, list[tuple[str, bytes]], TwinMachine]:
    sent: list[tuple[str, bytes]] = []
    ex = ThrowExecutor({"2d": PolicyRunner.load(policy)}, config=ExecutorConfig(release_check_radius_m=None))
    now = [100.0]
    service = RuntimeService("m1", ex, lambda k, d: sent.append((k, d)), lambda r: None,
                             verifier=CommandVerifier(KEY, EPOCH, window_s=600.0), clock=lambda: now[0], **kw)  # freshness: not judged here (a loaded host)
    twin = TwinMachine(SimulatedMachine(seed=1), "m1", clock=lambda: now[0])
    service.on_state(encode(twin.state()))
    return service, sent, twin


def _put(request_id: str, reason: str = "operator E-STOP") -> bytes:
    return encode(sign(AbortRequest(machine_id="m1", reason=reason, request_id=request_id), KEY, "op", EPOCH))


def test_queued_estop_puts_do_not_relatch_after_a_confirmed_reset(policy_path):
    service, sent, _ = _service(policy_path)
    service.on_estop(_put("aa01"))  # the first put of the press latches and is acked
    assert service.info().estop_latched
    acks = [decode(AbortAck, d) for k, d in sent if k == keys.estop_ack("m1")]
    assert [a.request_id for a in acks] == ["aa01"]
    reset = decode(EstopResetAck, service.handle_estop_reset(encode(sign(EstopReset(machine_id="m1"), KEY, "op", EPOCH))))
    assert reset.reset and not service.info().estop_latched
    for _ in range(5):  # repeats of that press, still queued at the slowed runtime
        service.on_estop(_put("aa01"))
    assert not service.info().estop_latched, "a stale E-STOP put re-latched after the confirmed reset"
    assert len([k for k, _ in sent if k == keys.estop_ack("m1")]) == 1  # ignored, unanswered
    query = decode(AbortAck, service.handle_abort(_put("aa01")))  # the same on the query path
    assert query.request_id == "aa01" and not service.info().estop_latched
    # a new press (a fresh request id), and an abort without one, latch as always
    service.on_estop(_put("bb02", "second press"))
    assert service.info().estop_reason == "second press"
    service.handle_estop_reset(encode(sign(EstopReset(machine_id="m1"), KEY, "op", EPOCH)))
    decode(AbortAck, service.handle_abort(b""))
    assert service.info().estop_latched


def test_no_throw_before_warm_up(policy_path):
    service, sent, twin = _service(policy_path, warm_up=True)
    req = ThrowRequest(throw_id="w1", machine_id="m1", mode="2d", target_m=TARGET)
    ack = decode(ThrowAck, service.handle_throw(encode(sign(req, KEY, "op", EPOCH))))
    assert not ack.accepted and ack.reason == WARMING
    info = service.info()
    assert not info.ready and info.not_ready_reason == WARMING
    service.on_estop(_put("cc03"))  # E-STOP works during the warm-up
    assert service.info().estop_latched
    service.handle_estop_reset(encode(sign(EstopReset(machine_id="m1"), KEY, "op", EPOCH)))
    took = service.warm_up()
    assert took >= 0 and service.warming is None
    published = [decode(RuntimeInfo, d) for k, d in sent if k == keys.runtime_state("m1")]
    assert published[-1].ready  # said at once, not at the next 2 Hz repeat
    service.on_state(encode(twin.state()))
    ack = decode(ThrowAck, service.handle_throw(encode(sign(req.model_copy(update={"throw_id": "w2"}), KEY, "op", EPOCH))))
    assert ack.accepted, ack.reason


def test_the_heap_is_trimmed_between_throws_only(policy_path, tmp_path):
    """runtime.node.watchdog_tick gives the free heap back (runtime.heap) only while no throw
    runs: a trim holds the heap's locks for a few ms, which no 10 ms control step may wait for."""
    from runtime.heap import HeapTrimmer
    from runtime.node import watchdog_tick
    from runtime.policy_update import PolicyUpdater

    service, _, twin = _service(policy_path)
    updater = PolicyUpdater("m1", tmp_path / "store", lambda name: b"", lambda msg: None, authorize=service.authorize)
    trimmer = HeapTrimmer(every_s=0.0)
    if not trimmer.available:
        pytest.skip("not glibc: no malloc_trim")
    req = ThrowRequest(throw_id="h1", machine_id="m1", mode="2d", target_m=TARGET)
    assert decode(ThrowAck, service.handle_throw(encode(sign(req, KEY, "op", EPOCH)))).accepted
    assert not service.idle()
    for _ in range(3):
        service.on_state(encode(twin.state()))
        watchdog_tick(service, updater, trimmer)
    assert trimmer.trims == 0  # the throw runs: no trim
    decode(AbortAck, service.handle_abort(b""))  # ends the throw (and latches E-STOP: still idle)
    assert service.idle()
    watchdog_tick(service, updater, trimmer)
    assert trimmer.trims == 1
