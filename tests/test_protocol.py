"""Protocol: keys, message validation, Zenoh config, and the README covering every key."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from runtime.protocol import keys, messages
from runtime.protocol.messages import MachineState, SimReset, ThrowRequest, ValidationError, ValveCommand, decode, encode
from runtime.zenoh_session import open_session, zenoh_config

README = Path(__file__).resolve().parents[1] / "runtime" / "protocol" / "README.md"


def _state(**kw) -> MachineState:
    base = dict(machine_id="m1", stamp_s=1.0, q=[0.0] * 6, qd=[0.0] * 6, gripper_open=False, payload_attached=True)
    return MachineState(**{**base, **kw})


@pytest.mark.parametrize("bad", ["", "m/1", "m*", "**", "$*", "a" * 65, "m 1"])
def test_machine_ids_cannot_inject_wildcards(bad):
    with pytest.raises(ValueError):
        keys.state(bad)


def test_keys_compose_and_parse():
    assert keys.state("m1") == "slinger/machine/m1/state"
    assert keys.sim_reset("m1") == "slinger/machine/m1/sim/reset"
    assert keys.throw("m-2") == "slinger/runtime/m-2/throw"
    assert keys.machine_id_of(keys.runtime_alive("abc")) == "abc"
    assert zenoh.KeyExpr(keys.ALL_STATES).intersects(zenoh.KeyExpr(keys.state("m1")))


def test_messages_roundtrip_and_reset_count():
    st = _state(reset_count=3, simulated=True, payload_pos_m=[1.0, 2.0, 3.0], payload_vel_mps=[0.0, 0.0, 0.0])
    assert decode(MachineState, encode(st)) == st
    assert decode(MachineState, encode(_state())).reset_count is None
    with pytest.raises(ValidationError):
        _state(reset_count=-1)


@pytest.mark.parametrize(
    "payload",
    [
        b"{not json",
        b'{"machine_id": "m1"}',
        json.dumps({**json.loads(encode(_state())), "q": [float("nan")] + [0.0] * 5}).replace("NaN", "NaN").encode(),
        json.dumps({**json.loads(encode(_state())), "qd": [0.0] * 5}).encode(),
        json.dumps({**json.loads(encode(_state())), "extra": 1}).encode(),
        json.dumps({**json.loads(encode(_state())), "schema_version": 2}).encode(),
        json.dumps({**json.loads(encode(_state())), "machine_id": "m/*"}).encode(),
    ],
)
def test_malformed_states_are_rejected(payload):
    with pytest.raises(ValidationError):
        decode(MachineState, payload)


def test_valve_commands_must_lie_in_the_unit_interval():
    ValveCommand(machine_id="m1", stamp_s=0.0, u=[1.0, -1.0, 0.0, 0.5])
    with pytest.raises(ValidationError):
        ValveCommand(machine_id="m1", stamp_s=0.0, u=[1.5, 0.0, 0.0, 0.0])
    with pytest.raises(ValidationError):
        ThrowRequest(throw_id="t", machine_id="m1", mode="4d", target_m=[1, 2, 3])
    assert SimReset(machine_id="m1", stamp_s=0.0).q_active is None


def test_zenoh_config_is_explicit():
    conf = zenoh_config("client", connect=["tcp/127.0.0.1:7447"])
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("listen/endpoints")) == []
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(zenoh_config(multicast_scouting=True).get_json("scouting/multicast/enabled")) is True
    with pytest.raises(ValueError):
        zenoh_config("server")
    with pytest.raises(ValueError):
        zenoh_config(listen=["127.0.0.1:7447"])


def test_isolated_session_opens_and_closes():
    with open_session() as session:
        received = []
        sub = session.declare_subscriber("slinger/test/x", lambda s: received.append(s.payload.to_bytes()))
        session.put("slinger/test/x", b"1")
        sub.undeclare()
    assert session.is_closed()


def test_readme_documents_every_key_and_message():
    text = README.read_text()
    names = ("state", "valve_cmd", "gripper_cmd", "impact", "sim_reset", "machine_alive", "throw", "abort", "info", "status",
             "runtime_alive", "estop_reset", "runtime_state")
    for name in names:
        key = getattr(keys, name)("ID").replace("ID", "<id>")
        assert f"`{key}`" in text, key
    assert f"`{keys.THROW_RESULT}`" in text
    for cls in messages.Message.__subclasses__() + messages.Stamped.__subclasses__():
        if cls is not messages.Stamped:
            assert f"`{cls.__name__}`" in text, cls.__name__
