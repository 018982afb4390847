"""The load benchmark's accounting (tests/benchmarks/fleet_load_stats.py): a requested throw
that never reaches a final status counts as stuck, final statuses are checked, reasons are
grouped, and the /proc CPU readings are sane."""

from __future__ import annotations

import os
import time

import pytest

from tests.benchmarks.fleet_load_stats import (
    Tally,
    host_cpu_s,
    is_pose_refusal,
    percentile,
    proc_cpu_s,
    short_reason,
    tree_cpu_s,
)


def test_unfinished_throw_is_stuck_and_reasons_grouped():
    t = Tally()
    for tid in ("a", "b", "c", "d"):
        t.accepted(tid, "m1")
    t.ended("a", "landed", None)
    t.ended("b", "failed", "machine fault: behind real time by 104 ms")
    t.ended("c", "failed", "machine fault: behind real time by 131 ms")
    o = t.outcome()
    assert o["requested"] == 4 and o["stuck"] == 1 and o["lost"] == 0
    assert o["by_status"] == {"landed": 1, "failed": 2}
    assert o["reasons"] == {"failed: machine fault: behind real time by # ms": 2}
    t.ended("d", "lost", "no result")
    assert t.outcome()["stuck"] == 0 and t.outcome()["lost"] == 1


def test_bad_accounting_is_refused():
    t = Tally()
    with pytest.raises(ValueError, match="never requested"):
        t.ended("x", "landed", None)
    t.accepted("x", "m1")
    with pytest.raises(ValueError, match="not a final status"):
        t.ended("x", "swinging", None)
    with pytest.raises(ValueError, match="quantile"):
        percentile([1.0], 1.5)


def test_percentile_and_pose_refusal():
    assert percentile(list(range(101)), 0.95) == 95
    assert percentile([], 0.5) != percentile([], 0.5)  # NaN
    assert is_pose_refusal("422 not ready: pose outside the envelope (dipper)")
    assert not is_pose_refusal("422 machine fault: behind real time by 120 ms")
    assert short_reason(None) == "(no reason given)"


def test_cpu_readings_grow_with_work():
    c0, (b0, t0) = proc_cpu_s(os.getpid()), host_cpu_s()
    end = time.process_time() + 0.2
    while time.process_time() < end:
        pass
    assert proc_cpu_s(os.getpid()) - c0 >= 0.1
    own = proc_cpu_s(os.getpid())  # read first: the process keeps running between the two reads
    assert tree_cpu_s(os.getpid()) >= own
    b1, t1 = host_cpu_s()
    assert b1 - b0 >= 0.1 and t1 >= b1
    assert proc_cpu_s(2**22 + 12345) == 0.0  # no such process


class _Resp:
    def __init__(self, status_code: int, body):
        self.status_code, self._body = status_code, body
        self.text = str(body)

    def json(self):
        return self._body


class _Http:
    """Stand-in for the benchmark client's httpx.Client: the machine reports ready on the 2nd poll."""

    def __init__(self):
        self.calls, self.polls = [], 0

    def post(self, path, **kw):
        self.calls.append(("POST", path))
        return _Resp(200, {"machine_id": "m1", "accepted": True})

    def get(self, path, **kw):
        self.calls.append(("GET", path))
        self.polls += 1
        return _Resp(200, [{"id": "m1", "ready": self.polls >= 2}])


def test_a_pose_refusal_makes_the_client_return_the_machine_to_ready(monkeypatch):
    from tests.benchmarks import bench_fleet_load as bench

    monkeypatch.setattr(bench, "RETURN_POLL_S", 0.0)
    site = type("S", (), {"machines": ["m1"], "base_url": "http://x"})()
    run, http = bench.Run(site, clients=1, drain_s=1.0), _Http()
    run._refused(http, "m1", "throw", _Resp(422, {"detail": "not ready: pose outside the envelope: ground"}))
    assert ("POST", "/api/machines/m1/return-to-ready") in http.calls
    assert run.tally.returns == {"accepted, ready again": 1} and len(run.tally.return_s) == 1
    assert run.tally.refusals == {"throw: # {'detail': 'not ready: pose outside the envelope: ground'}": 1}
    http2 = _Http()
    run._refused(http2, "m1", "throw", _Resp(422, {"detail": "machine fault: behind real time by 120 ms"}))
    assert http2.calls == []  # not a pose refusal: no recovery
