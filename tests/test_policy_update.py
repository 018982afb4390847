"""runtime.policy_update without Zenoh: SHA-256 check, manifest checks, swap only between throws."""

from __future__ import annotations

import json
import time

from runtime.command_auth import CommandVerifier, sign
from runtime.executor import ThrowExecutor
from runtime.policy import PolicyRunner
from runtime.protocol.messages import PolicyOffer, PolicyOfferAck, decode, encode
from runtime.policy_update import PolicyUpdater
from tests.fixtures import write_test_policy


class Busy:
    busy = True


KEY = bytes(range(32))


def _offer(path, machine_id="m1", signed=True):
    m = json.loads(path.with_suffix(".json").read_text())
    offer = PolicyOffer(machine_id=machine_id, mode="2d", version=m["name"], sha256=m["onnx_sha256"], manifest=m)
    return sign(offer, KEY, "alice", 0) if signed else offer


def _updater(tmp_path, fetch, updates):
    return PolicyUpdater("m1", tmp_path / "store", fetch, updates.append, authorize=CommandVerifier(KEY, 0).check)


def _wait(pred, timeout=10):
    end = time.monotonic() + timeout
    while time.monotonic() < end and not pred():
        time.sleep(0.02)
    return pred()


def test_fetch_check_and_swap_between_throws(tmp_path):
    import threading

    old = PolicyRunner.load(write_test_policy(tmp_path / "old", "2d", name="old"))
    new = write_test_policy(tmp_path / "new", "2d", name="new", seed=5)
    updates = []
    up = _updater(tmp_path, lambda sha: new.read_bytes(), updates)
    ack = decode(PolicyOfferAck, up.handle_offer(encode(_offer(new))))
    assert ack.accepted
    lock = threading.RLock()
    assert _wait(lambda: up._pending)
    assert up.apply_pending(Busy(), lock) == []  # a throw is running: keep the old policy
    ex = ThrowExecutor({"2d": old})
    assert up.apply_pending(ex, lock) == ["2d"]
    assert ex.policies["2d"].version == "new" and updates[-1].status == "loaded"


def test_sha_mismatch_and_wrong_machine_are_refused(tmp_path):
    new = write_test_policy(tmp_path / "new", "2d", name="new")
    updates = []
    up = _updater(tmp_path, lambda sha: b"tampered" + new.read_bytes(), updates)
    assert decode(PolicyOfferAck, up.handle_offer(encode(_offer(new)))).accepted
    assert _wait(lambda: updates)
    assert updates[0].status == "failed" and "SHA-256 mismatch" in updates[0].reason
    ack = decode(PolicyOfferAck, up.handle_offer(encode(_offer(new, "m2"))))
    assert not ack.accepted and "m1" in ack.reason
    assert not decode(PolicyOfferAck, up.handle_offer(b"{nonsense")).accepted


def test_unsigned_or_replayed_offers_are_refused_without_fetching(tmp_path):
    new = write_test_policy(tmp_path / "new", "2d", name="new")
    fetched = []
    up = _updater(tmp_path, lambda sha: fetched.append(sha) or new.read_bytes(), [])
    ack = decode(PolicyOfferAck, up.handle_offer(encode(_offer(new, signed=False))))
    assert not ack.accepted and ack.reason == "unsigned"
    offer = encode(_offer(new))
    assert decode(PolicyOfferAck, up.handle_offer(offer)).accepted
    ack = decode(PolicyOfferAck, up.handle_offer(offer))
    assert not ack.accepted and ack.reason == "replayed nonce"
    assert _wait(lambda: fetched) and len(fetched) == 1
