"""Live push: the one machine state judged from the runtime's RuntimeInfo, and the hub turning
Zenoh publications (runtime_state, liveliness, throw status) into events for subscribers."""

from __future__ import annotations

import asyncio
import time

import pytest

from runtime.protocol import keys
from runtime.protocol.messages import PolicyInfo, RuntimeInfo, ThrowStatus, encode
from server.live import LiveHub, machine_status
from tests.conftest import free_port

POL = [PolicyInfo(mode="2d", version="throw2d-v2", sha256="0" * 64)]


def _info(**kw) -> RuntimeInfo:
    base = {"machine_id": "m1", "busy": False, "policies": POL, "machine_online": True, "simulated": True}
    return RuntimeInfo(**{**base, **kw})


def test_machine_status_says_one_state_with_its_reason():
    assert machine_status("m1", False, _info(), 0.1)["state"] == "offline"
    st = machine_status("m1", True, None, None)
    assert st["state"] == "not_ready" and "waiting" in st["reason"]
    st = machine_status("m1", True, _info(machine_online=False), 0.1)
    assert (st["state"], st["reason"]) == ("not_ready", "machine offline (no joint states)")
    frozen = machine_status("m1", True, _info(busy=True, phase="swinging", throw_id="t1", estop_latched=True), 9.0,
                            {"throw_id": "t1", "phase": "swinging"})
    assert (frozen["state"], frozen["reason"], frozen["phase"]) == ("offline", "runtime not answering for 9 s", None)
    # a running throw (known from ThrowStatus) is shown with its phase
    st = machine_status("m1", True, _info(busy=True), 0.1, {"throw_id": "t1", "phase": "swinging"})
    assert (st["state"], st["phase"], st["throw_id"]) == ("throwing", "swinging", "t1")
    assert machine_status("m1", True, _info(policies=[]), 0.1)["reason"] == "no policy installed"
    st = machine_status("m1", True, _info(), 0.1)
    assert st["state"] == "ready" and st["policies"] == {"2d": "throw2d-v2"} and st["simulated"]


def test_machine_status_follows_the_runtime_fields():
    st = machine_status("m1", True, _info(estop_latched=True, estop_reason="operator E-STOP (ann)", ready=False,
                                          not_ready_reason="E-STOP latched"), 0.1)
    assert (st["state"], st["estop_reason"]) == ("estopped", "operator E-STOP (ann)")
    st = machine_status("m1", True, _info(ready=False, not_ready_reason="pose outside the envelope"), 0.1)
    assert (st["state"], st["reason"]) == ("not_ready", "pose outside the envelope")
    assert machine_status("m1", True, _info(ready=True, phase="released", throw_id="t2"), 0.1)["state"] == "throwing"
    assert machine_status("m1", True, _info(ready=True), 0.1)["state"] == "ready"



def test_machine_status_carries_the_recovery_action_and_its_progress():
    st = machine_status("m1", True, _info(ready=False, not_ready_reason="joint at end: telescope",
                                          recovery="return_to_ready"), 0.1)
    assert (st["state"], st["recovery"], st["returning"]) == ("not_ready", "return_to_ready", False)
    st = machine_status("m1", True, _info(ready=False, not_ready_reason="returning to the ready pose (40 %)",
                                          returning=True, return_progress=0.4), 0.1)
    assert (st["state"], st["returning"], st["return_progress"], st["recovery"]) == ("not_ready", True, 0.4, None)
    st = machine_status("m1", True, _info(ready=True, return_result="reached the ready pose"), 0.1)
    assert st["state"] == "ready" and st["return_result"] == "reached the ready pose"
    assert machine_status("m1", False, _info(recovery="return_to_ready"), 0.1)["recovery"] is None  # offline: none


class _Fleet:
    def __init__(self):
        self.result_listeners = []
        self.online = set()

    def is_online(self, mid):
        return mid in self.online

    def online_ids(self):
        return set(self.online)

    def latest_state(self, mid):
        return None

    def latest_states(self):
        return {}

    def cached_info(self, mid):
        return None

    def fresh_info(self, mid, **kw):
        return None


def test_hub_pushes_runtime_state_presence_progress_and_results():
    from runtime.zenoh_session import open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    fleet = _Fleet()
    with open_session(mode="peer", listen=(endpoint,)) as server_z, \
            open_session(mode="peer", connect=(endpoint,)) as runtime_z:
        hub = LiveHub(server_z, fleet)
        hub.start()
        try:
            asyncio.run(_exercise(hub, fleet, runtime_z))
        finally:
            hub.stop()


async def _next(sub, event: str, pred=lambda d: True, timeout_s: float = 10.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            name, data = await asyncio.wait_for(sub.queue.get(), timeout=max(0.05, deadline - time.monotonic()))
        except TimeoutError:
            break
        if name == event and pred(data):
            return data
    pytest.fail(f"no {event} event within {timeout_s} s")


async def _exercise(hub, fleet, z):
    sub = hub.subscribe("c1")
    other = hub.subscribe("c2")
    token = z.liveliness().declare_token(keys.runtime_alive("m1"))
    fleet.online.add("m1")
    st = await _next(sub, "machine", lambda d: d["machine_id"] == "m1")
    assert st["state"] in ("not_ready", "ready")
    z.put(keys.runtime_state("m1"), encode(_info(busy=False)))
    st = await _next(sub, "machine", lambda d: d["state"] == "ready")
    assert st["policies"] == {"2d": "throw2d-v2"}
    # throw progress: a phase change is an event with the elapsed time, and the state follows
    z.put(keys.status("m1"), encode(ThrowStatus(machine_id="m1", throw_id="t1", phase="swinging", stamp_s=1.0)))
    ev = await _next(sub, "throw")
    assert (ev["machine_id"], ev["throw_id"], ev["phase"]) == ("m1", "t1", "swinging")
    assert (await _next(sub, "machine", lambda d: d["state"] == "throwing"))["phase"] == "swinging"
    # results and heartbeats reach every page; console events only their console
    fleet.result_listeners[0]("t1")
    assert (await _next(sub, "result"))["throw_id"] == "t1"
    await _next(sub, "heartbeat", timeout_s=3.0)
    hub.publish("console", {"console_id": "c2", "target": [8, 0, 0]}, console_id="c2")
    assert (await _next(other, "console"))["console_id"] == "c2"
    assert all(name != "console" for name, _ in _drain(sub))
    # the runtime stops: offline at once (liveliness), not after a timeout
    t0 = time.monotonic()
    token.undeclare()
    fleet.online.discard("m1")
    st = await _next(sub, "machine", lambda d: d["state"] == "offline", timeout_s=5.0)
    assert st["reason"] == "runtime offline" and time.monotonic() - t0 < 2.0
    hub.unsubscribe(sub)
    hub.unsubscribe(other)


def _drain(sub):
    out = []
    while not sub.queue.empty():
        out.append(sub.queue.get_nowait())
    return out
