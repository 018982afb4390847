"""GET /api/machines: the machines the server knows or hears, with presence, policies and the
runtime's state (E-STOP latch, readiness, running throw). E-STOP: POST .../estop (alias .../abort)
on the fast path; POST .../estop/reset releases the latch, POST .../return-to-ready starts the
runtime's recovery action and POST .../lease/takeover takes the machine's lease from another
server (operator, audited; like the E-STOP these need no storage: the session is checked in
memory and the audit entry waits in memory while storage fails). POST .../drift/ack acknowledges
the machine's drift alert (server.analysis.drift; operator, audited)."""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections.abc import Callable
from datetime import datetime
from functools import partial
from typing import Any

from fastapi import APIRouter, Request
from pydantic import BaseModel, Field
from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError

from runtime.protocol.messages import ABORT_REASON_CHARS
from server.accounts.auth import AuditBacklog, SessionUser, clean_text, record_audit
from server.api.deps import (
    AuditBacklogDep,
    DriftDep,
    FleetDep,
    SessionsDep,
    ViewerDep,
    authorised_or_audited,
    stopper_from_memory,
    user_from_memory,
)
from server.api.report_schemas import DriftAlertOut
from server.api.responses import errors
from server.api.schemas import MachineOut
from server.db.models import Machine, Throw, User
from server.errors import Conflict, NotFound, Unavailable
from server.fleet.link import RUNTIME_SILENT_S, Fleet, RuntimeUnavailable, clock_warning
from server.site.storage import StorageFault

router = APIRouter(prefix="/api/machines", tags=["machines"])
log = logging.getLogger(__name__)

INFO_TIMEOUT_S = 1.0
INFO_MAX_AGE_S = 2.0  # busy flag and policies are at most this old
"""A runtime whose wall clock is further off the server's gets a clock warning in its row."""


STORAGE_ERRORS = (StorageFault, SQLAlchemyError, OSError)
"""What a database read raises during a storage fault (server.site.storage)."""


@router.get("", response_model=list[MachineOut], responses=errors(
    401, (503, "the session is not in memory and storage does not answer")))
def list_machines(request: Request, sessions: SessionsDep, fleet: FleetDep) -> list[MachineOut]:
    """All machines in the database plus any heard on Zenoh or latched on the server, sorted by id.

    ``simulated`` is True when the machine's own state says it is the simulated machine. The
    session is checked in memory (server.accounts.auth.SessionMirror) and the machines' state comes from
    the fleet link, so during a storage fault this still answers: from memory alone, without the
    stored machines that are not heard now and without the latest throw and accuracy.
    """
    user_from_memory(request, "viewer")
    states = fleet.latest_states()
    heard = fleet.online_ids() | set(states) | fleet.estop_latched_ids()
    try:
        with sessions() as db:
            rows = {m.id: m for m in db.scalars(select(Machine))}
            return [_with_throws(db, _machine_out(mid, rows.get(mid), fleet)) for mid in sorted(set(rows) | heard)]
    except STORAGE_ERRORS as e:
        log.warning("machine list answered from memory: %s", _sentence(e))
        return [_machine_out(mid, None, fleet) for mid in sorted(heard)]


RECENT_THROWS = 20


def _with_throws(db, m: MachineOut) -> MachineOut:
    """Add the latest throw and the accuracy over the last RECENT_THROWS landed throws."""
    import math

    last = db.scalar(select(Throw).where(Throw.machine_id == m.id).order_by(Throw.requested_at.desc()).limit(1))
    if last is not None:
        m.last_throw_at, m.last_throw_status, m.current_mode = last.requested_at, last.status, last.mode
    landed = list(db.execute(select(Throw.downrange_error_m, Throw.crossrange_error_m).where(
        Throw.machine_id == m.id, Throw.status == "landed", Throw.downrange_error_m.is_not(None)
    ).order_by(Throw.requested_at.desc()).limit(RECENT_THROWS)))
    if landed:
        m.recent_throws = len(landed)
        m.recent_mean_abs_error_m = sum(math.hypot(d, c) for d, c in landed) / len(landed)
    return m


