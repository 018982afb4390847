"""One machine's E-STOP never waits for another's (issue 24, finding 1), through the API with two
stand-in runtimes (tests/conftest.py FakeRuntime): m2's is frozen (its stops are never
answered), eight clients keep pressing m2's E-STOP, and m1's E-STOP is still confirmed at once.
The whole-stack version with a SIGSTOPped runtime process is tests/test_estop_faults.py; the
latency figures come from tests/benchmarks/bench_estop_latency.py --frozen-peers."""

from __future__ import annotations

import threading
import time

from tests.conftest import wait_for, wait_online


def test_a_frozen_machines_estops_do_not_delay_another_machines(client, fake_runtime_factory):
    m1 = fake_runtime_factory(machine_id="m1", hold=True)
    m2 = fake_runtime_factory(machine_id="m2")
    wait_online(client, "m1")
    wait_online(client, "m2")
    wait_for(lambda: all(m["policies"] for m in client.get("/api/machines").json()), 10, "runtime infos")
    m2.frozen = True
    replies: list[int] = []

    def press_m2() -> None:
        for _ in range(3):
            replies.append(client.post("/api/machines/m2/estop", json={"reason": "m2 press"}).status_code)

    presses = [threading.Thread(target=press_m2) for _ in range(8)]
    for t in presses:
        t.start()
    time.sleep(0.3)  # m2's presses are in flight
    t0 = time.monotonic()
    r = client.post("/api/machines/m1/estop", json={"reason": "m1 press"})
    took_s = time.monotonic() - t0
    assert r.status_code == 200, r.text
    assert took_s < 1.0, f"m1's E-STOP took {took_s:.2f} s behind m2's"  # old code: >= the 2 s query timeout
    assert m1.estop_reason == "m1 press (admin)"
    for t in presses:
        t.join(timeout=30)
    assert replies and set(replies) == {503}  # m2 never confirmed: each press says so
    assert m2.estop_reason is None
    fleet = client.app.state.fleet
    assert fleet._estop.coalesced > 0  # presses joined the unconfirmed stop instead of queueing more
    m2.frozen = False
    assert client.post("/api/machines/m2/estop").status_code == 200  # thawed: confirmed
    assert m2.estop_reason is not None


def test_a_runtime_clock_8_s_off_still_takes_signed_commands_and_the_row_says_so(client, fake_runtime_factory):
    """The runtime's clock runs 8 s ahead (its host lost time sync; injected, the system clock
    is untouched): the server measures the offset from its RuntimeInfo and signs in its time, so
    E-STOP, reset and throw work; the machine row names the difference. Replay protection holds."""
    rt = fake_runtime_factory(machine_id="m1", clock_offset_s=8.0, hold=True)
    wait_online(client, "m1")
    m = wait_for(lambda: (m := client.get("/api/machines").json()[0])["clock_offset_s"] is not None and m, 10, "offset")
    assert abs(m["clock_offset_s"] - 8.0) < 0.5
    assert "clock differs from the server by +8.0 s" in m["clock_warning"]
    assert client.post("/api/machines/m1/estop").status_code == 200
    r = client.post("/api/machines/m1/estop/reset")
    assert r.status_code == 200, r.text
    assert rt.estop_reason is None
    r = client.post("/api/throws", json={"machine_id": "m1", "mode": "2d", "target": [8.0, -0.292, 0.0]})
    assert r.status_code == 202, r.text
    replayed = rt.verifier.check(rt.requests[-1])
    assert replayed == "replayed nonce"
