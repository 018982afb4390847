"""Policy updates on the runtime: accept an offered policy version, fetch its file from the
server, check its SHA-256 and manifest, and swap it into the executor only between throws.

Flow: PolicyOffer (query; must pass ``authorize``: signed with the machine's command key for
this runtime's epoch, fresh, not replayed) -> PolicyOfferAck at once -> a worker thread fetches the bytes
(keys.policy_file), writes ``<policy_dir>/<sha256>.onnx`` + manifest, loads it with
runtime.policy.PolicyRunner (all manifest, hash and graph checks) -> pending;
:meth:`PolicyUpdater.apply_pending` (called periodically by the node) installs pending policies
while the executor is idle and publishes PolicyUpdate("loaded"); any failure publishes
PolicyUpdate("failed", reason) and leaves the running policy untouched.
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from runtime.policy import PolicyError, PolicyRunner
from runtime.protocol.messages import PolicyOffer, PolicyOfferAck, PolicyUpdate, ValidationError, decode, encode

log = logging.getLogger(__name__)


class PolicyUpdater:
    """Args:
        machine_id: this runtime's machine.
        policy_dir: where fetched policy files are kept.
        fetch: returns the file bytes for a SHA-256 (raises on failure).
        publish: sends a PolicyUpdate.
        authorize: returns why an offer may not run (e.g. RuntimeService.authorize: "unsigned",
            "no command key configured", ...) or None; offers it refuses are acked accepted=False.
    """

    def __init__(self, machine_id: str, policy_dir: Path, fetch: Callable[[str], bytes],
                 publish: Callable[[PolicyUpdate], None], authorize: Callable[[PolicyOffer], str | None]):
        self.machine_id = machine_id
        self.authorize = authorize
        self.policy_dir = Path(policy_dir)
        self.fetch, self.publish = fetch, publish
        self._pending: dict[str, PolicyRunner] = {}
        self._lock = threading.Lock()
        self._threads: list[threading.Thread] = []

    def handle_offer(self, payload: bytes) -> bytes:
        """PolicyOffer -> PolicyOfferAck; the fetch and checks run on a worker thread."""
        try:
            offer = decode(PolicyOffer, payload)
        except ValidationError as e:
            return encode(PolicyOfferAck(machine_id=self.machine_id, accepted=False, reason=f"malformed offer: {e.errors()[0]['msg']}"))
        if offer.machine_id != self.machine_id:
            return encode(PolicyOfferAck(machine_id=self.machine_id, accepted=False, reason=f"this runtime serves {self.machine_id!r}"))
        denied = self.authorize(offer)
        if denied:
            log.warning("policy offer %s refused: %s", offer.version, denied)
            return encode(PolicyOfferAck(machine_id=self.machine_id, accepted=False, reason=denied))
        if offer.manifest.get("mode") != offer.mode:
            return encode(PolicyOfferAck(machine_id=self.machine_id, accepted=False, reason="manifest mode differs from the offer"))
        t = threading.Thread(target=self._install, args=(offer,), name="policy-fetch", daemon=True)
        self._threads = [x for x in self._threads if x.is_alive()] + [t]
        t.start()
        return encode(PolicyOfferAck(machine_id=self.machine_id, accepted=True))

    def _install(self, offer: PolicyOffer) -> None:
        try:
            data = self.fetch(offer.sha256)
            digest = hashlib.sha256(data).hexdigest()
            if digest != offer.sha256:
                raise PolicyError(f"SHA-256 mismatch: fetched {digest[:12]}…, offered {offer.sha256[:12]}…")
            self.policy_dir.mkdir(parents=True, exist_ok=True)
            path = self.policy_dir / f"{offer.sha256}.onnx"
            path.write_bytes(data)
            path.with_suffix(".json").write_text(json.dumps(offer.manifest, indent=2))
            runner = PolicyRunner.load(path)
            if runner.mode != offer.mode:
                raise PolicyError(f"a {runner.mode} policy offered for {offer.mode}")
            runner.act(np.zeros(runner.manifest["observation_size"], dtype=np.float32))  # warmed before it runs a throw
        except Exception as e:  # noqa: BLE001  fetch errors, PolicyError, OSError
            log.error("policy %s (%s) not loaded: %s", offer.version, offer.mode, e)
            self._publish(offer, "failed", str(e))
            return
        with self._lock:
            self._pending[offer.mode] = runner
        log.info("policy %s fetched and checked; loads between throws", offer.version)

    def apply_pending(self, executor, lock) -> list[str]:
        """Install pending policies if the executor is idle (under ``lock``); returns the modes
        installed."""
        with self._lock:
            if not self._pending:
                return []
        with lock:
            if executor.busy:
                return []
            with self._lock:
                pending, self._pending = self._pending, {}
            for mode, runner in pending.items():
                executor.policies[mode] = runner
        for mode, runner in pending.items():
            log.info("%s policy is now %s (sha256 %s…)", mode, runner.version, runner.sha256[:12])
            self._publish_runner(runner)
        return list(pending)

    def _publish_runner(self, runner: PolicyRunner) -> None:
        self.publish(PolicyUpdate(machine_id=self.machine_id, stamp_s=time.monotonic(), mode=runner.mode,
                                  version=runner.version, sha256=runner.sha256, status="loaded"))

    def _publish(self, offer: PolicyOffer, status: str, reason: str | None) -> None:
        self.publish(PolicyUpdate(machine_id=self.machine_id, stamp_s=time.monotonic(), mode=offer.mode,
                                  version=offer.version, sha256=offer.sha256, status=status, reason=reason))


def zenoh_fetcher(session, timeout_s: float = 30.0) -> Callable[[str], bytes]:
    """A ``fetch`` that queries keys.policy_file(sha256) on ``session``."""
    from runtime.protocol import keys

    def fetch(sha256: str) -> bytes:
        for reply in session.get(keys.policy_file(sha256), timeout=timeout_s):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            raise PolicyError(f"server refused the file: {reply.err.payload.to_string()}")
        raise PolicyError(f"no reply for policy file {sha256[:12]}… within {timeout_s:.0f} s")

    return fetch