def _machine_out(mid: str, row: Machine | None, fleet: Fleet) -> MachineOut:
    """The machine's row of the list; a server-held E-STOP (server.fleet.estop) shows it latched and
    not ready whatever its runtime says."""
    out = _runtime_out(mid, row, fleet)
    latch = fleet.estop_latch(mid)
    if latch is not None:
        out.estop_latched, out.estop_reason = True, latch.reason
        out.ready, out.not_ready_reason = False, latch.describe()
    return out


def _runtime_out(mid: str, row: Machine | None, fleet: Fleet) -> MachineOut:
    online = fleet.is_online(mid)
    silent_s = fleet.silent_for_s(mid)
    state = fleet.latest_state(mid)
    offset_s = fleet.clock_offset_s(mid)
    clock = {"clock_offset_s": round(offset_s, 3) if offset_s is not None else None, "clock_warning": clock_warning(offset_s)}
    if silent_s > RUNTIME_SILENT_S:  # frozen or cut off: its last state is no longer true
        return MachineOut(id=mid, online=False, simulated=bool((state and state.simulated) or (row and row.simulated)),
                          cabin_turn_rad=state.q[0] if state is not None else None, ready=False,
                          not_ready_reason=f"runtime not answering for {silent_s:.0f} s", **clock)
    info = fleet.fresh_info(mid, max_age_s=INFO_MAX_AGE_S, timeout_s=INFO_TIMEOUT_S)
    simulated = bool(
        (state is not None and state.simulated)
        or (info is not None and info.simulated)
        or (row is not None and row.simulated)
    )
    return MachineOut(
        id=mid, online=online, simulated=simulated, **clock,
        policies={p.mode: p.version for p in info.policies} if info else {},
        busy=info.busy if info else None,
        cabin_turn_rad=state.q[0] if state is not None else None,
        estop_latched=info.estop_latched if info else None, estop_reason=info.estop_reason if info else None,
        ready=info.ready if info else (False if not online else None),
        not_ready_reason=(info.not_ready_reason if info else ("runtime offline" if not online else None)),
        phase=info.phase if info else None, throw_id=info.throw_id if info else None,
        lease_holder=info.lease_holder if info else None,
        lease_held_here=(info.lease_holder == fleet.signer.server_id) if info and info.lease_holder is not None else None,
        undeliverable_results=info.undeliverable_results if info else None,
    )


class AbortIn(BaseModel):
    """The E-STOP's body, optional. Documented for the API; the route reads it itself
    (:func:`stop_reason`) so that no body refuses a stop."""

    reason: str = Field(default="operator abort", max_length=ABORT_REASON_CHARS)


def stop_reason(raw: bytes, limit: int = ABORT_REASON_CHARS) -> str:
    """The reason of an E-STOP's request body ``raw`` (JSON ``{"reason": "..."}``, optional). A
    stop is never refused for its body: a reason longer than ``limit`` characters is cut, and a body
    that is not such JSON (malformed, another type, a reason that is not text) gives the default
    reason marked "(request body not read: ...)". Control characters are escaped
    (server.accounts.auth.clean_text)."""
    default = AbortIn.model_fields["reason"].default
    try:
        data = json.loads(raw) if raw.strip() else {}
    except (ValueError, UnicodeDecodeError):
        return f"{default} (request body not read: not JSON)"
    reason = data.get("reason", default) if isinstance(data, dict) else None
    if not isinstance(reason, str):
        return f"{default} (request body not read: no text reason)"
    return clean_text(reason.strip() or default, limit)


class AbortOut(BaseModel):
    machine_id: str
    aborted_throw_id: str | None
    login_expired_at: datetime | None = None
    """When the pressing console's log-in expired (UTC), if it has: the stop was still taken
    (server.accounts.auth.STOP_GRACE_S); nothing else is until the operator logs in again."""


class EstopResetOut(BaseModel):
    machine_id: str
    reset: bool
    reason: str | None = None


STOP_RESPONSES = errors((401, "no session: none sent, logged out, account disabled or deleted, or its log-in expired more "
                              "than 24 h ago (server.accounts.auth.STOP_GRACE_S)"), (403, "needs the operator role"), (404, "unknown machine"),
                        (503, "the runtime did not confirm the stop (the server holds it latched and keeps sending "
                              "it), or the session is unknown in memory and storage does not answer"))
