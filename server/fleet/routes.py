"""GET /api/machines: the machines the server knows or hears, with presence, policies and the
runtime's state (E-STOP latch, readiness, running throw). E-STOP: POST .../estop (alias .../abort)
on the fast path; POST .../estop/reset releases the latch and POST .../return-to-ready starts the
runtime's recovery action (operator, audited). POST .../drift/ack acknowledges the machine's
drift alert (server.analysis.drift; operator, audited)."""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

from fastapi import APIRouter, Request
from pydantic import BaseModel, Field
from sqlalchemy import select
from sqlalchemy.exc import SQLAlchemyError

from server.accounts.auth import AuditBacklog, audit, record_audit
from server.api.deps import (
    AuditBacklogDep,
    DriftDep,
    FleetDep,
    OperatorDep,
    SessionDep,
    SessionsDep,
    ViewerDep,
    authorised_or_audited,
    user_from_memory,
)
from server.api.report_schemas import DriftAlertOut
from server.api.responses import errors
from server.api.schemas import MachineOut
from server.db.models import Machine, Throw
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
    )


class AbortIn(BaseModel):
    reason: str = Field(default="operator abort", max_length=200)


class AbortOut(BaseModel):
    machine_id: str
    aborted_throw_id: str | None


class EstopResetOut(BaseModel):
    machine_id: str
    reset: bool
    reason: str | None = None


STOP_RESPONSES = errors(401, (403, "needs the operator role"), (404, "unknown machine"),
                        (503, "the runtime did not confirm the stop (the server holds it latched and keeps sending "
                              "it), or the session is unknown in memory and storage does not answer"))
"""The E-STOP checks its session itself (server.api.deps.user_from_memory): it lists 401/403."""


@router.post("/{machine_id}/estop", response_model=AbortOut, responses=STOP_RESPONSES)
@router.post("/{machine_id}/abort", response_model=AbortOut, responses=STOP_RESPONSES)
async def estop(machine_id: str, request: Request, fleet: FleetDep, sessions: SessionsDep, backlog: AuditBacklogDep,
                body: AbortIn | None = None) -> AbortOut:
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
    in memory while storage fails (server.accounts.auth.AuditBacklog)."""
    t0 = time.perf_counter()
    user = user_from_memory(request, "operator")
    reason = f"{(body or AbortIn()).reason} ({user.username})"
    try:
        t_auth = time.perf_counter()
        ack = await asyncio.wrap_future(fleet.estop(machine_id, reason, user.username))
        log.info("E-STOP %s: authenticated in %.1f ms, runtime confirmed after %.1f ms more", machine_id,
                 (t_auth - t0) * 1e3, (time.perf_counter() - t_auth) * 1e3)
    except (RuntimeUnavailable, ValueError) as e:
        error = _sentence(e)
        _audit_later(fleet, backlog, user.username, machine_id[:64], reason=reason, delivered=False, error=error)
        await asyncio.to_thread(_404_if_unknown, fleet, sessions, machine_id)
        raise Unavailable(f"abort of {machine_id} not confirmed: {error}") from e
    fleet.forget_info(machine_id)
    _audit_later(fleet, backlog, user.username, machine_id, reason=reason, delivered=True,
                 throw_id=ack.aborted_throw_id)
    return AbortOut(machine_id=machine_id, aborted_throw_id=ack.aborted_throw_id)


def _audit_later(fleet: Fleet, backlog: AuditBacklog, username: str, subject: str, **detail) -> None:
    """Audit an E-STOP (action ``abort``) on the fleet's database thread, after the stop went out;
    while storage fails the entry waits in ``backlog``. The E-STOP reply never waits for it."""
    def logged(done) -> None:
        if done.exception() is not None:
            log.error("E-STOP audit entry not written: %s", done.exception())

    fleet.submit_db_job(lambda: backlog.record(username, "abort", subject, **detail)).add_done_callback(logged)


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


def _delivered(db, username: str, action: str, machine_id: str, what: str, send, fleet: Fleet | None = None,
               sessions=None):
    """The runtime's ack of a signed command ``send()``; if it was not confirmed, the attempt is
    audited as undelivered (action ``action``) and NotFound (unknown machine, checked when
    ``fleet`` and ``sessions`` are given) or Unavailable names ``what``."""
    try:
        return send()
    except (RuntimeUnavailable, ValueError) as e:
        audit(db, username, action, machine_id[:64], delivered=False, error=_sentence(e))
        db.commit()
        if fleet is not None and sessions is not None:
            _404_if_unknown(fleet, sessions, machine_id)
        raise Unavailable(f"{what} of {machine_id} not confirmed: {_sentence(e)}") from e


@router.post("/{machine_id}/estop/reset", response_model=EstopResetOut,
             responses=errors((404, "unknown machine"), (409, "the runtime refused the reset (its reason)"),
                              (503, "the runtime did not answer, or no command key")))
def estop_reset(machine_id: str, db: SessionDep, sessions: SessionsDep, fleet: FleetDep, user: OperatorDep) -> EstopResetOut:
    """Release the runtime's latched E-STOP (a signed EstopReset in the operator's name); audited."""
    ack = _delivered(db, user.username, "estop_reset", machine_id, "E-STOP reset",
                     lambda: fleet.estop_reset(machine_id, user.username), fleet, sessions)
    audit(db, user.username, "estop_reset", machine_id, delivered=True, reset=ack.reset, reason=ack.reason)
    db.commit()
    if not ack.reset:
        clock = clock_warning(fleet.clock_offset_s(machine_id))
        raise Conflict(f"the runtime of {machine_id} kept E-STOP latched: {ack.reason}" + (f"; {clock}" if clock else ""))
    return EstopResetOut(machine_id=machine_id, reset=True, reason=ack.reason)


class ReturnToReadyOut(BaseModel):
    machine_id: str
    accepted: bool
    reason: str | None = None


@router.post("/{machine_id}/return-to-ready", response_model=ReturnToReadyOut,
             responses=errors((404, "unknown machine"), (409, "the runtime refused (its reason: E-STOP latched, a throw runs, ...)"),
                              (503, "the runtime did not answer, or no command key")))
def return_to_ready(machine_id: str, db: SessionDep, sessions: SessionsDep, fleet: FleetDep,
                    user: OperatorDep) -> ReturnToReadyOut:
    """Recovery action: the runtime drives the arm back to its ready pose (a signed ReturnToReady
    in the operator's name; runtime/recovery.py). Progress and the end follow in the machine's live
    state (``returning``, ``return_progress``, ``return_result``). Audited."""
    ack = _delivered(db, user.username, "return_to_ready", machine_id, "return to the ready pose",
                     lambda: fleet.return_to_ready(machine_id, user.username), fleet, sessions)
    audit(db, user.username, "return_to_ready", machine_id, delivered=True, accepted=ack.accepted, reason=ack.reason)
    db.commit()
    if not ack.accepted:
        raise Conflict(f"the runtime of {machine_id} refused to return to the ready pose: {ack.reason}")
    return ReturnToReadyOut(machine_id=machine_id, accepted=True)


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
