"""Finality: a throw that a watchdog stopped, or during which the runtime itself stalled, ends
failed with the reason and never resumes; nothing queued during a stall is acted on after it
(runtime.service, runtime.executor, the simulated machine's valve watchdog in sim_twin.twin.plant).

The unit cases drive RuntimeService and ThrowExecutor with an injected clock; the system case
freezes a real runtime process with SIGSTOP mid-swing (plant and runtime on loopback Zenoh, the
deployed 2D policy) and checks that after SIGCONT the throw is failed and the arm stays still.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from runtime.command_auth import CommandVerifier, sign, write_key
from runtime.executor import ExecutorConfig, ThrowExecutor
from runtime.policy import PolicyRunner
from runtime.protocol import keys
from runtime.protocol.messages import (
    STALE_COMMAND_S,
    MachineState,
    ResultAck,
    RuntimeInfo,
    ThrowAck,
    ThrowRequest,
    ThrowResult,
    ThrowStatus,
    ValveCommand,
    decode,
    encode,
)
from runtime.service import STALLED, RuntimeService
from runtime.throw_geometry import ARM_PLANE_OFFSET_M
from sim_twin.twin.plant import VALVE_WATCHDOG_S, PlantInbox, plant_tick
from sim_twin.twin.simulated_machine import SimulatedMachine
from sim_twin.twin.twin_machine import TwinMachine
from tests.conftest import TEST_POLICY_CHECK, free_port, wait_for
from tests.fixtures import write_test_policy

REPO = Path(__file__).resolve().parents[1]
TARGET = [8.0, ARM_PLANE_OFFSET_M, 0.0]
KEY = bytes(range(32))
EPOCH = 1_700_000_000_000


@pytest.fixture(scope="module")
def holding_path(tmp_path_factory) -> Path:
    """A test policy that swings and never releases (the throw runs until a watchdog or timeout)."""
    return write_test_policy(tmp_path_factory.mktemp("hold"), "2d", name="hold", release_after_bias=-2.0)


def _throw(throw_id: str, epoch: int = EPOCH, now_unix_s: float | None = None) -> bytes:
    req = ThrowRequest(throw_id=throw_id, machine_id="m1", mode="2d", target_m=TARGET)
    return encode(sign(req, KEY, "alice", epoch, now_unix_s))


class _Sample:
    """What a Zenoh subscriber hands the plant's inbox: ``.payload.to_bytes()``."""

    def __init__(self, data: bytes):
        self.payload = self
        self._data = data

    def to_bytes(self) -> bytes:
        return self._data


_NOW = [100.0]
"""The fake monotonic clock of the unit cases: the runtime's, the machine's stamps and the plant
inbox's receive times (sim_twin.twin.plant reads ``time.monotonic``, patched by :func:`_fake_clock`)."""


@pytest.fixture(autouse=True)
def _fake_clock(monkeypatch):
    import sim_twin.twin.plant

    _NOW[0] = 100.0
    monkeypatch.setattr(sim_twin.twin.plant, "time", SimpleNamespace(monotonic=lambda: _NOW[0]))


