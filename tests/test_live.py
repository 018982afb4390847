"""Live push: the one machine state judged from the runtime's RuntimeInfo, and the hub turning
Zenoh publications (runtime_state, liveliness, throw status, machine state), heard once by the
fleet's listener, into events for subscribers."""

from __future__ import annotations

import asyncio
import time

import pytest

from runtime.protocol import keys
from runtime.protocol.messages import MachineState, PolicyInfo, RuntimeInfo, ThrowStatus, encode
from server.fleet.link import Fleet
from server.fleet.events import ResultStored
from server.console.live import NO_REASON, LiveHub, machine_status
from tests.conftest import free_port

POL = [PolicyInfo(mode="2d", version="throw2d-v2", sha256="0" * 64)]


def _info(**kw) -> RuntimeInfo:
    base = {"machine_id": "m1", "busy": False, "policies": POL, "machine_online": True, "simulated": True,
            "ready": True}
    return RuntimeInfo(**{**base, **kw})


def test_machine_status_names_the_lease_holder_and_the_undeliverable_results():
    """The Fleet page follows them live (web/js/fleet.js reloads the machine's row when they change)."""
    st = machine_status("m1", True, _info(lease_holder="srv-a", undeliverable_results=2), 0.1)
    assert (st["lease_holder"], st["undeliverable_results"]) == ("srv-a", 2)
    st = machine_status("m1", False, _info(lease_holder="srv-a", undeliverable_results=2), 0.1)
    assert (st["lease_holder"], st["undeliverable_results"]) == (None, None)  # offline: not known now


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
    st = machine_status("m1", True, _info(policies=[], ready=False, not_ready_reason="no policy loaded"), 0.1)
    assert (st["state"], st["reason"]) == ("not_ready", "no policy loaded")
    # not ready without a reason (the runtime always gives one): not ready, never guessed ready
    st = machine_status("m1", True, _info(ready=False), 0.1)
    assert (st["state"], st["reason"]) == ("not_ready", NO_REASON)
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


class _Store:
    """The fleet's database side, not needed here."""

    def upsert_machine(self, *a, **kw):
        pass

    def apply_status(self, status):
        pass


@pytest.fixture
def linked():
    """(server-side Fleet with a LiveHub consuming it, the runtime's Zenoh session)."""
    from runtime.zenoh_session import open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session(mode="peer", listen=(endpoint,)) as server_z, \
            open_session(mode="peer", connect=(endpoint,)) as runtime_z:
        fleet = Fleet(server_z, _Store(), query_timeout_s=0.5)
        hub = LiveHub(fleet)
        hub.start()
        fleet.start()
        try:
            yield fleet, hub, runtime_z
        finally:
            hub.stop()
            fleet.stop()


def test_hub_pushes_runtime_state_presence_progress_and_results(linked):
    fleet, hub, runtime_z = linked
    asyncio.run(_exercise(hub, fleet, runtime_z))


def test_a_machine_state_is_decoded_once_and_reaches_the_fleet_and_the_live_stream(linked, monkeypatch):
    """Counted at pydantic's JSON parse of each message class (whatever module decodes it), so a
    second subscriber anywhere in the server would show as a second decode."""
    fleet, hub, z = linked
    decoded: list[type] = []
    for cls in (MachineState, ThrowStatus):
        real = cls.model_validate_json

        def counting(payload, *a, _cls=cls, _real=real, **kw):
            decoded.append(_cls)
            return _real(payload, *a, **kw)

        monkeypatch.setattr(cls, "model_validate_json", counting)
    asyncio.run(_state_once(hub, fleet, z, decoded))


def test_one_runtime_info_cache_feeds_commands_and_the_console(linked, monkeypatch):
    """The RuntimeInfo the runtime publishes lands in the fleet's one cache (clock offset measured
    from it); the console state reads the same entry, keeps showing it after the fleet forgot it
    for reads, and shows the runtime offline once it is silent too long."""
    from server.console import live

    fleet, hub, z = linked
    monkeypatch.setattr(live, "SILENT_AFTER_S", 1.0)
    asyncio.run(_one_cache(hub, fleet, z))