"""The E-STOP checks its session itself (server.api.deps.stopper_from_memory): it lists 401/403."""


STOP_BODY = {"requestBody": {"required": False, "content": {"application/json": {"schema": AbortIn.model_json_schema()}}}}
"""The E-STOP's body as documented (AbortIn); the route reads it with :func:`stop_reason`."""


@router.post("/{machine_id}/estop", response_model=AbortOut, responses=STOP_RESPONSES, openapi_extra=STOP_BODY)
@router.post("/{machine_id}/abort", response_model=AbortOut, responses=STOP_RESPONSES, openapi_extra=STOP_BODY)
async def estop(machine_id: str, request: Request, fleet: FleetDep, sessions: SessionsDep, backlog: AuditBacklogDep) -> AbortOut:
    """E-STOP: the runtime ends any throw as aborted, puts the valves to neutral and LATCHES
    (throws refused until POST .../estop/reset; the latch survives a runtime restart). Fast path:
    an async route that puts the stop for this machine at once (server.fleet.estop: fire-and-forget,
    repeated until the runtime confirms; presses of a machine whose stop is unconfirmed join it)
    and replies on the runtime's confirmation (AbortAck, sent after the latch is on disk), or 503
    after the stop's deadline; the server then holds the stop latched (server.fleet.estop: the machine
    shows E-STOPPED, throws are refused, the stop is sent until a runtime confirms it, until a
    deliberate reset). The operator's session is checked in memory (server.accounts.auth.SessionMirror) and
    no other machine, query, thread pool or storage is waited for: the audit entry is written
    afterwards on the fleet's database thread, also when the runtime does not confirm, and queued
    in memory while storage fails (server.accounts.auth.AuditBacklog). A session whose log-in expired
    less than server.accounts.auth.STOP_GRACE_S ago still stops (``login_expired_at`` in the answer and
    the audit entry). No body refuses a stop (:func:`stop_reason`: a long reason is cut, an unreadable
    body gives the default reason)."""
    t0 = time.perf_counter()
    user, expired_at = await stopper_from_memory(request)
    late = {"login_expired_at": expired_at.isoformat()} if expired_at is not None else {}
    who = f" ({user.username}{', log-in expired' if late else ''})"  # kept whole: the body's reason is cut first
    reason = stop_reason(await request.body(), ABORT_REASON_CHARS - len(who)) + who
    try:
        t_auth = time.perf_counter()
        ack = await asyncio.wrap_future(fleet.estop(machine_id, reason, user.username))
        log.info("E-STOP %s: authenticated in %.1f ms, runtime confirmed after %.1f ms more", machine_id,
                 (t_auth - t0) * 1e3, (time.perf_counter() - t_auth) * 1e3)
    except (RuntimeUnavailable, ValueError) as e:
        refused = _not_confirmed(partial(_audit_later, fleet, backlog), user.username, "abort", machine_id, "abort", e,
                                 reason=reason, **late)
        await asyncio.to_thread(_404_if_unknown, fleet, sessions, machine_id)
        raise refused from e
    fleet.forget_info(machine_id)
    _audit_later(fleet, backlog, user.username, "abort", machine_id, reason=reason, delivered=True,
                 throw_id=ack.aborted_throw_id, **late)
    return AbortOut(machine_id=machine_id, aborted_throw_id=ack.aborted_throw_id, login_expired_at=expired_at)


def _audit_later(fleet: Fleet, backlog: AuditBacklog, username: str, action: str, subject: str, **detail) -> None:
    """Audit an E-STOP (``action`` ``abort``) on the fleet's database thread, after the stop went
    out; while storage fails the entry waits in ``backlog``. The E-STOP reply never waits for it."""
    def logged(done) -> None:
        if done.exception() is not None:
            log.error("E-STOP audit entry not written: %s", done.exception())

    fleet.submit_db_job(lambda: backlog.record(username, action, subject, **detail)).add_done_callback(logged)


