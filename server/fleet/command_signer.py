"""The server's command keys: signs what it sends to runtimes, checks what runtimes send back.

One 32-byte key per machine, hex in ``<site_dir>/machines/<machine_id>/command.key`` (made by
``slinger certs``; ``slinger up`` makes them for its machines). The server reads every machine's
key; a key file that appears later (a machine added to the site) is picked up on first use.

A machine without a key file gets unsigned commands (its runtime, which holds no key either,
cannot check them; a runtime with a key refuses them as "unsigned") and its results are accepted
without a MAC, still only for throws the server issued. Each case is logged once per machine.
Signing and checking follow the wire contract in runtime.command_auth (HMAC-SHA256 over the
canonical JSON, user, wall-clock time, nonce, runtime epoch, server).

Every command names this server (``CommandAuth.server``, :func:`default_server_id`): a runtime
obeys one server at a time (its lease, runtime.service) and tags each throw's result with the
server that issued it. Two servers of one site (the same certificates and keys) are told apart
by it, so each runs with its own: the environment's ``SLINGER_SERVER_ID``, else the host name
and the site directory's path.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import socket
import threading
from pathlib import Path
from typing import TypeVar

from runtime.command_auth import load_key, sign, verify_mac
from runtime.protocol.keys import validate_machine_id
from runtime.protocol.messages import Message, ThrowResult
from server.errors import Unavailable

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)


SERVER_ID_ENV = "SLINGER_SERVER_ID"


def default_server_id(site_dir: Path | None) -> str:
    """This server's identity in the commands it signs: ``SLINGER_SERVER_ID`` if set, else
    ``<host name>-<8 hex digits of the SHA-256 of the site directory's absolute path>``
    ([A-Za-z0-9_.:@-], at most 64 characters).

    Raises:
        ValueError: SLINGER_SERVER_ID is set but not 1-64 of those characters.
    """
    given = os.environ.get(SERVER_ID_ENV)
    if given is not None:
        if not re.fullmatch(r"[A-Za-z0-9_.:@-]{1,64}", given):
            raise ValueError(f"{SERVER_ID_ENV} must be 1-64 of A-Z a-z 0-9 _ . : @ -, got {given!r}")
        return given
    where = str(Path(site_dir).resolve()) if site_dir is not None else ""
    host = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname())[:55] or "server"
    return f"{host}-{hashlib.sha256(where.encode()).hexdigest()[:8]}"


class NoCommandKey(Unavailable, RuntimeError):
    """The server has no command key for a machine, so it cannot command it."""


class CommandSigner:
    """Command keys of a site.

    Args:
        site_dir: the site directory (None: no keys; every signature attempt raises NoCommandKey).
        server_id: this server's identity in its commands (default: :func:`default_server_id`).

    Raises:
        ValueError: a malformed SLINGER_SERVER_ID.
    """

    def __init__(self, site_dir: Path | None, server_id: str | None = None):
        self.site_dir = Path(site_dir) if site_dir is not None else None
        self.server_id = server_id or default_server_id(self.site_dir)
        self._keys: dict[str, bytes] = {}
        self._warned: set[str] = set()
        self._lock = threading.Lock()

    def key_path(self, machine_id: str) -> Path | None:
        if self.site_dir is None:
            return None
        return self.site_dir / "machines" / validate_machine_id(machine_id) / "command.key"

    def key(self, machine_id: str) -> bytes | None:
        """The machine's command key, or None when the site has none for it.

        Raises:
            ValueError: a malformed machine id or key file.
        """
        with self._lock:
            key = self._keys.get(machine_id)
        if key is not None:
            return key
        path = self.key_path(machine_id)
        if path is None or not path.is_file():
            return None
        key = load_key(path)
        with self._lock:
            self._keys[machine_id] = key
        log.info("command key of %s loaded from %s", machine_id, path)
        return key

    def sign(self, msg: M, machine_id: str, user: str, epoch: int, required: bool = False,
             now_unix_s: float | None = None) -> M:
        """``msg`` signed for ``machine_id``'s runtime of claim ``epoch`` on behalf of ``user``;
        ``msg`` unchanged when the site has no key for the machine (logged once). ``now_unix_s``:
        the issue time to sign (the runtime's clock as the fleet measured it; default time.time()).

        Raises:
            NoCommandKey: no key for the machine and ``required``.
            ValueError: a malformed key file.
        """
        key = self.key(machine_id)
        if key is None:
            where = self.key_path(machine_id) or "(no site directory configured)"
            problem = f"the server has no command key for {machine_id} at {where} (slinger certs makes one)"
            if required:
                raise NoCommandKey(problem)
            self._warn_once(machine_id, f"{problem}: its commands go unsigned and its results unchecked")
            return msg
        return sign(msg, key, user[:64], epoch, now_unix_s, server=self.server_id)

    def _warn_once(self, machine_id: str, text: str) -> None:
        with self._lock:
            if machine_id in self._warned:
                return
            self._warned.add(machine_id)
        log.warning("%s", text)

    def check_result(self, result: ThrowResult) -> str | None:
        """None if the result carries a valid MAC of its machine's key (or the site has no key
        for the machine), else the reason ("unsigned", "bad signature", a bad key file)."""
        try:
            key = self.key(result.machine_id)
        except ValueError as e:
            return str(e)
        if key is None:
            self._warn_once(result.machine_id, f"no command key for {result.machine_id}: its results go unchecked")
            return None
        return verify_mac(result, key)