async def _one_cache(hub, fleet, z):
    sub = hub.subscribe()
    token = z.liveliness().declare_token(keys.runtime_alive("m1"))
    await _next(sub, "machine", lambda d: d["machine_id"] == "m1" and d["state"] != "offline")
    z.put(keys.runtime_state("m1"), encode(_info(clock_unix_s=time.time() + 5.0)))
    await _next(sub, "machine", lambda d: d["state"] == "ready")
    assert fleet.cached_info("m1").policies == POL and abs(fleet.clock_offset_s("m1") - 5.0) < 0.5
    fleet.forget_info("m1")
    assert fleet.cached_info("m1") is None and fleet.last_info("m1") is not None
    assert hub.status("m1")["state"] == "ready"
    assert (hub.status("m1")["lease_holder"], hub.status("m1")["lease_held_here"]) == (None, None)
    z.put(keys.runtime_state("m1"), encode(_info(lease_holder="srv-other")))
    st = await _next(sub, "machine", lambda d: d["lease_holder"] == "srv-other")
    assert st["lease_held_here"] is False  # the Fleet page offers a takeover from this state
    z.put(keys.runtime_state("m1"), encode(_info(lease_holder=fleet.signer.server_id)))
    assert (await _next(sub, "machine", lambda d: d["lease_holder"] == fleet.signer.server_id))["lease_held_here"] is True
    st = await _next(sub, "machine", lambda d: d["state"] == "offline", timeout_s=5.0)  # silent > 1 s
    assert st["reason"].startswith("runtime not answering")
    token.undeclare()
    hub.unsubscribe(sub)


async def _state_once(hub, fleet, z, decoded):
    sub = hub.subscribe()
    token = z.liveliness().declare_token(keys.runtime_alive("m1"))
    await _next(sub, "machine", lambda d: d["machine_id"] == "m1" and d["state"] != "offline")
    z.put(keys.status("m1"), encode(ThrowStatus(machine_id="m1", throw_id="t1", phase="swinging", stamp_s=1.0)))
    await _next(sub, "throw")
    state = MachineState(machine_id="m1", stamp_s=2.0, q=[0.3, -0.5, 1.5, 0.2, -1.0, 0.1], qd=[0.5] * 6,
                         gripper_open=False, payload_attached=True, simulated=True)
    z.put(keys.state("m1"), encode(state))
    sample = await _next(sub, "sample")
    assert (sample["machine_id"], sample["throw_id"], sample["qd"]) == ("m1", "t1", [0.5] * 4)
    assert fleet.latest_state("m1") == state
    assert decoded.count(MachineState) == 1 and decoded.count(ThrowStatus) == 1, decoded
    token.undeclare()
    hub.unsubscribe(sub)


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
    fleet.listener.emit(ResultStored("t1"))
    assert (await _next(sub, "result"))["throw_id"] == "t1"
    await _next(sub, "heartbeat", timeout_s=3.0)
    hub.publish("console", {"console_id": "c2", "target": [8, 0, 0]}, console_id="c2")
    assert (await _next(other, "console"))["console_id"] == "c2"
    assert all(name != "console" for name, _ in _drain(sub))
    # the runtime stops: offline at once (liveliness), not after a timeout
    t0 = time.monotonic()
    token.undeclare()
    st = await _next(sub, "machine", lambda d: d["state"] == "offline", timeout_s=5.0)
    assert st["reason"] == "runtime offline" and time.monotonic() - t0 < 2.0
    hub.unsubscribe(sub)
    hub.unsubscribe(other)


def _drain(sub):
    out = []
    while not sub.queue.empty():
        out.append(sub.queue.get_nowait())
    return out
