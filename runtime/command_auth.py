"""Signed commands between the server and a machine's runtime (issue 8, shared wire contract).

Every command the runtime executes (ThrowRequest, EstopReset, PolicyOffer; AbortRequest when
the server has a key) carries a :class:`~runtime.protocol.messages.CommandAuth`: the requesting
user, the signer's wall clock, a fresh nonce, the runtime claim epoch it addresses and an
HMAC-SHA256 (RFC 2104, Python's :mod:`hmac`) with the machine's 32-byte command key over the
canonical JSON of the whole message with ``auth.mac = ""``::

    json.dumps(msg.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))

Runtime results (ThrowResult) are MAC'ed the same way by the runtime (user "runtime:<id>") and
checked by the server with :func:`verify_mac` (no freshness: the outbox may deliver late).

The key file holds the key as 64 hex digits (``<site_dir>/machines/<id>/command.key``, mode
0600, written by ``slinger certs``). The server reads every machine's key, a runtime only its own.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import secrets
import stat
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from runtime.protocol.messages import CommandAuth, Message

log = logging.getLogger(__name__)

KEY_BYTES = 32
DEFAULT_WINDOW_S = 5.0
"""Accepted difference between a command's issue time and the runtime's clock, s (both sides of
'now'). The server signs in the runtime's time (its clock plus the offset it measured from the
runtime's RuntimeInfo.clock_unix_s), so drift between the hosts does not count against it; 5 s
covers transit, queueing and the measurement's age with margin."""
MAX_NONCES = 4096
"""Replay cache bound. Nonces are kept only while their message could still be fresh
(issued + window), so the cache holds at most the commands of one 2*window span; beyond this
many the verifier refuses ("replay cache full") rather than forget a nonce too early."""

M = TypeVar("M", bound=Message)


def new_key() -> bytes:
    """A fresh random 32-byte command key (:func:`secrets.token_bytes`)."""
    return secrets.token_bytes(KEY_BYTES)


