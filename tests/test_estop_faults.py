"""E-STOP and machine-state faults on the whole stack (tests/fault_stack.py: server, worker, and
the simulated machine and runtime of m1 and of m2 as separate processes, the deployed 2D policy):

* m2's runtime frozen (SIGSTOP) while eight clients keep pressing m2's E-STOP: m1's E-STOP is
  confirmed promptly and m1's throw ends aborted (issue 24, finding 1);
* a frozen runtime is shown offline ("runtime not answering") within seconds, not online / busy;
* E-STOP latched, kill -9 of the runtime, restart: it comes back latched, throws are refused
  until the operator resets it (finding 2);
* m2's runtime restarted with its wall clock 8 s ahead (SLINGER_CLOCK_OFFSET_S, fault injection
  only): its row names the difference, E-STOP, reset and a throw work (finding 4).

One stack serves the module's cases in order; each leaves both machines ready.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import httpx
import pytest

from tests.conftest import wait_for
from tests.fault_stack import FAST_BOUNDS, FINAL, FaultStack, ValveWatch, orphans, stop_proc

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    root = tmp_path_factory.mktemp("estop-faults")
    with FaultStack(root, REPO / "policies" / "throw2d.onnx", env=FAST_BOUNDS) as s:
        s.spawn("plant-m2", s.plant_argv("m2"))
        s.spawn("runtime-m2", s.runtime_argv("m2"))
        s.wait_ready(180, "m2", ("server", "plant-m2", "runtime-m2"))
        s.watch = ValveWatch(s.endpoint)
        try:
            yield s
        finally:
            s.watch.close()
            for name in ("runtime-m2", "plant-m2"):
                proc = s.procs.get(name)
                if proc is not None and proc.poll() is None:
                    os.kill(proc.pid, signal.SIGCONT)
                stop_proc(proc)
    assert wait_for(lambda: not orphans(root), 20, "no orphaned process") is True


def _client(stack) -> httpx.Client:
    """Another console of the same operator (own connection, same session cookie)."""
    return httpx.Client(base_url=stack.base_url, cookies=stack.http.cookies, timeout=30)


def _reset_and_ready(stack, machine_id: str) -> None:
    wait_for(lambda: stack.http.post(f"/api/machines/{machine_id}/estop/reset").status_code == 200, 30,
             f"E-STOP reset of {machine_id}")
    stack.watch.reload(machine_id)  # stopped mid-swing with the payload in hand: start afresh
    stack.wait_ready(60, machine_id, ("server", f"plant-{machine_id}" if machine_id != "m1" else "plant",
                                      f"runtime-{machine_id}" if machine_id != "m1" else "runtime"))


def test_a_frozen_runtimes_estops_do_not_delay_another_machines(stack):
    tid = stack.throw()
    stack.wait_phase(tid, ("swinging",))
    frozen = stack.procs["runtime-m2"]
    os.kill(frozen.pid, signal.SIGSTOP)
    replies: list[int] = []

    def press_m2() -> None:
        with _client(stack) as c:
            for _ in range(2):
                replies.append(c.post("/api/machines/m2/estop", json={"reason": "m2 press"}).status_code)

    presses = [threading.Thread(target=press_m2) for _ in range(8)]
    try:
        for t in presses:
            t.start()
        time.sleep(0.1)
        t0 = time.monotonic()
        r = stack.http.post("/api/machines/m1/estop", json={"reason": "m1 press"})
        took_s = time.monotonic() - t0
        assert r.status_code == 200, r.text
        assert took_s < 2.0, f"m1's E-STOP took {took_s:.2f} s behind m2's"  # pooled queries: 4.7 s
        assert r.json()["aborted_throw_id"] == tid
        assert stack.watch.first_neutral_after(t0) is not None
        for t in presses:
            t.join(timeout=60)
        assert replies and set(replies) == {503}, replies  # m2 never confirmed while frozen
    finally:
        os.kill(frozen.pid, signal.SIGCONT)
    row, _ = stack.wait_final(tid, 30)
    assert row["status"] == "aborted", row
    wait_for(lambda: (m := stack.machine("m2")) and m["online"], 30, "m2 answering again")
    _reset_and_ready(stack, "m1")
    _reset_and_ready(stack, "m2")


def test_a_frozen_runtime_is_shown_offline_within_seconds(stack):
    frozen = stack.procs["runtime-m2"]
    os.kill(frozen.pid, signal.SIGSTOP)
    try:
        t0 = time.monotonic()
        m = wait_for(lambda: (m := stack.machine("m2")) and not m["online"] and m, 8, "m2 offline")
        assert m["ready"] is False and m["not_ready_reason"].startswith("runtime not answering"), m
        assert time.monotonic() - t0 < 8.0
        assert stack.machine("m1")["online"]  # the other machine is unaffected
    finally:
        os.kill(frozen.pid, signal.SIGCONT)
    stack.wait_ready(60, "m2", ("server", "plant-m2", "runtime-m2"))


def test_the_estop_latch_survives_kill_9_and_a_restart_of_the_runtime(stack):
    r = stack.http.post("/api/machines/m1/estop", json={"reason": "latch test"})
    assert r.status_code == 200, r.text
    stack.kill("runtime")
    stack.start_runtime()
    m = wait_for(lambda: (m := stack.machine()) and m["online"] and m["estop_latched"] is not None and m, 90,
                 "runtime back")
    assert m["estop_latched"] is True and m["ready"] is False, m
    assert "latch test" in m["estop_reason"]
    refused = stack.http.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": [8.0, -0.292, 0.0]})
    assert refused.status_code == 409 and "E-STOP" in refused.json()["detail"], refused.text
    _reset_and_ready(stack, "m1")
    row, _ = stack.wait_final(stack.throw(), 60)
    assert row["status"] in FINAL and row["status"] != "aborted", row


def test_a_runtime_clock_8_s_ahead_still_takes_signed_commands(stack):
    stop_proc(stack.procs["runtime-m2"])
    stack.spawn("runtime-m2", stack.runtime_argv("m2"), env={**stack.env, "SLINGER_CLOCK_OFFSET_S": "8"})
    try:
        m = stack.wait_ready(120, "m2", ("server", "plant-m2", "runtime-m2"))
        assert abs(m["clock_offset_s"] - 8.0) < 1.0 and "clock differs from the server by +8" in m["clock_warning"], m
        assert stack.http.post("/api/machines/m2/estop").status_code == 200
        r = stack.http.post("/api/machines/m2/estop/reset")
        assert r.status_code == 200, r.text  # refused "stale (issued 8.0 s ago)" before
        stack.wait_ready(60, "m2", ("server", "plant-m2", "runtime-m2"))
        row, _ = stack.wait_final(stack.throw(machine_id="m2"), 60)
        assert row["status"] == "landed", row
    finally:
        stop_proc(stack.procs["runtime-m2"])
        stack.spawn("runtime-m2", stack.runtime_argv("m2"))
    stack.wait_ready(120, "m2", ("server", "plant-m2", "runtime-m2"))