class Loop:
    """RuntimeService with the fake monotonic clock and an in-process simulated machine that obeys
    its commands through the plant's inbox (valve watchdog included), 10 ms per period."""

    def __init__(self, policy: Path):
        self.sent: list[tuple[str, bytes]] = []
        self.results: list[ThrowResult] = []
        ex = ThrowExecutor({"2d": PolicyRunner.load(policy)}, config=ExecutorConfig(release_check_radius_m=None))
        self.service = RuntimeService("m1", ex, lambda k, d: self.sent.append((k, d)), self.results.append,
                                      verifier=CommandVerifier(KEY, EPOCH, window_s=600.0), clock=lambda: _NOW[0])  # freshness: not judged here (a loaded host)
        self.twin = TwinMachine(SimulatedMachine(seed=1), "m1", clock=lambda: _NOW[0])
        self.inbox = PlantInbox("m1")
        self._seen = 0

    @property
    def now_s(self) -> float:
        return _NOW[0]

    @now_s.setter
    def now_s(self, value: float) -> None:
        _NOW[0] = value

    def of(self, key: str, cls, since: int = 0):
        return [decode(cls, d) for k, d in self.sent[since:] if k == key]

    def machine_period(self) -> MachineState:
        """One plant period at the fake clock, then the clock advances 10 ms."""
        state, report = plant_tick(self.twin, self.inbox, self.now_s)
        self.now_s += 0.01
        assert report is None
        return state

    def deliver(self, state: MachineState) -> None:
        """``state`` reaches the runtime; its commands reach the plant's inbox."""
        self.service.on_state(encode(state))
        for key, data in self.sent[self._seen:]:
            if key == keys.valve_cmd("m1"):
                self.inbox.on_valve(_Sample(data))
            elif key == keys.gripper_cmd("m1"):
                self.inbox.on_gripper(_Sample(data))
        self._seen = len(self.sent)


def _run(loop: Loop, n: int) -> None:
    for _ in range(n):
        loop.deliver(loop.machine_period())


def test_a_stalled_runtime_fails_its_throw_and_acts_on_nothing_queued(holding_path):
    loop = Loop(holding_path)
    _run(loop, 5)
    assert decode(ThrowAck, loop.service.handle_throw(_throw("t1"))).accepted
    _run(loop, 40)
    assert loop.service.executor.phase == "swinging" and np.any(loop.of(keys.valve_cmd("m1"), ValveCommand)[-1].u)
    # The runtime stalls 1.5 s (SIGSTOP): the machine runs on, its watchdog puts the valves
    # neutral; its states and a throw request signed meanwhile queue up at the runtime.
    queued = []
    for _ in range(150):
        queued.append(loop.machine_period())
    assert loop.inbox.latch.trips == 1 and not loop.inbox.latch.armed
    during = _throw("t2")
    mark = len(loop.sent)
    for state in queued:  # SIGCONT: the queue drains in a burst
        loop.deliver(state)
        loop.now_s += 0.0001
    refused = decode(ThrowAck, loop.service.handle_throw(during))
    assert not refused.accepted and refused.reason == STALLED
    assert loop.results and loop.results[-1].throw_id == "t1" and loop.results[-1].status == "failed"
    assert loop.results[-1].failure_reason.startswith("machine link lost: runtime stalled 1.5")
    assert all(not any(v.u) for v in loop.of(keys.valve_cmd("m1"), ValveCommand, mark)), "a queued state drove the valves"
    statuses = [s.phase for s in loop.of(keys.status("m1"), ThrowStatus) if s.throw_id == "t1"]
    assert statuses[-1] == "failed" and "released" not in statuses
    assert loop.service.stalls == 1 and loop.service.stale_states > 0  # the queued states were dropped
    # never resumes: fresh states after the stall leave the valves neutral, the runtime idle
    mark = len(loop.sent)
    _run(loop, 100)
    assert not loop.service.executor.busy and all(not any(v.u) for v in loop.of(keys.valve_cmd("m1"), ValveCommand, mark))
    assert loop.inbox.latch.armed  # the runtime's neutral commands re-armed the plant
    # a new, freshly signed throw request is what starts the next throw (once the arm is at rest)
    for _ in range(300):
        if loop.service.info().ready:
            break
        _run(loop, 1)
    assert loop.service.info().ready
    assert decode(ThrowAck, loop.service.handle_throw(_throw("t3"))).accepted


def test_the_watchdog_tick_alone_sees_a_stall(holding_path):
    loop = Loop(holding_path)
    _run(loop, 5)
    assert decode(ThrowAck, loop.service.handle_throw(_throw("t1"))).accepted
    _run(loop, 30)
    loop.now_s += 0.5  # nothing ran for 0.5 s; the first to run again is the watchdog thread
    assert loop.service.check_watchdog()
    assert loop.results[-1].failure_reason == "machine link lost: runtime stalled 0.50 s"
    assert loop.of(keys.valve_cmd("m1"), ValveCommand)[-1].u == [0.0] * 4
    assert not loop.service.info().busy


