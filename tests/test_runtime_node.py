"""The runtime's message handling (RuntimeService, driven without Zenoh, with the simulated
machine on the other side of the wire messages), its bad-input paths, and a Zenoh integration
test with the plant and the runtime as subprocesses on loopback."""

from __future__ import annotations

import argparse
import base64
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from runtime import node
from runtime.command_auth import CommandVerifier, sign, verify_mac, write_key
from runtime.executor import ExecutorConfig, ThrowExecutor
from runtime.policy import PolicyError, PolicyRunner, build_manifest, write_manifest
from runtime.protocol import keys
from runtime.protocol.messages import (
    AbortAck,
    EstopReset,
    EstopResetAck,
    GripperCommand,
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
from runtime.service import RuntimeService
from runtime.telemetry import read_telemetry
from runtime.throw_geometry import ARM_PLANE_OFFSET_M
from runtime.zenoh_session import open_session
from sim_twin.twin.simulated_machine import SimulatedMachine
from sim_twin.twin.twin_machine import TwinMachine
from tests.conftest import free_port, wait_for
from tests.fixtures import write_test_policy

REPO = Path(__file__).resolve().parents[1]
TARGET = [8.0, ARM_PLANE_OFFSET_M, 0.0]


@pytest.fixture(scope="module")
def policy_path(tmp_path_factory) -> Path:
    return write_test_policy(tmp_path_factory.mktemp("pol"), "2d", release_after_bias=2.0)


@pytest.fixture(scope="module")
def holding_path(tmp_path_factory) -> Path:
    return write_test_policy(tmp_path_factory.mktemp("hold"), "2d", name="hold", release_after_bias=-2.0)


KEY = bytes(range(32))
EPOCH = 1_700_000_000_000


def _signed(msg, key=KEY, epoch=EPOCH, **kw):
    return encode(sign(msg, key, "alice", epoch, **kw))


def _throw_payload(throw_id="t1", target=TARGET, mode="2d", machine_id="m1", epoch=EPOCH, signed=True) -> bytes:
    req = ThrowRequest(throw_id=throw_id, machine_id=machine_id, mode=mode, target_m=target)
    return _signed(req, epoch=epoch) if signed else encode(req)


class Harness:
    """RuntimeService (command key KEY, epoch EPOCH) + a simulated machine that obeys the
    service's wire messages and reloads itself as the plant does."""

    def __init__(self, path: Path, verifier: CommandVerifier | None = CommandVerifier(KEY, EPOCH)):
        self.sent: list[tuple[str, bytes]] = []
        self.results: list[ThrowResult] = []
        self.now_s = 100.0
        ex = ThrowExecutor({"2d": PolicyRunner.load(path)}, config=ExecutorConfig(release_check_radius_m=None))  # test policies do not throw
        if verifier is not None:
            verifier = CommandVerifier(verifier.key, verifier.epoch)  # a fresh replay cache
        self.service = RuntimeService("m1", ex, lambda k, d: self.sent.append((k, d)), self.results.append,
                                      verifier=verifier, clock=lambda: self.now_s)
        self.twin = TwinMachine(SimulatedMachine(seed=1), "m1")
        self.valve_u, self.gripper_open, self._seen = np.zeros(4), False, 0

    def of(self, key: str, cls):
        return [decode(cls, d) for k, d in self.sent if k == key]

    def tick(self, n: int = 1) -> None:
        for _ in range(n):
            self.service.on_state(encode(self.twin.state()))
            for key, data in self.sent[self._seen :]:
                if key == keys.valve_cmd("m1"):
                    self.valve_u = np.asarray(decode(ValveCommand, data).u)
                elif key == keys.gripper_cmd("m1"):
                    self.gripper_open = decode(GripperCommand, data).open
            self._seen = len(self.sent)
            report = self.twin.step(self.valve_u, self.gripper_open)
            if report is None and self.twin.reload_if_due():
                self.gripper_open = False
            self.now_s += 0.01
            if report is not None:
                self.service.on_impact(encode(report))


def test_service_runs_a_throw_over_wire_messages(policy_path):
    h = Harness(policy_path)
    h.tick()
    ack = decode(ThrowAck, h.service.handle_throw(_throw_payload()))
    assert ack.accepted and ack.policy_version == "test-linear"
    for _ in range(300):
        h.tick()
        if h.results:
            break
    phases = [s.phase for s in h.of(keys.status("m1"), ThrowStatus)]
    assert phases == ["preparing", "swinging", "released", "landed"]
    res = h.results[0]
    assert res.status == "landed" and res.impact_m is not None and res.downrange_error_m is not None
    assert len(read_telemetry(base64.b64decode(res.telemetry_mcap_b64))["t_s"]) > 10
    assert verify_mac(res, KEY) is None and res.auth.user == "runtime:m1" and res.auth.epoch == EPOCH
    valves = h.of(keys.valve_cmd("m1"), ValveCommand)
    assert len(valves) >= 10 and {v.epoch for v in valves} == {EPOCH}  # one per state tick
    assert [g.open for g in h.of(keys.gripper_cmd("m1"), GripperCommand)] == [False, True]
    assert not any(k.endswith("sim/reset") for k, _ in h.sent)  # the runtime never resets a machine
    h.tick(110)  # the simulated machine reloads by itself a second after the landing
    assert h.twin.reset_count == 1 and h.twin.state().payload_attached and not h.twin.state().gripper_open
    info = decode(RuntimeInfo, h.service.handle_info())
    assert not info.busy and info.machine_online and info.simulated and info.ready and info.epoch == EPOCH
    assert info.policies[0].version == "test-linear" and len(info.policies[0].sha256) == 64
    # a second throw from where the machine waits, loaded
    assert decode(ThrowAck, h.service.handle_throw(_throw_payload("t2"))).accepted


def test_malformed_nan_and_foreign_states_are_dropped(policy_path):
    h = Harness(policy_path)
    good = json.loads(encode(h.twin.state()))
    bad = [b"garbage", json.dumps({**good, "q": [float("nan")] * 6}).encode(), json.dumps({**good, "machine_id": "m2"}).encode(), json.dumps({**good, "qd": [0.0]}).encode()]
    for payload in bad:
        h.service.on_state(payload)
    assert h.service.dropped == 4 and h.sent == [] and h.service.latest_state is None
    h.service.on_impact(b"{}")
    assert h.service.dropped == 5
    h.tick()
    assert len(h.of(keys.valve_cmd("m1"), ValveCommand)) == 1


def test_refusals_offline_busy_malformed_and_out_of_reach(policy_path):
    h = Harness(policy_path)
    assert "offline" in decode(ThrowAck, h.service.handle_throw(_throw_payload())).reason
    h.tick()
    far = decode(ThrowAck, h.service.handle_throw(_throw_payload(target=[30.0, -0.3, 0.0])))
    assert not far.accepted and "beyond" in far.reason
    assert "3d" in decode(ThrowAck, h.service.handle_throw(_throw_payload(mode="3d", target=[6.0, 5.0, 0.0]))).reason
    assert "serves" in decode(ThrowAck, h.service.handle_throw(_throw_payload(machine_id="m2"))).reason
    bad = decode(ThrowAck, h.service.handle_throw(b'{"throw_id": "x"}'))
    assert not bad.accepted and "malformed" in bad.reason
    assert decode(ThrowAck, h.service.handle_throw(_throw_payload("a"))).accepted
    busy = decode(ThrowAck, h.service.handle_throw(_throw_payload("b")))
    assert not busy.accepted and "busy" in busy.reason


def test_dropped_link_fails_the_throw_with_neutral_valves(holding_path):
    h = Harness(holding_path)
    h.tick()
    assert decode(ThrowAck, h.service.handle_throw(_throw_payload())).accepted
    h.tick(30)
    assert h.service.executor.phase == "swinging"
    assert np.any(h.of(keys.valve_cmd("m1"), ValveCommand)[-1].u)
    h.now_s += 0.15  # the machine goes silent
    assert not h.service.check_watchdog()
    h.now_s += 0.1
    assert h.service.check_watchdog()
    assert h.of(keys.valve_cmd("m1"), ValveCommand)[-1].u == [0.0] * 4
    status = h.of(keys.status("m1"), ThrowStatus)[-1]
    assert status.phase == "failed" and status.detail == "machine link lost"
    assert h.results[-1].status == "failed" and h.results[-1].failure_reason == "machine link lost"
    assert not h.service.check_watchdog()  # idle now: nothing more to fail


def _reset(h, **kw) -> EstopResetAck:
    return decode(EstopResetAck, h.service.handle_estop_reset(kw.pop("payload", None) or _signed(EstopReset(machine_id="m1"), **kw)))


def test_abort_latches_estop_until_a_signed_reset(holding_path):
    h = Harness(holding_path)
    h.tick()
    h.service.handle_throw(_throw_payload("t7"))
    h.tick(20)
    ack = decode(AbortAck, h.service.handle_abort(b'{"machine_id": "m1", "reason": "stop!"}'))  # unsigned: honoured
    assert ack.aborted_throw_id == "t7"
    assert h.results[-1].status == "aborted" and h.results[-1].failure_reason == "stop!"
    h.tick(5)
    assert all(v.u == [0.0] * 4 for v in h.of(keys.valve_cmd("m1"), ValveCommand)[-6:])
    refused = decode(ThrowAck, h.service.handle_throw(_throw_payload("t8")))
    assert not refused.accepted and refused.reason == "E-STOP latched: stop!"
    info = h.service.info()
    assert info.estop_latched and info.estop_reason == "stop!" and not info.ready and info.not_ready_reason == "E-STOP latched"
    assert _reset(h, payload=encode(EstopReset(machine_id="m1"))).reason == "unsigned"
    assert _reset(h, key=bytes(32)).reason == "bad signature"
    assert _reset(h, epoch=EPOCH - 1).reason.startswith("wrong epoch")
    assert h.service.estop_reason == "stop!"
    assert _reset(h).reset
    assert not h.service.info().estop_latched
    for _ in range(300):  # stopped mid-swing: READY once the arm is at rest
        if h.service.info().ready:
            break
        assert h.service.info().not_ready_reason.startswith("machine moving")
        h.tick()
    assert decode(ThrowAck, h.service.handle_throw(_throw_payload("t9"))).accepted
    # an empty abort payload (idle or not) latches too
    decode(AbortAck, h.service.handle_abort(b""))
    assert "E-STOP latched" in decode(ThrowAck, h.service.handle_throw(_throw_payload("t10"))).reason


def test_forged_unsigned_replayed_and_stale_throws_are_refused(policy_path):
    h = Harness(policy_path)
    h.tick()
    req = ThrowRequest(throw_id="f1", machine_id="m1", mode="2d", target_m=TARGET)

    def reason(payload):
        ack = decode(ThrowAck, h.service.handle_throw(payload))
        assert not ack.accepted
        return ack.reason

    assert reason(encode(req)) == "unsigned"
    assert reason(_signed(req, key=bytes(32))) == "bad signature"
    signed = sign(req, KEY, "alice", EPOCH)
    assert reason(encode(signed.model_copy(update={"target_m": [9.0, TARGET[1], 0.0]}))) == "bad signature"
    assert reason(_signed(req, epoch=EPOCH + 1)) == f"wrong epoch: addressed {EPOCH + 1}, this runtime is {EPOCH}"
    assert reason(_signed(req, now_unix_s=time.time() - 60)).startswith("stale (issued 60")
    assert decode(ThrowAck, h.service.handle_throw(encode(signed))).accepted
    assert reason(encode(signed)).startswith(("replayed nonce", "runtime busy"))
    assert [st.phase for st in h.of(keys.status("m1"), ThrowStatus)] == ["preparing"]  # only the accepted one runs


def test_without_a_command_key_every_command_but_abort_is_refused(policy_path):
    h = Harness(policy_path, verifier=None)
    h.tick()
    assert decode(ThrowAck, h.service.handle_throw(_throw_payload())).reason == "no command key configured"
    assert _reset(h).reason == "no command key configured"
    assert h.service.info().not_ready_reason == "no command key configured"
    decode(AbortAck, h.service.handle_abort(b""))
    assert h.service.info().estop_latched


def test_machine_fault_refuses_throws_and_fails_a_running_one(holding_path):
    h = Harness(holding_path)
    h.tick()
    fault = "behind real time by 150 ms"
    h.twin.fault = fault
    h.tick()
    ack = decode(ThrowAck, h.service.handle_throw(_throw_payload("t1")))
    assert not ack.accepted and ack.reason == f"machine fault: {fault}"
    assert h.service.info().not_ready_reason == f"machine fault: {fault}"
    h.twin.fault = None
    h.tick()
    assert decode(ThrowAck, h.service.handle_throw(_throw_payload("t2"))).accepted
    h.tick(20)
    h.twin.fault = fault
    h.tick()
    assert h.results[-1].status == "failed" and h.results[-1].failure_reason == f"machine fault: {fault}"
    assert h.of(keys.valve_cmd("m1"), ValveCommand)[-1].u == [0.0] * 4


def test_a_pose_at_a_joint_end_is_not_ready(policy_path):
    h = Harness(policy_path)
    st = h.twin.state()
    q = list(st.q)
    q[3] = 1.8  # telescope fully out
    h.service.on_state(encode(st.model_copy(update={"q": q})))
    assert h.service.info().not_ready_reason == "joint at end: telescope"
    assert decode(ThrowAck, h.service.handle_throw(_throw_payload())).reason == "joint at end: telescope"


def test_runtime_state_is_published_on_change_and_at_2_hz(holding_path):
    h = Harness(holding_path)
    h.tick()

    def infos():
        return h.of(keys.runtime_state("m1"), RuntimeInfo)

    assert len(infos()) == 1 and infos()[0].ready
    h.tick(10)  # 0.1 s, nothing changed
    assert len(infos()) == 1
    h.tick(45)  # 0.55 s in all: the 2 Hz repeat
    assert len(infos()) == 2
    h.service.handle_throw(_throw_payload("t3"))
    assert infos()[-1].busy and infos()[-1].phase == "preparing" and infos()[-1].throw_id == "t3"
    h.tick()
    assert infos()[-1].phase == "swinging"
    h.service.handle_abort(b"")
    assert infos()[-1].estop_latched and infos()[-1].phase is None and not infos()[-1].ready


def test_wrong_onnx_file_is_refused(tmp_path, policy_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"this is not an onnx graph")
    write_manifest(bad, build_manifest(bad, "2d", "bad", (5.0, 10.7)))
    with pytest.raises(PolicyError):
        PolicyRunner.load(bad)
    parser = argparse.ArgumentParser()
    node.build_parser(parser)
    assert node.run(parser.parse_args(["--machine-id", "m1", "--policy-2d", str(bad)])) == 2
    assert node.run(parser.parse_args(["--machine-id", "m1"])) == 2  # no policy at all
    assert node.run(parser.parse_args(["--machine-id", "m1", "--policy-3d", str(policy_path)])) == 2  # wrong mode


# --- Zenoh integration ------------------------------------------------------------------------
def _spawn(args: list[str], log_path: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    log = open(log_path, "wb")
    return subprocess.Popen([sys.executable, "-m", *args], cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)


def _stop(proc: subprocess.Popen) -> int | None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    return proc.returncode


def test_plant_and_runtime_throw_over_zenoh(tmp_path, policy_path):
    port, mid = free_port(), "itest"
    endpoint = f"tcp/127.0.0.1:{port}"
    outbox = tmp_path / "outbox"
    key_file = write_key(tmp_path / "command.key", KEY)
    runtime_args = ["runtime.node", "--machine-id", mid, "--policy-2d", str(policy_path), "--outbox-dir", str(outbox), "--command-key", str(key_file)]
    runtime = _spawn([*runtime_args, "--listen", endpoint], tmp_path / "runtime.log")
    plant = None
    statuses: list[ThrowStatus] = []
    results: list[ThrowResult] = []

    def on_result(query):
        res = decode(ThrowResult, query.payload.to_bytes())
        results.append(res)
        query.reply(query.key_expr, encode(ResultAck(throw_id=res.throw_id, stored=True)))

    try:
        with open_session(connect=[endpoint]) as session:
            subs = [
                session.declare_subscriber(keys.status(mid), lambda s: statuses.append(decode(ThrowStatus, s.payload.to_bytes()))),
                session.declare_queryable(keys.THROW_RESULT, on_result),
            ]

            def info() -> RuntimeInfo | None:
                for reply in session.get(keys.info(mid), timeout=1.0):
                    if reply.ok is not None:
                        return decode(RuntimeInfo, reply.ok.payload.to_bytes())
                return None

            wait_for(lambda: runtime.poll() is not None or info(), 60, "runtime up")
            assert runtime.poll() is None, (tmp_path / "runtime.log").read_text()
            link = ["--connect", endpoint, "--listen", "tcp/127.0.0.1:0"]  # as `slinger up` links its children
            plant = _spawn(["sim_twin.twin.plant", "--machine-id", mid, *link, "--seed", "3"], tmp_path / "plant.log")
            wait_for(lambda: (i := info()) is not None and i.machine_online, 60, "machine online")

            epoch = info().epoch
            res = None
            for attempt in range(3):  # a loaded machine may fall behind real time: a correct refusal, retried
                wait_for(lambda: info().ready, 30, "runtime ready")
                payload = _throw_payload(f"z{attempt}", machine_id=mid, epoch=epoch)
                acks = [decode(ThrowAck, r.ok.payload.to_bytes()) for r in session.get(keys.throw(mid), payload=payload, timeout=5.0) if r.ok]
                assert len(acks) == 1, acks
                if not acks[0].accepted and acks[0].reason.startswith("machine fault: behind real time"):
                    continue
                assert acks[0].accepted, acks
                res = wait_for(lambda: next((r for r in results if r.throw_id == f"z{attempt}"), None), 30, "result")
                if not (res.status == "failed" and res.failure_reason.startswith(("machine fault: behind real time", "machine link lost"))):
                    break
            assert res is not None and res.status == "landed", res and res.failure_reason
            assert res.impact_m is not None and abs(res.impact_m[2]) < 1e-9 and res.downrange_error_m is not None
            assert res.policy_version == "test-linear"
            tel = read_telemetry(base64.b64decode(res.telemetry_mcap_b64))
            assert len(tel["t_s"]) > 10 and np.all(np.diff(tel["t_s"]) > 0)
            assert 0.007 < np.median(np.diff(tel["t_s"])) < 0.013  # ~100 Hz over the wire
            wait_for(lambda: [s.phase for s in statuses][-1:] == ["landed"], 5, "landed status")
            assert [s.phase for s in statuses if s.throw_id == res.throw_id] == ["preparing", "swinging", "released", "landed"]
            assert verify_mac(res, KEY) is None and res.auth.epoch == epoch
            wait_for(lambda: not list(outbox.glob("*.json")), 5, "outbox drained")
            replayed = [decode(ThrowAck, r.ok.payload.to_bytes()) for r in session.get(keys.throw(mid), payload=payload, timeout=5.0) if r.ok]
            assert [a.reason for a in replayed] == ["replayed nonce"]
            # a second runtime and a second plant for the same machine refuse to start (exit 3)
            second = [_spawn([*runtime_args, *link], tmp_path / "runtime2.log"),
                      _spawn(["sim_twin.twin.plant", "--machine-id", mid, *link], tmp_path / "plant2.log")]
            for proc, name in zip(second, ("runtime2.log", "plant2.log")):
                assert proc.wait(20) == 3, (tmp_path / name).read_text()[-2000:]
            assert "already has a runtime" in (tmp_path / "runtime2.log").read_text()
            assert "already has a plant" in (tmp_path / "plant2.log").read_text()
            for sub in subs:
                sub.undeclare()
    finally:
        codes = [_stop(p) for p in (plant, runtime) if p is not None]
    assert codes == [0, 0], [(tmp_path / f).read_text()[-2000:] for f in ("plant.log", "runtime.log")]
