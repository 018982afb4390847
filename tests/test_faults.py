"""Fault injection on the whole stack (tests/fault_stack.py: server, simulated machine and runtime
of m1 as separate processes, reconciliation bounds shortened to 4 s / 8 s).

For each fault: kill -9 of the plant, the runtime and the server mid-swing, a forged peer on the
Zenoh port (throw, result, policy offer, E-STOP reset), a second runtime and a second plant for
m1, two CPU-burning processes beside the stack, a Zenoh link cut (m2's plant and runtime in their
own network namespace, the veth taken down mid-swing) and kill -9 of ``slinger up`` itself, the
suite asserts: every throw final within its bound, no forged command runs (valve commands stay
neutral, the machine stays still), no second runtime or plant drives the machine, no orphaned
process (``ps`` scan for the test's directory).

One stack serves the module's cases in order; each case leaves it ready for the next.
"""

from __future__ import annotations

import os
import signal
import time
import uuid

import pytest

from runtime.command_auth import new_key, sign
from runtime.protocol import keys
from runtime.protocol.messages import (
    AbortRequest,
    EstopReset,
    EstopResetAck,
    PolicyOffer,
    PolicyOfferAck,
    ThrowAck,
    ThrowRequest,
    ThrowResult,
    decode,
    encode,
)
from runtime.zenoh_session import open_session
from tests.conftest import SlingerUp, wait_for
from tests.fault_stack import FAST_BOUNDS, FINAL, TARGET_2D, FaultStack, Netns, ValveWatch, burner, orphans, stop_proc
from tests.fixtures import write_test_policy


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("faults")


@pytest.fixture(scope="module")
def netns(root):
    """m2's network namespace, or the reason it cannot be made here."""
    try:
        ns = Netns(os.getpid())
    except (PermissionError, FileNotFoundError) as e:
        yield str(e)
        return
    yield ns
    ns.remove()


@pytest.fixture(scope="module")
def stack(root, netns):
    policy = write_test_policy(root / "policies", "2d", release_after_bias=2.0)
    extra = (f"tcp/{netns.host_ip}:{_free_ns_port()}",) if isinstance(netns, Netns) else ()
    with FaultStack(root, policy, env=FAST_BOUNDS, extra_listen=extra) as s:
        s.watch = ValveWatch(s.endpoint)
        yield s
        s.watch.close()
        unfinished = [(t, (s.row(t) or {}).get("status")) for t in s.thrown if (s.row(t) or {}).get("status") not in FINAL]
        assert not unfinished, f"throws left non-final: {unfinished}"
    assert wait_for(lambda: not orphans(root), 20, "no orphaned process") is True


def _free_ns_port() -> int:
    from tests.conftest import free_port

    return free_port()


def _query(session, key: str, msg, wait_s: float = 15.0) -> bytes | None:
    """The first reply's payload (None for an error reply); retried until some reply comes
    (a fresh peer needs a moment to be linked to the others by gossip)."""
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        for reply in session.get(key, payload=encode(msg), timeout=2.0):
            return reply.ok.payload.to_bytes() if reply.ok is not None else None
        time.sleep(0.2)
    raise AssertionError(f"no reply on {key} within {wait_s} s")