def test_a_late_state_is_dropped_and_fails_the_throw(holding_path):
    loop = Loop(holding_path)
    _run(loop, 5)
    assert decode(ThrowAck, loop.service.handle_throw(_throw("t1"))).accepted
    _run(loop, 30)
    state = loop.machine_period()
    loop.service.check_watchdog()  # the runtime is alive (its watchdog ticks) ...
    loop.now_s += 0.15
    loop.service.check_watchdog()
    loop.now_s += 0.15  # ... but this state took 0.3 s to arrive
    mark = len(loop.sent)
    loop.service.on_state(encode(state))
    assert loop.service.stale_states == 1 and loop.service.stalls == 0
    assert loop.results[-1].failure_reason.startswith("machine link lost: machine state 0.3")
    assert all(not any(v.u) for v in loop.of(keys.valve_cmd("m1"), ValveCommand, mark))


def _started(policy: Path, throw_id: str) -> tuple[ThrowExecutor, TwinMachine]:
    """An executor (release check off) that has started throw ``throw_id`` on a simulated machine."""
    ex = ThrowExecutor({"2d": PolicyRunner.load(policy)}, config=ExecutorConfig(release_check_radius_m=None))
    twin = TwinMachine(SimulatedMachine(seed=2), "m1")
    assert ex.start(ThrowRequest(throw_id=throw_id, machine_id="m1", mode="2d", target_m=TARGET), twin.state()) is None
    return ex, twin


def _executor_at_swing(policy: Path) -> tuple[ThrowExecutor, TwinMachine]:
    ex, twin = _started(policy, "e1")
    for _ in range(20):
        out = ex.tick(twin.state())
        twin.step(out.valve_u, out.gripper_open)
    assert ex.phase == "swinging"
    return ex, twin


def test_executor_fails_a_throw_whose_machine_states_jump(holding_path):
    ex, twin = _executor_at_swing(holding_path)
    later = twin.state().model_copy(update={"stamp_s": twin.state().stamp_s + 0.5})
    out = ex.tick(later)
    assert out.finished is not None and out.finished.status == "failed"
    assert out.finished.failure_reason == "machine link lost: machine states 0.51 s apart (a watchdog stopped the arm)"
    assert not any(out.valve_u) and not ex.busy


def test_executor_fails_a_throw_when_the_machines_valve_watchdog_tripped(holding_path):
    ex, twin = _executor_at_swing(holding_path)
    out = ex.tick(twin.state().model_copy(update={"watchdog_trips": 1}))  # it started with None
    assert out.finished is not None and out.finished.failure_reason == "machine link lost: the machine's valve watchdog stopped the arm"
    ex2, twin2 = _executor_at_swing(holding_path)
    ex2.abort()
    st = twin2.state().model_copy(update={"watchdog_trips": 3})
    assert ex2.start(ThrowRequest(throw_id="e2", machine_id="m1", mode="2d", target_m=TARGET), st) is None
    assert ex2.tick(st.model_copy(update={"stamp_s": st.stamp_s + 0.01})).finished is None  # 3 at the start: fine
    assert ex2.tick(st.model_copy(update={"stamp_s": st.stamp_s + 0.02, "watchdog_trips": 4})).finished.status == "failed"


def _cmd(u, stamp_s) -> _Sample:
    return _Sample(encode(ValveCommand(machine_id="m1", stamp_s=stamp_s, u=u)))