def _not_confirmed(record, username: str, action: str, machine_id: str, what: str, e: Exception,
                   **detail) -> Unavailable:
    """A command the runtime did not confirm (``e``: offline, no answer, no command key): the
    attempt is audited as undelivered through ``record(username, action, subject, **detail)``
    (AuditBacklog.record, or :func:`_audit_later` on the E-STOP's fast path) and the returned
    Unavailable (503) names ``what`` and the cause. The caller checks :func:`_404_if_unknown`
    and raises it."""
    error = _sentence(e)
    record(username, action, machine_id[:64], **detail, delivered=False, error=error)
    return Unavailable(f"{what} of {machine_id} not confirmed: {error}")


def _operator_command(request: Request, fleet: Fleet, sessions, backlog: AuditBacklog, action: str, machine_id: str,
                      what: str, send: Callable[[str], Any]) -> tuple[User | SessionUser, Any]:
    """A deliberate operator command that, like the E-STOP, needs no storage while storage fails
    (an E-STOP reset, a return to the ready pose, a lease takeover: docs/safety.md, row S10): the
    session is checked in memory (server.api.deps.user_from_memory), ``send(username)`` sends the
    signed command and returns the runtime's ack, and the audit entries go through ``backlog``
    (written at once, or kept in memory in order until storage is back). An undelivered command is
    audited as such (:func:`_not_confirmed`). The caller audits the delivered one with the ack's
    outcome (``backlog.record``).

    Returns:
        (the operator, the runtime's ack).

    Raises:
        Unauthenticated (401), Denied (403): no session, or a role below operator.
        NotFound (404): the runtime did not answer and the machine was never registered.
        Unavailable (503): the runtime did not answer (offline, no reply, no command key), or the
            session is not in memory and storage does not answer.
    """
    user = user_from_memory(request, "operator")
    try:
        return user, send(user.username)
    except (RuntimeUnavailable, ValueError) as e:
        refused = _not_confirmed(backlog.record, user.username, action, machine_id, what, e)
        _404_if_unknown(fleet, sessions, machine_id)
        raise refused from e


def _sentence(e: Exception) -> str:
    """The first line of an error's text (a pydantic ValidationError's first line names the
    model; its field dump is left out)."""
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def _404_if_unknown(fleet: Fleet, sessions, machine_id: str) -> None:
    """NotFound (404) if no machine ``machine_id`` was ever registered nor is online (checked
    only after a command failed, so the E-STOP path never waits for the database); the server's
    latch of such an id is dropped. While storage fails the id counts as known (the latch holds)."""
    if fleet.is_online(machine_id) or fleet.latest_state(machine_id) is not None:
        return
    try:
        with sessions() as db:
            known = db.get(Machine, machine_id) is not None
    except STORAGE_ERRORS as e:
        log.warning("E-STOP of %s: cannot check that the machine exists (%s); its latch holds", machine_id, _sentence(e))
        return
    if not known:
        fleet.release_unknown_estop(machine_id)
        raise NotFound(f"unknown machine {machine_id!r}")


COMMAND_RESPONSES = ((404, "unknown machine"), (503, "the runtime did not answer, or no command key, or the session is "
                                                    "not in memory and storage does not answer"))


@router.post("/{machine_id}/estop/reset", response_model=EstopResetOut,
             responses=errors(401, (403, "needs the operator role"), (409, "the runtime refused the reset (its reason)"),
                              *COMMAND_RESPONSES))
def estop_reset(machine_id: str, request: Request, sessions: SessionsDep, fleet: FleetDep,
                backlog: AuditBacklogDep) -> EstopResetOut:
    """Release the runtime's latched E-STOP (a signed EstopReset in the operator's name); audited.
    Works during a storage fault as the E-STOP does (:func:`_operator_command`)."""
    user, ack = _operator_command(request, fleet, sessions, backlog, "estop_reset", machine_id, "E-STOP reset",
                                  lambda username: fleet.estop_reset(machine_id, username))
    backlog.record(user.username, "estop_reset", machine_id, delivered=True, reset=ack.reset, reason=ack.reason)
    if not ack.reset:
        clock = clock_warning(fleet.clock_offset_s(machine_id))
        raise Conflict(f"the runtime of {machine_id} kept E-STOP latched: {ack.reason}" + (f"; {clock}" if clock else ""))
    return EstopResetOut(machine_id=machine_id, reset=True, reason=ack.reason)