def test_forged_peer_cannot_move_the_machine(stack):
    """A peer without the command key: its throw, policy offer and E-STOP reset are refused with
    the reason, its result never reaches the history, and the valves stay neutral throughout."""
    t0 = time.monotonic()
    forged_key = new_key()
    with open_session(mode="peer", connect=(stack.endpoint,)) as peer:
        req = ThrowRequest(throw_id=str(uuid.uuid4()), machine_id="m1", mode="2d", target_m=TARGET_2D)
        for msg, why in ((req, "unsigned"), (sign(req, forged_key, "mallory", 0), "bad signature")):
            ack = decode(ThrowAck, _query(peer, keys.throw("m1"), msg))
            assert not ack.accepted and why in ack.reason, ack
        offer = PolicyOffer(machine_id="m1", mode="2d", version="evil", sha256="0" * 64, manifest={})
        ack = decode(PolicyOfferAck, _query(peer, keys.policy_offer("m1"), offer))
        assert not ack.accepted and "unsigned" in ack.reason
        result = ThrowResult(machine_id="m1", stamp_s=1.0, throw_id=req.throw_id, mode="2d", status="landed",
                             target_m=TARGET_2D, impact_m=TARGET_2D, duration_s=1.0)
        assert _query(peer, keys.THROW_RESULT, result) is None  # refused
        # stopping is always allowed, even unsigned; releasing the stop is not
        assert _query(peer, keys.abort("m1"), AbortRequest(machine_id="m1", reason="forged")) is not None
        wait_for(lambda: (m := stack.machine()) and m["estop_latched"], 5, "latched by the unsigned stop")
        ack = decode(EstopResetAck, _query(peer, keys.estop_reset("m1"), EstopReset(machine_id="m1")))
        assert not ack.reset and "unsigned" in ack.reason
    time.sleep(0.5)
    assert not stack.watch.moving_since(t0), "a forged command moved the valves"
    assert stack.row(req.throw_id) is None
    assert stack.http.get("/api/throws").headers["x-total-count"] == str(len(stack.thrown))
    assert stack.http.post("/api/machines/m1/estop/reset").status_code == 200  # the operator releases it
    stack.wait_ready(30)


def test_second_runtime_and_plant_refuse_to_start(stack):
    t0 = time.monotonic()
    for name, argv in (("runtime-2", stack.runtime_argv()), ("plant-2", stack.plant_argv())):
        proc = stack.spawn(name, argv)
        assert proc.wait(timeout=90) == 3, stack.log_text(name)[-2000:]
        assert "already has a" in stack.log_text(name)
    assert not stack.watch.moving_since(t0)
    assert stack.wait_ready(30)["online"]


def test_plant_killed_mid_swing_fails_the_throw(stack):
    tid = stack.throw()
    stack.wait_phase(tid)
    stack.kill("plant")
    row, took_s = stack.wait_final(tid, 10)
    assert row["status"] == "failed" and row["failure_reason"], row
    stack.start_plant()
    stack.wait_ready()


def test_runtime_killed_mid_swing_the_machine_stops_and_the_throw_is_lost(stack):
    tid = stack.throw()
    before = stack.wait_phase(tid)["status"]
    t_kill = time.monotonic()
    stack.kill("runtime")
    assert wait_for(lambda: stack.watch.still_since(t_kill), 5, "the machine stops (plant watchdog)")
    stack.start_runtime()  # as `slinger up` restarts it: a new claim epoch, nothing of the throw
    row, took_s = stack.wait_final(tid, 60)
    if before not in FINAL:  # lost: restarted without it, or (slow restart) offline past the bound
        assert row["status"] == "lost" and ("restarted" in row["failure_reason"]
                                            or "offline for" in row["failure_reason"]), row
    stack.wait_ready()


def test_server_killed_mid_swing_the_result_arrives_after_restart(stack):
    tid = stack.throw()
    stack.wait_phase(tid)
    stack.kill("server")
    stack.start_server()
    stack.connect_http()
    row, took_s = stack.wait_final(tid, 60)
    assert row["status"] == "landed", row  # from the runtime's outbox
    stack.wait_ready()