def test_plant_valve_watchdog_is_final_and_stale_commands_are_dropped():
    _NOW[0] = 50.0
    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1"), PlantInbox("m1")
    inbox.on_valve(_cmd([0.0, 0.0, 0.0, 1.0], 50.0))
    assert inbox.valve_u[3] == 1.0
    st, _ = plant_tick(twin, inbox, 50.0 + VALVE_WATCHDOG_S + 0.01)
    assert inbox.latch.trips == 1 and st.watchdog_trips == 1 and not inbox.latch.armed
    _NOW[0] = 50.2
    inbox.on_valve(_cmd([0.0, 0.0, 0.0, 1.0], 50.2))  # fresh, but the watchdog disarmed the valves
    assert not inbox.valve_u.any()
    inbox.on_valve(_cmd([0.0] * 4, 50.2))  # the runtime sends neutral: re-armed
    assert inbox.latch.armed
    inbox.on_valve(_cmd([0.0, 0.0, 0.0, 0.5], 50.2))
    assert inbox.valve_u[3] == 0.5
    inbox.on_valve(_cmd([0.0, 0.0, 0.0, 1.0], 50.2 - STALE_COMMAND_S - 0.05))  # answers a state 250 ms old
    assert inbox.valve_u[3] == 0.5 and inbox.stale_commands == 1
    inbox.on_valve(_cmd([0.0] * 4, 40.0))  # an old neutral command is still obeyed (stopping is safe)
    assert not inbox.valve_u.any()
    # a watchdog that fires while the valves are neutral stopped nothing: no trip, still armed
    plant_tick(twin, inbox, 51.0)
    assert inbox.latch.trips == 1 and inbox.latch.armed