class ReturnToReadyOut(BaseModel):
    machine_id: str
    accepted: bool
    reason: str | None = None


@router.post("/{machine_id}/return-to-ready", response_model=ReturnToReadyOut,
             responses=errors(401, (403, "needs the operator role"),
                              (409, "the runtime refused (its reason: E-STOP latched, a throw runs, ...)"),
                              *COMMAND_RESPONSES))
def return_to_ready(machine_id: str, request: Request, sessions: SessionsDep, fleet: FleetDep,
                    backlog: AuditBacklogDep) -> ReturnToReadyOut:
    """Recovery action: the runtime drives the arm back to its ready pose (a signed ReturnToReady
    in the operator's name; runtime/recovery.py). Progress and the end follow in the machine's live
    state (``returning``, ``return_progress``, ``return_result``). Audited; works during a storage
    fault as the E-STOP does (:func:`_operator_command`)."""
    user, ack = _operator_command(request, fleet, sessions, backlog, "return_to_ready", machine_id,
                                  "return to the ready pose", lambda username: fleet.return_to_ready(machine_id, username))
    backlog.record(user.username, "return_to_ready", machine_id, delivered=True, accepted=ack.accepted, reason=ack.reason)
    if not ack.accepted:
        raise Conflict(f"the runtime of {machine_id} refused to return to the ready pose: {ack.reason}")
    return ReturnToReadyOut(machine_id=machine_id, accepted=True)


class LeaseOut(BaseModel):
    """The machine's lease after a takeover: ``holder`` is the server id that commands it now."""

    machine_id: str
    granted: bool
    holder: str | None = None
    reason: str | None = None


@router.post("/{machine_id}/lease/takeover", response_model=LeaseOut,
             responses=errors(401, (403, "needs the operator role"),
                              (409, "the runtime refused the takeover (its reason: a throw of the holder runs, ...)"),
                              *COMMAND_RESPONSES))
def take_over(machine_id: str, request: Request, sessions: SessionsDep, fleet: FleetDep,
              backlog: AuditBacklogDep) -> LeaseOut:
    """Take the machine's lease from the server that holds it (one writer per machine:
    runtime.service): a signed ``LeaseRequest(takeover=True)`` in the operator's name
    (server.fleet.commands.FleetCommands.lease); the runtime refuses it while a throw runs. From
    then on this server commands the machine and the other one is refused with this server named.
    Audited (``lease_takeover``), from memory as the E-STOP reset (:func:`_operator_command`)."""
    user, ack = _operator_command(request, fleet, sessions, backlog, "lease_takeover", machine_id, "lease takeover",
                                  lambda username: fleet.lease(machine_id, username, takeover=True))
    backlog.record(user.username, "lease_takeover", machine_id, delivered=True, granted=ack.granted, holder=ack.holder,
                   reason=ack.reason)
    if not ack.granted:
        raise Conflict(f"the runtime of {machine_id} refused the takeover: {ack.reason}")
    return LeaseOut(machine_id=machine_id, granted=True, holder=ack.holder, reason=ack.reason)


@router.post("/{machine_id}/drift/ack", response_model=DriftAlertOut, responses=errors(
    (403, "needs the operator role"), (404, "the machine has no drift alert")))
def acknowledge_drift(machine_id: str, drift: DriftDep, sessions: SessionsDep, user: ViewerDep) -> dict[str, Any]:
    """Acknowledge the machine's drift alert (server.analysis.drift.DriftWatch.acknowledge): it stays on
    record as acknowledged, and every open console clears its drift alarm (a ``drift`` event on
    /api/live). Operators and admins; audited as ``drift_ack`` (refusals too). Returns the alert."""
    authorised_or_audited(user, "operator", lambda reason: record_audit(
        sessions, user.username, "drift_ack", machine_id[:64], acknowledged=False, reason=reason),
        "acknowledging a drift alert")
    alert = drift.acknowledge(machine_id, user.username)
    if alert is None:
        raise NotFound(f"{machine_id} has no drift alert to acknowledge")
    record_audit(sessions, user.username, "drift_ack", machine_id, acknowledged=True, raised_at=alert.get("raised_at"),
                 alert=alert.get("text"))
    return alert
