"""Commands and queries the server sends to the fleet's runtimes (split out of :mod:`server.fleet.link`).

:class:`FleetCommands` is the query half of :class:`server.fleet.link.Fleet`: it asks runtimes for
their RuntimeInfo (cached per machine), signs commands (ThrowRequest, EstopReset, ReturnToReady,
PolicyOffer) with the machine's command key for the runtime's claim epoch and decodes their acks,
and hands E-STOPs (signed when it can be, else unsigned) to the per-machine fire-and-forget path
of :mod:`server.fleet.estop`.
:class:`RuntimeUnavailable` is what every query raises when no valid reply comes back. Both are
re-exported by :mod:`server.fleet.link`; callers import them from there.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from runtime.protocol import keys
from runtime.protocol.messages import (
    AbortRequest,
    EstopReset,
    EstopResetAck,
    LeaseAck,
    LeaseRequest,
    PolicyOffer,
    PolicyOfferAck,
    ReturnToReady,
    ReturnToReadyAck,
    RuntimeInfo,
    ThrowAck,
    ThrowRequest,
    decode,
    encode,
)
from server.errors import Conflict, Unavailable

if TYPE_CHECKING:
    import zenoh

    from server.fleet.command_signer import CommandSigner
    from server.fleet.estop import EstopLine, Latch

log = logging.getLogger("server.fleet.link")  # the logger of server.fleet.link, as before the split


RETRY_REASONS = ("wrong epoch", "stale (", "in the future")
"""A signed command refused for one of these is signed again once with the runtime's epoch and
clock asked afresh (it restarted, or its clock moved)."""


class RuntimeUnavailable(Unavailable, RuntimeError):
    """The runtime did not answer (offline, or no reply within the timeout)."""


class FleetCommands:
    """Queries and signed commands to runtimes; a base of :class:`server.fleet.link.Fleet`, which
    provides what these methods use: ``session`` (open Zenoh session), ``signer``
    (:class:`server.fleet.command_signer.CommandSigner`), ``query_timeout_s`` (s), ``_lock``,
    ``_infos`` (machine id -> (monotonic s, RuntimeInfo)), ``_estop`` (the
    :class:`server.fleet.estop.EstopLine`),
    :meth:`~server.fleet.link.Fleet.is_online`, :meth:`~server.fleet.link.Fleet.cached_info`,
    :meth:`~server.fleet.link.Fleet.forget_info`, :meth:`~server.fleet.link.Fleet.clock_offset_s` and
    :meth:`~server.fleet.link.Fleet._note_info`.
    """

    # what server.fleet.link.Fleet provides, declared for the type checker
    session: zenoh.Session
    signer: CommandSigner
    query_timeout_s: float
    _estop: EstopLine

    if TYPE_CHECKING:
        def is_online(self, machine_id: str) -> bool: ...
        def cached_info(self, machine_id: str) -> RuntimeInfo | None: ...
        def forget_info(self, machine_id: str) -> None: ...
        def clock_offset_s(self, machine_id: str) -> float | None: ...
        def _note_info(self, info: RuntimeInfo, published: bool) -> None: ...

    # --- queries -------------------------------------------------------------------------------
    def query_info(self, machine_id: str, timeout_s: float | None = None) -> RuntimeInfo:
        """Ask the runtime for its RuntimeInfo (and cache it).

        Raises:
            RuntimeUnavailable: no valid reply within the timeout.
        """
        info = decode(RuntimeInfo, self._query_one(keys.info(machine_id), None, timeout_s))
        self._note_info(info, published=False)
        return info

    def epoch_of(self, machine_id: str, fresh: bool = False) -> int:
        """The claim epoch of the machine's runtime (RuntimeInfo.epoch): cached, or asked when
        ``fresh`` or unknown.

        Raises:
            RuntimeUnavailable: the runtime is offline or does not answer.
        """
        info = None if fresh else self.cached_info(machine_id)
        if info is None:
            if not self.is_online(machine_id):
                raise RuntimeUnavailable(f"the runtime of {machine_id} is offline")
            info = self.query_info(machine_id)
        return info.epoch

    def _signed_query(self, key_of, msg, machine_id: str, user: str, ack_type, timeout_s: float | None = None):
        """Sign ``msg`` for the runtime's current epoch, query ``key_of(machine_id)``, decode the
        ack; once more with a fresh epoch when the runtime says the epoch is wrong (it restarted).

        Raises:
            RuntimeUnavailable: offline, no reply, an error reply or a malformed ack.
            ValueError: a malformed command key file.
        """
        for attempt in (0, 1):
            epoch = self.epoch_of(machine_id, fresh=attempt > 0)
            signed = self.signer.sign(msg, machine_id, user, epoch, now_unix_s=self.runtime_now(machine_id))
            payload = self._query_one(key_of(machine_id), encode(signed), timeout_s)
            try:
                ack = decode(ack_type, payload)
            except ValidationError as e:
                raise RuntimeUnavailable(f"malformed {ack_type.__name__} from {machine_id}: {e}") from e
            reason = getattr(ack, "reason", None) or ""
            if attempt == 0 and any(why in reason for why in RETRY_REASONS):
                log.info("%s: %s; asking its epoch and clock again", machine_id, reason)
                self.forget_info(machine_id)
                continue
            return ack, epoch
        return ack, epoch

    def request_throw(self, request: ThrowRequest, user: str = "system") -> tuple[ThrowAck, int]:
        """Sign a ThrowRequest for ``user``, send it and wait for the runtime's ThrowAck.

        Returns:
            (ack, epoch of the runtime it was addressed to).

        Raises:
            RuntimeUnavailable: offline, no reply within the timeout, an error reply or a malformed ack.
            ValueError: a malformed command key file.
            Conflict: the server holds the machine's E-STOP latched (condition ``estop_latched``).
        """
        self.refuse_if_latched(request.machine_id)
        return self._signed_query(keys.throw, request, request.machine_id, user, ThrowAck)

    def estop_latch(self, machine_id: str) -> Latch | None:
        """The E-STOP the server holds latched for ``machine_id`` (server.fleet.estop.Latch), or None."""
        return self._estop.latch(machine_id)

    def estop_latched_ids(self) -> set[str]:
        """The machines whose E-STOP the server holds latched."""
        return self._estop.latched_ids()

    def release_unknown_estop(self, machine_id: str) -> None:
        """Drop the server's latch of an id that names no machine (an E-STOP of an unknown id)."""
        self._estop.release_unknown(machine_id)

    def refuse_if_latched(self, machine_id: str) -> None:
        """Raise Conflict (``estop_latched``) while the server holds ``machine_id``'s E-STOP."""
        latch = self._estop.latch(machine_id)
        if latch is not None:
            raise Conflict(f"E-STOP latched on {machine_id} ({latch.reason}): reset it before throwing or moving",
                           "estop_latched")

    def estop_reset(self, machine_id: str, user: str) -> EstopResetAck:
        """Ask the runtime to release its latched E-STOP (signed for ``user``).

        The server's own latch of the machine (:meth:`estop_latch`) pauses its puts while the reset
        is asked and is cleared only when the runtime confirms the reset.

        Raises:
            RuntimeUnavailable, ValueError: as :meth:`request_throw`.
        """
        self._estop.begin_reset(machine_id)
        released = False
        try:
            ack = self._state_command(keys.estop_reset, EstopReset(machine_id=machine_id), user, EstopResetAck)
            released = ack.reset
            return ack
        finally:
            self._estop.end_reset(machine_id, released)

    def return_to_ready(self, machine_id: str, user: str) -> ReturnToReadyAck:
        """Ask the runtime to drive its arm back to the ready pose (signed for ``user``).

        Raises:
            RuntimeUnavailable, ValueError, Conflict: as :meth:`request_throw`.
        """
        self.refuse_if_latched(machine_id)
        return self._state_command(keys.return_to_ready, ReturnToReady(machine_id=machine_id), user, ReturnToReadyAck)

    def _state_command(self, key_of, command, user: str, ack_type):
        """Send a signed command that changes the runtime's state (``key_of(machine_id)`` the
        query key, ``command`` its message with ``machine_id``) and drop the cached RuntimeInfo,
        so the next read asks the runtime. Returns the decoded ``ack_type``.

        Raises:
            RuntimeUnavailable, ValueError: as :meth:`request_throw`.
        """
        ack, _ = self._signed_query(key_of, command, command.machine_id, user, ack_type)
        self.forget_info(command.machine_id)
        return ack

    def lease(self, machine_id: str, user: str, takeover: bool = False) -> LeaseAck:
        """Ask the runtime for its lease (one writer per machine: runtime.service), renewing it
        when this server holds it; ``takeover`` takes it from another server at once (a
        deliberate takeover, signed for ``user``; the runtime refuses it while a throw runs).

        Raises:
            RuntimeUnavailable, ValueError: as :meth:`request_throw`.
        """
        return self._state_command(keys.lease, LeaseRequest(machine_id=machine_id, takeover=takeover), user, LeaseAck)

    def offer_policy(self, offer: PolicyOffer, user: str) -> PolicyOfferAck:
        """Offer a policy version to the runtime (signed for ``user``); returns its ack.

        Raises:
            RuntimeUnavailable, ValueError: as :meth:`request_throw`.
        """
        ack, _ = self._signed_query(keys.policy_offer, offer, offer.machine_id, user, PolicyOfferAck)
        return ack

    def estop(self, machine_id: str, reason: str = "operator abort", user: str = "system") -> Future:
        """E-STOP ``machine_id``: the AbortRequest is put at once (per machine, fire-and-forget,
        repeated until confirmed; presses while one is unconfirmed join it) and the returned
        Future gets the runtime's AbortAck, or fails with :class:`server.fleet.estop.EstopUnconfirmed`
        (a RuntimeUnavailable) after the press's deadline. Never waits for another machine, a
        query or a thread pool.

        Raises:
            ValueError: a malformed machine id.
        """
        return self._estop.press(machine_id, reason, user)

    def _sign_abort(self, request: AbortRequest, machine_id: str, user: str) -> AbortRequest:
        """``request`` signed for the runtime's cached epoch (no query before a stop), or
        unchanged when the epoch is unknown or the site has no key (stops are honoured unsigned).

        Raises:
            ValueError: a malformed command key file.
        """
        info = self.cached_info(machine_id)
        if info is None:
            return request
        return self.signer.sign(request, machine_id, user, info.epoch, now_unix_s=self.runtime_now(machine_id))

    def runtime_now(self, machine_id: str) -> float:
        """The runtime's wall clock now as the server estimates it, Unix s: time.time() plus
        the clock offset measured from its RuntimeInfo (:meth:`clock_offset_s`; 0 if unknown)."""
        return time.time() + (self.clock_offset_s(machine_id) or 0.0)

    def _query_one(self, key: str, payload: bytes | None, timeout_s: float | None = None) -> bytes:
        timeout_s = timeout_s or self.query_timeout_s
        kwargs: dict[str, Any] = {"timeout": timeout_s}
        if payload is not None:
            kwargs["payload"] = payload
        errors = []
        for reply in self.session.get(key, **kwargs):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            errors.append(reply.err.payload.to_string() if reply.err is not None else "?")
        if errors:
            raise RuntimeUnavailable(f"{key}: error reply: {'; '.join(errors)}")
        raise RuntimeUnavailable(f"no reply on {key} within {timeout_s:.1f} s")
