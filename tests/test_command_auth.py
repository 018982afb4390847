"""Signed commands (runtime/command_auth.py): what the runtime accepts and why it refuses."""

from __future__ import annotations

import os

import pytest

from runtime import command_auth
from runtime.command_auth import CommandVerifier, load_key, sign, verify_mac, write_key
from runtime.protocol.messages import (
    AbortRequest,
    EstopReset,
    PolicyOffer,
    ThrowRequest,
    ThrowResult,
    decode,
    encode,
)

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
EPOCH = 7
NOW = 1_800_000_000.0


def _throw(**kw) -> ThrowRequest:
    return ThrowRequest(**{"throw_id": "t1", "machine_id": "m1", "mode": "2d", "target_m": [10.0, 0.0, 0.0], **kw})


def _verifier(**kw) -> CommandVerifier:
    return CommandVerifier(KEY, EPOCH, **kw)


def test_signed_command_passes_once_after_the_wire():
    msg = sign(_throw(), KEY, "alice", EPOCH, now_unix_s=NOW)
    assert msg.auth.user == "alice" and len(msg.auth.mac) == 64 and len(msg.auth.nonce) == 32
    wire = decode(ThrowRequest, encode(msg))
    v = _verifier()
    assert v.check(wire, now_unix_s=NOW + 0.5) is None
    assert v.check(wire, now_unix_s=NOW + 0.6) == "replayed nonce"


def test_unsigned_command_is_refused():
    assert _verifier().check(_throw(), now_unix_s=NOW) == "unsigned"


@pytest.mark.parametrize(
    "change",
    [
        {"target_m": [10.0, 0.0, 0.1]},
        {"mode": "3d"},
        {"machine_id": "m2"},
        {"throw_id": "t2"},
    ],
)
def test_tampered_field_breaks_the_signature(change):
    msg = sign(_throw(), KEY, "alice", EPOCH, now_unix_s=NOW)
    assert _verifier().check(msg.model_copy(update=change), now_unix_s=NOW) == "bad signature"


def test_tampered_auth_fields_break_the_signature():
    msg = sign(_throw(), KEY, "alice", EPOCH, now_unix_s=NOW)
    for change in ({"user": "mallory"}, {"issued_unix_s": NOW + 1}, {"nonce": "0" * 32}):
        forged = msg.model_copy(update={"auth": msg.auth.model_copy(update=change)})
        assert _verifier().check(forged, now_unix_s=NOW) == "bad signature"


def test_wrong_key_is_a_bad_signature():
    msg = sign(_throw(), OTHER_KEY, "alice", EPOCH, now_unix_s=NOW)
    assert _verifier().check(msg, now_unix_s=NOW) == "bad signature"


def test_stale_and_future_dated_commands_are_refused():
    assert _verifier().check(sign(_throw(), KEY, "a", EPOCH, now_unix_s=NOW - 12.3), now_unix_s=NOW) == (
        "stale (issued 12.3 s ago)"
    )
    assert _verifier().check(sign(_throw(), KEY, "a", EPOCH, now_unix_s=NOW + 7.0), now_unix_s=NOW) == (
        "issued 7.0 s in the future"
    )
    assert _verifier(window_s=20.0).check(sign(_throw(), KEY, "a", EPOCH, now_unix_s=NOW - 12.3), now_unix_s=NOW) is None


def test_wrong_epoch_is_refused_with_both_epochs():
    msg = sign(_throw(), KEY, "alice", 5, now_unix_s=NOW)
    assert _verifier().check(msg, now_unix_s=NOW) == "wrong epoch: addressed 5, this runtime is 7"


def test_replay_cache_is_bounded_and_forgets_only_expired_nonces():
    v = _verifier(window_s=1.0, max_nonces=3)
    for i in range(3):
        assert v.check(sign(_throw(), KEY, "a", EPOCH, now_unix_s=NOW), now_unix_s=NOW) is None
    assert v.check(sign(_throw(), KEY, "a", EPOCH, now_unix_s=NOW), now_unix_s=NOW) == "replay cache full"
    # Once the first three could no longer be fresh they are dropped and room is free again.
    later = sign(_throw(), KEY, "a", EPOCH, now_unix_s=NOW + 2.0)
    assert v.check(later, now_unix_s=NOW + 2.0) is None
    assert len(v._seen) == 1


def test_every_command_type_and_results_can_be_signed():
    sha = "a" * 64
    for msg in (
        AbortRequest(machine_id="m1"),
        EstopReset(machine_id="m1"),
        PolicyOffer(machine_id="m1", mode="2d", version="v1", sha256=sha, manifest={"x": [1.5, 2], "n": "é"}),
        ThrowResult(machine_id="m1", stamp_s=1.0, throw_id="t", mode="2d", status="landed", target_m=[1, 2, 3], duration_s=2.0),
    ):
        signed = sign(msg, KEY, "runtime:m1", EPOCH)
        assert verify_mac(decode(type(msg), encode(signed)), KEY) is None
        assert verify_mac(msg, KEY) == "unsigned"
    with pytest.raises(ValueError, match="no auth field"):
        sign(command_auth.CommandAuth(user="u", issued_unix_s=0.0, nonce="0" * 32, epoch=0), KEY, "u", 0)


def test_key_files(tmp_path):
    path = write_key(tmp_path / "machines" / "m1" / "command.key", KEY)
    assert os.stat(path).st_mode & 0o777 == 0o600
    assert load_key(path) == KEY
    (tmp_path / "bad.key").write_text("abc")
    with pytest.raises(ValueError, match="64 hex digits"):
        load_key(tmp_path / "bad.key")
    with pytest.raises(FileNotFoundError):
        load_key(tmp_path / "missing.key")
    with pytest.raises(ValueError):
        CommandVerifier(b"short", 0)
    with pytest.raises(ValueError):
        sign(_throw(), b"short", "a", 0)