def write_key(path: str | Path, key: bytes) -> Path:
    """Write ``key`` as hex to ``path`` with mode 0600 (parent directories created).

    Raises:
        ValueError: if ``key`` is not 32 bytes.
    """
    if len(key) != KEY_BYTES:
        raise ValueError(f"command key must be {KEY_BYTES} bytes, got {len(key)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key.hex() + "\n")
    os.chmod(path, 0o600)
    return path


def load_key(path: str | Path) -> bytes:
    """Read a command key file (64 hex digits, surrounding white space ignored).

    Logs a warning when the file is readable by group or others.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the content is not 64 hex digits.
    """
    path = Path(path)
    text = path.read_text().strip()
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_BYTES:
        raise ValueError(f"{path}: a command key file must hold {2 * KEY_BYTES} hex digits")
    if path.stat().st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        log.warning("command key %s is readable by group/others (chmod 600 it)", path)
    return key


def canonical_bytes(msg: Message) -> bytes:
    """The bytes the MAC covers: the message as canonical JSON with ``auth.mac`` = ""."""
    data = msg.model_dump(mode="json")
    if isinstance(data.get("auth"), dict):
        data["auth"]["mac"] = ""
    return json.dumps(data, sort_keys=True, separators=(",", ":")).encode()


def _mac(msg: Message, key: bytes) -> str:
    return hmac.new(key, canonical_bytes(msg), hashlib.sha256).hexdigest()


def sign(msg: M, key: bytes, user: str, epoch: int, now_unix_s: float | None = None, server: str | None = None) -> M:
    """A copy of ``msg`` with a fresh ``auth`` (user, wall clock, nonce, epoch, server, MAC).

    Args:
        msg: a message with an ``auth`` field (ThrowRequest, AbortRequest, EstopReset,
            PolicyOffer, ThrowResult).
        key: the machine's 32-byte command key.
        user: who asks (1-64 chars); "runtime:<id>" for results.
        epoch: the runtime claim addressed (RuntimeInfo.epoch).
        now_unix_s: signing time, Unix s (default: time.time()).
        server: the signing server's identity (CommandAuth.server), None for results.

    Raises:
        ValueError: the message has no ``auth`` field, or a bad key / user / epoch.
    """
    if "auth" not in type(msg).model_fields:
        raise ValueError(f"{type(msg).__name__} carries no auth field")
    if len(key) != KEY_BYTES:
        raise ValueError(f"command key must be {KEY_BYTES} bytes, got {len(key)}")
    auth = CommandAuth(
        user=user,
        issued_unix_s=time.time() if now_unix_s is None else now_unix_s,
        nonce=secrets.token_hex(16),
        epoch=epoch,
        server=server,
    )
    signed = msg.model_copy(update={"auth": auth})
    return signed.model_copy(update={"auth": auth.model_copy(update={"mac": _mac(signed, key)})})


def verify_mac(msg: Message, key: bytes) -> str | None:
    """None if ``msg`` carries a valid MAC under ``key``, else "unsigned" or "bad signature"."""
    auth = getattr(msg, "auth", None)
    if auth is None or not auth.mac:
        return "unsigned"
    if not hmac.compare_digest(auth.mac, _mac(msg, key)):
        return "bad signature"
    return None


class CommandVerifier:
    """The runtime's check of signed commands: MAC, epoch, freshness and nonce replay.

    Thread-safe (Zenoh callbacks run on several threads).

    Args:
        key: the machine's 32-byte command key.
        epoch: this runtime's claim epoch; commands addressed to another one are refused.
        window_s: accepted |now - issued_unix_s|, s (DEFAULT_WINDOW_S).
        max_nonces: replay cache bound (MAX_NONCES).
        wall_clock: this host's wall clock, Unix s (default time.time; tests inject an offset
            through runtime.node's SLINGER_CLOCK_OFFSET_S).

    Raises:
        ValueError: bad key length or a non-positive window.
    """

    def __init__(self, key: bytes, epoch: int, window_s: float = DEFAULT_WINDOW_S, max_nonces: int = MAX_NONCES,
                 wall_clock: Callable[[], float] = time.time):
        if len(key) != KEY_BYTES:
            raise ValueError(f"command key must be {KEY_BYTES} bytes, got {len(key)}")
        if not window_s > 0:
            raise ValueError(f"window_s must be > 0, got {window_s}")
        self.key = key
        self.epoch = int(epoch)
        self.window_s = float(window_s)
        self.max_nonces = int(max_nonces)
        self.wall_clock = wall_clock
        self._seen: OrderedDict[str, float] = OrderedDict()  # nonce -> forget after (unix s)
        self._lock = threading.Lock()

    def check(self, msg: Message, now_unix_s: float | None = None) -> str | None:
        """None if ``msg`` may be executed (and its nonce is now spent), else the reason:
        "unsigned", "bad signature", "wrong epoch: addressed 5, this runtime is 7",
        "stale (issued 12.3 s ago)", "issued 7.0 s in the future", "replayed nonce",
        "replay cache full"."""
        reason = verify_mac(msg, self.key)
        if reason:
            return reason
        auth = getattr(msg, "auth", None)
        assert auth is not None, "verify_mac found it"
        if auth.epoch != self.epoch:
            return f"wrong epoch: addressed {auth.epoch}, this runtime is {self.epoch}"
        now = self.wall_clock() if now_unix_s is None else now_unix_s
        age_s = now - auth.issued_unix_s
        if age_s > self.window_s:
            return f"stale (issued {age_s:.1f} s ago)"
        if age_s < -self.window_s:
            return f"issued {-age_s:.1f} s in the future"
        with self._lock:
            while self._seen and next(iter(self._seen.values())) < now:
                self._seen.popitem(last=False)
            if auth.nonce in self._seen:
                return "replayed nonce"
            if len(self._seen) >= self.max_nonces:
                return "replay cache full"
            # Keep until the message can no longer be fresh; insertion order ~ expiry order.
            self._seen[auth.nonce] = max(auth.issued_unix_s + self.window_s, now)
        return None