def test_cpu_burners_beside_the_stack_estop_latches(stack):
    """Two busy loops beside the stack: a throw is either accepted and E-STOPped mid-swing, or
    refused because the simulated machine says it cannot keep real time (never half-run); the
    E-STOP latches either way, throws are refused until the reset, and every throw ends."""
    burners = [burner(), burner()]
    try:
        r = stack.try_throw()
        if r.status_code == 202:
            stack.wait_phase(r.json()["id"], ("swinging",))
        else:
            assert r.status_code == 422 and "behind real time" in r.json()["detail"], r.text
        t0 = time.monotonic()
        e = stack.http.post("/api/machines/m1/estop", json={"reason": "fault suite"})
        assert e.status_code == 200, e.text
        assert wait_for(lambda: stack.watch.first_neutral_after(t0), 5, "neutral valves")
        m = wait_for(lambda: (m := stack.machine()) and m["estop_latched"] and m, 5, "latched")
        assert m["ready"] is False and "E-STOP" in m["not_ready_reason"]
        if r.status_code == 202:
            row, _ = stack.wait_final(r.json()["id"], 20)
            assert row["status"] in ("aborted", "landed"), row  # landed: the payload was already out
        time.sleep(1.5)  # a landed throw: the simulated machine reloads (moves) 1 s after the landing
        refused = stack.try_throw()
        assert refused.status_code in (409, 422), refused.text  # E-STOP latched (or the arm still settling)
        assert "E-STOP" in refused.json()["detail"] or refused.headers.get("x-refused-condition"), refused.text
    finally:
        for b in burners:
            stop_proc(b, signal.SIGKILL)
    assert stack.http.post("/api/machines/m1/estop/reset").status_code == 200
    stack.wait_ready(60)
    row, _ = stack.wait_final(stack.throw(), 60)
    assert row["status"] == "landed", row


def test_link_cut_mid_swing_the_throw_still_ends(stack, netns):
    if not isinstance(netns, Netns):
        pytest.skip(f"no network namespace here: {netns}")
    hub = next(e for e in stack.extra_listen if netns.host_ip in e)
    link = stack.link(connect=hub, listen_host=netns.ns_ip)
    stack.spawn("plant-m2", netns.prefix() + stack.plant_argv("m2", link))
    stack.spawn("runtime-m2", netns.prefix() + stack.runtime_argv("m2", link))
    try:
        stack.wait_ready(120, "m2", ("server", "plant-m2", "runtime-m2"))
        tid = stack.throw(machine_id="m2")
        stack.wait_phase(tid)
        netns.link_up(False)
        time.sleep(3.0)
        netns.link_up(True)
        row, took_s = stack.wait_final(tid, 60)
        assert row["status"] in ("landed", "failed"), row
    finally:
        netns.link_up(True)
        stop_proc(stack.procs["runtime-m2"])
        stop_proc(stack.procs["plant-m2"])


def test_slinger_up_killed_leaves_no_process_and_no_open_throw(tmp_path, monkeypatch):
    """kill -9 of `slinger up` mid-swing: its children die with it; after a restart on the same
    data the throw is final within the bound: aborted by its runtime on the way down (delivered
    from the outbox after the restart) or lost (the runtime died before it could say so)."""
    for k, v in FAST_BOUNDS.items():
        monkeypatch.setenv(k, v)
    with SlingerUp(tmp_path) as up:
        up.wait_machine_online()
        body = {"machine_id": "m1", "mode": "2d", "target": TARGET_2D}
        p = up.http.post("/api/previews", json={**body, "rollouts": 1}).json()
        tid = up.http.post("/api/throws", json={**body, "preview_id": p["id"]}).json()["id"]
        os.kill(up.proc.pid, signal.SIGKILL)
        up.proc.wait(timeout=10)
        assert wait_for(lambda: not orphans(up.data_dir), 15, "children gone with slinger up") is True
    again = SlingerUp(tmp_path, create_admin=False)
    with again:
        again.wait_machine_online()
        row = wait_for(lambda: (r := again.http.get(f"/api/throws/{tid}").json())["status"] in FINAL and r, 60,
                       "throw final after restart")
        # aborted ("runtime shutting down": the warden stopped it, the outbox kept the result) or lost
        assert row["status"] in ("aborted", "lost") and row["failure_reason"], row
        # a plain peer without the site's certificate gets nowhere on the TLS port
        zport = again.argv[again.argv.index("--zenoh-port") + 1]
        with open_session(mode="peer", connect=(f"tcp/127.0.0.1:{zport}",)) as peer:
            with pytest.raises(AssertionError, match="no reply"):
                _query(peer, keys.info("m1"), EstopReset(machine_id="m1"), wait_s=3.0)
    assert not orphans(tmp_path)