# --- system: a real runtime process frozen mid-swing -----------------------------------------------
def _spawn(args: list[str], log_path: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    with open(log_path, "wb") as log:
        return subprocess.Popen([sys.executable, "-m", *args], cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGCONT)
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@pytest.mark.processes
def test_sigstop_of_the_runtime_mid_swing_fails_the_throw_for_good(tmp_path):
    from runtime.zenoh_session import open_session

    port, mid = free_port(), "fin1"
    endpoint = f"tcp/127.0.0.1:{port}"
    key_file = write_key(tmp_path / "command.key", KEY)
    runtime = _spawn(["runtime.node", "--machine-id", mid, "--policy-2d", str(REPO / "policies" / "throw2d.onnx"),
                      "--outbox-dir", str(tmp_path / "outbox"), "--command-key", str(key_file), *TEST_POLICY_CHECK,
                      "--listen", endpoint], tmp_path / "runtime.log")
    plant = None
    statuses: list[ThrowStatus] = []
    results: list[ThrowResult] = []
    speeds: list[tuple[float, float]] = []  # (receive time, largest active joint speed)

    def on_result(query):
        res = decode(ThrowResult, query.payload.to_bytes())
        results.append(res)
        query.reply(query.key_expr, encode(ResultAck(throw_id=res.throw_id, stored=True)))

    def on_state(sample):
        st = decode(MachineState, sample.payload.to_bytes())
        speeds.append((time.monotonic(), max(abs(v) for v in st.qd[:4])))

    try:
        with open_session(connect=[endpoint]) as session:
            subs = [session.declare_subscriber(keys.status(mid), lambda s: statuses.append(decode(ThrowStatus, s.payload.to_bytes()))),
                    session.declare_subscriber(keys.state(mid), on_state),
                    session.declare_queryable(keys.THROW_RESULT, on_result)]

            def info() -> RuntimeInfo | None:
                for reply in session.get(keys.info(mid), timeout=1.0):
                    if reply.ok is not None:
                        return decode(RuntimeInfo, reply.ok.payload.to_bytes())
                return None

            wait_for(lambda: runtime.poll() is not None or info(), 60, "runtime up")
            assert runtime.poll() is None, (tmp_path / "runtime.log").read_text()
            plant = _spawn(["sim_twin.twin.plant", "--machine-id", mid, "--connect", endpoint, "--listen", "tcp/127.0.0.1:0",
                            "--seed", "3"], tmp_path / "plant.log")
            froze = None
            for attempt in range(4):  # a loaded host may fail a throw for real-time reasons first: retried
                wait_for(lambda: (i := info()) is not None and i.ready, 90, "runtime ready")
                tid = f"s{attempt}"
                payload = encode(sign(ThrowRequest(throw_id=tid, machine_id=mid, mode="2d", target_m=TARGET), KEY, "alice", info().epoch))
                acks = [decode(ThrowAck, r.ok.payload.to_bytes()) for r in session.get(keys.throw(mid), payload=payload, timeout=5.0) if r.ok]
                if not acks[0].accepted:
                    assert acks[0].reason.startswith("machine fault"), acks
                    continue
                wait_for(lambda tid=tid: any(s.throw_id == tid and s.phase in ("swinging", "failed", "aborted") for s in statuses), 30, "swinging")
                time.sleep(0.4)
                if any(s.throw_id == tid and s.phase != "swinging" and s.phase != "preparing" for s in statuses):
                    wait_for(lambda tid=tid: any(r.throw_id == tid for r in results), 30, "the early result")
                    continue  # it ended before the freeze (loaded host): again
                runtime.send_signal(signal.SIGSTOP)
                froze = time.monotonic()
                time.sleep(1.5)
                runtime.send_signal(signal.SIGCONT)
                resumed = time.monotonic()
                break
            assert froze is not None, "no throw reached its swing"
            res = wait_for(lambda: next((r for r in results if r.throw_id == tid), None), 30, "the frozen throw's result")
            assert res.status == "failed", (res.status, res.failure_reason)
            assert res.failure_reason.startswith(("machine link lost: runtime stalled", "machine link lost: the machine's valve watchdog")), res.failure_reason
            assert res.release_stamp_s is None and "released" not in [s.phase for s in statuses if s.throw_id == tid]
            time.sleep(3.0)  # time enough for the old behaviour: it drove the arm up again and released 1-4 s later
            after = [v for t, v in speeds if t > resumed + 0.5]
            assert after and max(after) < 0.05, f"the arm moved after SIGCONT: {max(after):.2f} rad/s"
            assert not info().busy
            for sub in subs:
                sub.undeclare()
    finally:
        for proc in (plant, runtime):
            if proc is not None:
                _stop(proc)


def test_a_valve_watchdog_trip_stops_a_return_to_the_ready_pose_for_good(holding_path):
    from runtime.protocol.messages import ReturnToReady, ReturnToReadyAck

    loop = Loop(holding_path)
    _run(loop, 5)
    ack = decode(ReturnToReadyAck, loop.service.handle_return_to_ready(encode(sign(ReturnToReady(machine_id="m1"), KEY, "op", EPOCH))))
    assert ack.accepted, ack.reason
    _run(loop, 10)
    assert loop.service.returning
    state = loop.machine_period().model_copy(update={"watchdog_trips": loop.inbox.latch.trips + 1})
    mark = len(loop.sent)
    loop.deliver(state)
    assert not loop.service.returning
    assert loop.service.recovery.status.result == "stopped: machine link lost: the machine's valve watchdog stopped the arm"
    _run(loop, 20)
    assert all(not any(v.u) for v in loop.of(keys.valve_cmd("m1"), ValveCommand, mark))


def test_a_stale_release_command_is_dropped_by_the_plant():
    from runtime.protocol.messages import GripperCommand

    _NOW[0] = 70.0
    inbox = PlantInbox("m1")
    inbox.on_gripper(_Sample(encode(GripperCommand(machine_id="m1", stamp_s=70.0 - STALE_COMMAND_S - 0.1, open=True))))
    assert not inbox.gripper_open  # a release queued at a stalled runtime comes too late
    inbox.on_gripper(_Sample(encode(GripperCommand(machine_id="m1", stamp_s=69.99, open=True))))
    assert inbox.gripper_open
    inbox.on_gripper(_Sample(encode(GripperCommand(machine_id="m1", stamp_s=10.0, open=False))))
    assert not inbox.gripper_open  # closing is always obeyed


def test_a_machine_whose_clock_changed_is_judged_afresh_after_a_second(holding_path):
    """A bridge restarted with another clock: its states all look late at first (dropped, the
    machine offline), then the runtime takes its new clock as the baseline and follows it."""
    loop = Loop(holding_path)
    _run(loop, 20)
    for k in range(150):  # 1.5 s of states stamped 100 s in the past
        state = loop.machine_period()
        loop.service.on_state(encode(state.model_copy(update={"stamp_s": state.stamp_s - 100.0})))
        if k == 50:
            assert loop.service.stale_states == 51
            assert decode(ThrowAck, loop.service.handle_throw(_throw("c1"))).reason == "machine offline (no recent state)"
    assert loop.service.stale_states < 110 and loop.service.info().machine_online
    assert decode(ThrowAck, loop.service.handle_throw(_throw("c2"))).accepted


def test_a_short_idle_stall_refuses_no_command(holding_path):
    """A loaded host stalls an idle runtime for a few hundred ms: a throw the server is still
    waiting for is not refused (a stall of a second or more refuses what queued meanwhile)."""
    loop = Loop(holding_path)
    _run(loop, 5)
    pending = _throw("t1")
    loop.now_s += 0.4
    _run(loop, 3)
    assert loop.service.stalls == 1 and decode(ThrowAck, loop.service.handle_throw(pending)).accepted


def test_a_watchdog_after_the_release_stops_the_arm_and_the_throw_still_lands(tmp_path):
    """The payload is out: a watchdog trip (or a stall) then holds the arm with neutral valves for
    good, and the impact report still lands the throw (a landed throw is not reported failed)."""
    from runtime.protocol.messages import ImpactReport

    policy = write_test_policy(tmp_path, "2d", release_after_bias=2.0)  # releases at the first step
    ex, twin = _started(policy, "r1")
    for _ in range(5):
        out = ex.tick(twin.state())
        twin.step(out.valve_u, out.gripper_open)
    assert ex.phase == "released"
    st = twin.state()
    out = ex.tick(st.model_copy(update={"watchdog_trips": 1}))
    assert out.finished is None and ex.phase == "released" and not any(out.valve_u)
    assert [e.detail for e in out.events] == ["arm stopped: machine link lost: the machine's valve watchdog stopped the arm"]
    for k in range(20):  # fresh states afterwards: the arm stays stopped
        out = ex.tick(st.model_copy(update={"stamp_s": st.stamp_s + 0.01 * (k + 1), "watchdog_trips": 1}))
        assert not any(out.valve_u) and out.finished is None
    impact = ImpactReport(machine_id="m1", stamp_s=st.stamp_s + 0.3, impact_pos_m=[7.8, -0.3, 0.0], opening_stamp_s=st.stamp_s,
                          impact_stamp_s=st.stamp_s + 0.3, release_pos_m=[3.0, 0.0, 2.0], release_vel_mps=[5.0, 0.0, 3.0])
    done = ex.on_impact(impact).finished
    assert done is not None and done.status == "landed" and done.failure_reason is None


def _released(policy: Path, throw_id: str) -> tuple[ThrowExecutor, TwinMachine, float]:
    """An executor and twin ticked at 100 Hz until the policy's first release command; the
    release's machine stamp (s)."""
    ex, twin = _started(policy, throw_id)
    for _ in range(50):
        out = ex.tick(twin.state())
        if out.gripper_open:
            return ex, twin, twin.state().stamp_s
        twin.step(out.valve_u, out.gripper_open)
    raise AssertionError("the policy did not release")


def test_a_lost_opening_command_fails_the_throw_and_commands_the_gripper_closed(tmp_path):
    """Hazard RT14: the opening command is lost on the way or dropped by the machine as stale (a
    stalled runtime): the gripper stays closed. The throw fails "gripper did not open" about a
    second after the release command, not "no impact" six seconds later, and the gripper is
    commanded closed, so that no opening arrives late. Against it: a gripper that opens after
    its delay, and a worn one three times slower, are not failed."""
    policy = write_test_policy(tmp_path, "2d", release_after_bias=2.0)  # releases at the first step
    ex, twin, released_s = _released(policy, "g1")
    assert ex.phase == "released"
    commands, out = [], None
    for _ in range(200):  # the machine never sees the opening: it keeps stepping with the gripper closed
        twin.step(out.valve_u if out is not None else np.zeros(4), False)
        out = ex.tick(twin.state())
        commands.append(out.gripper_open)
        if out.finished is not None:
            break
    done = out.finished
    assert done is not None and done.status == "failed", done
    assert done.failure_reason.startswith("gripper did not open within 1.0 s of the release command"), done.failure_reason
    assert 1.0 < done.end_stamp_s - released_s <= 1.02 and done.opening_stamp_s is None
    assert commands[0] and not commands[-1] and not any(out.valve_u) and not ex.busy
    assert twin.sim.payload_attached  # still held: nothing was thrown

    ex, twin, released_s = _released(policy, "g2")  # the twin's gripper opens after its delay (258 ms)
    out = ex.tick(twin.state())
    for _ in range(150):
        twin.step(out.valve_u, out.gripper_open)
        out = ex.tick(twin.state())
        assert out.finished is None or not out.finished.failure_reason.startswith("gripper"), out.finished
        if out.finished is not None:
            break
    assert ex.phase in ("released", "idle") and out.gripper_open

    ex, twin, released_s = _released(policy, "g3")  # a worn gripper: open 0.9 s after the command
    st = twin.state()
    for k in range(1, 100):
        out = ex.tick(st.model_copy(update={"stamp_s": released_s + 0.01 * k, "gripper_open": k >= 90}))
        assert out.finished is None and out.gripper_open


def test_the_runtime_sends_the_opening_once_and_closes_the_gripper_after_it_was_lost(tmp_path):
    """Hazard RT14 through the runtime service: the one opening command is lost before the plant;
    the throw fails "gripper did not open", the runtime does not resend the opening (it would be
    a late release) and sends a closing command, which the plant obeys."""
    from runtime.protocol.messages import GripperCommand

    loop = Loop(write_test_policy(tmp_path, "2d", release_after_bias=2.0))
    lost, on_gripper = [], loop.inbox.on_gripper

    def lossy(sample) -> None:
        if decode(GripperCommand, sample.to_bytes()).open:
            lost.append(sample)
            return
        on_gripper(sample)

    loop.inbox.on_gripper = lossy
    _run(loop, 5)
    assert decode(ThrowAck, loop.service.handle_throw(_throw("o1"))).accepted
    for _ in range(600):
        _run(loop, 1)
        if loop.results:
            break
    result = loop.results[-1]
    assert result.throw_id == "o1" and result.status == "failed"
    assert result.failure_reason.startswith("gripper did not open within 1.0 s"), result.failure_reason
    assert [g.open for g in loop.of(keys.gripper_cmd("m1"), GripperCommand)][-2:] == [True, False] and len(lost) == 1
    assert not loop.inbox.gripper_open and loop.twin.sim.payload_attached


@pytest.mark.parametrize("fault, why", [({"gripper_open": True}, "the gripper opened"),
                                        ({"payload_attached": False}, "the payload is no longer attached")])
def test_a_payload_lost_before_the_release_command_stops_the_arm_at_once(holding_path, fault, why):
    """Hazard RT15: the gripper opens by itself or the load slips out mid-swing (no release was
    commanded). The throw fails at the first state that shows it with valves neutral, instead of
    swinging on with nothing to throw until the release timeout (10 s)."""
    ex, twin = _executor_at_swing(holding_path)
    out = ex.tick(twin.state())
    assert out.finished is None and any(out.valve_u)  # swinging, valves driven
    twin.step(out.valve_u, out.gripper_open)
    out = ex.tick(twin.state().model_copy(update=fault))
    assert out.finished is not None and out.finished.status == "failed"
    assert out.finished.failure_reason == f"payload lost during the swing: {why} without a release command"
    assert not any(out.valve_u) and not out.gripper_open and not ex.busy
