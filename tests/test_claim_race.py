"""One runtime (plant) per machine also when two start at the same instant
(runtime.zenoh_session.claim_exclusive): claim tokens, a settle period, the earlier claim wins.
Several rounds of two claimants released by a barrier in one process (separate Zenoh sessions,
clients of a router), a forced same-millisecond tie, a late claimant whose clock is behind, bad
claims; and once two real ``slinger runtime`` processes started together."""

from __future__ import annotations

import subprocess
import threading
import time

import pytest

from runtime.protocol import keys
from runtime.zenoh_session import Claimed, claim_exclusive, new_claim, open_session
from server.site.stack import slinger_command
from tests.conftest import free_port, wait_for
from tests.fixtures import write_test_policy

WAIT_S = 1.0


@pytest.fixture
def router():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session("router", listen=[endpoint]):
        yield endpoint


def _claimants(endpoint: str, claims: list[str | None], mid: str = "m1") -> list:
    """Run claim_exclusive in one session per claim, released together; returns, per claimant,
    the tokens or the Claimed exception, and closes nothing (the caller closes ``sessions``)."""
    sessions = [open_session("client", connect=[endpoint]) for _ in claims]
    out: list = [None] * len(claims)
    gate = threading.Barrier(len(claims))

    def go(i: int) -> None:
        gate.wait()
        try:
            out[i] = claim_exclusive(sessions[i], keys.runtime_alive(mid), lambda c: keys.runtime_claim(mid, c),
                                     WAIT_S, claims[i])
        except Claimed as e:
            out[i] = e

    threads = [threading.Thread(target=go, args=(i,)) for i in range(len(claims))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10 + WAIT_S)
    return out, sessions


def _close(sessions) -> None:
    for s in sessions:
        s.close()


def test_two_claimants_at_once_exactly_one_wins_every_round(router):
    for round_ in range(5):
        out, sessions = _claimants(router, [None, None], mid=f"r{round_}")
        try:
            winners = [o for o in out if isinstance(o, tuple)]
            losers = [o for o in out if isinstance(o, Claimed)]
            assert len(winners) == 1 and len(losers) == 1, (round_, out)
            assert "starting at the same time" in str(losers[0]) or "held by" in str(losers[0])
        finally:
            _close(sessions)


def test_a_same_millisecond_tie_and_a_late_claimant_with_a_slow_clock(router):
    early, late = "1700000000000-aaaaaaaa", "1700000000000-bbbbbbbb"
    out, sessions = _claimants(router, [late, early])
    try:
        assert isinstance(out[0], Claimed) and f"claim {early} before ours {late}" in str(out[0])
        assert isinstance(out[1], tuple)  # the random part decided, the same way in both
        # a claimant whose clock is far behind (its claim sorts first) still yields to the holder
        behind, more = _claimants(router, ["0000000000001-00000000"])
        sessions += more
        assert isinstance(behind[0], Claimed) and "held by a running process" in str(behind[0])
    finally:
        _close(sessions)
    with pytest.raises(ValueError, match="bad claim"):
        keys.runtime_claim("m1", "soon")
    with pytest.raises(ValueError, match="bad claim"):
        keys.machine_claim("m1", "1700000000000-aaaaaaaa/**")
    assert keys.CLAIM_RE.match(new_claim())


def test_two_runtime_processes_started_together(router, tmp_path):
    policy = write_test_policy(tmp_path / "policies", "2d")
    argv = slinger_command("runtime", "--machine-id", "m7", "--policy-2d", str(policy), "--mode", "client",
                           "--connect", router)
    logs = [tmp_path / f"runtime{i}.log" for i in (1, 2)]
    procs = [subprocess.Popen([*argv, "--outbox-dir", str(tmp_path / f"outbox{i}")], stdout=open(log, "wb"),
                              stderr=subprocess.STDOUT) for i, log in enumerate(logs)]
    try:
        wait_for(lambda: any(p.poll() is not None for p in procs), 90, "one runtime exits")
        time.sleep(1.0)
        codes = [p.poll() for p in procs]
        text = [log.read_text(errors="replace") for log in logs]
        assert sorted(codes, key=str) == [3, None], (codes, [t[-1500:] for t in text])
        loser = text[codes.index(3)]
        assert "already has a runtime" in loser, loser[-1500:]
        assert "runtime m7 up" in text[codes.index(None)]
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(20)
