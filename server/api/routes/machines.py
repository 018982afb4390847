"""GET /api/machines: the machines the server knows or hears, with presence and policies."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException
from pydantic import BaseModel, Field
from sqlalchemy import select

from server.api.deps import FleetDep, OperatorDep, SessionDep, ViewerDep
from server.auth import audit
from server.api.schemas import MachineOut
from server.db.models import Machine, Throw
from server.fleet import Fleet, RuntimeUnavailable

router = APIRouter(prefix="/api/machines", tags=["machines"])

INFO_TIMEOUT_S = 1.0
INFO_MAX_AGE_S = 2.0  # busy flag and policies are at most this old


@router.get("", response_model=list[MachineOut])
def list_machines(db: SessionDep, fleet: FleetDep, _user: ViewerDep) -> list[MachineOut]:
    """All machines in the database plus any heard on Zenoh, sorted by id.

    ``simulated`` is True when the machine's own state says it is the simulated machine.
    """
    rows = {m.id: m for m in db.scalars(select(Machine))}
    states = fleet.latest_states()
    ids = sorted(set(rows) | fleet.online_ids() | set(states))
    return [_with_throws(db, _machine_out(mid, rows.get(mid), fleet)) for mid in ids]


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
    online = fleet.is_online(mid)
    info = fleet.fresh_info(mid, max_age_s=INFO_MAX_AGE_S, timeout_s=INFO_TIMEOUT_S)
    state = fleet.latest_state(mid)
    simulated = bool(
        (state is not None and state.simulated)
        or (info is not None and info.simulated)
        or (row is not None and row.simulated)
    )
    return MachineOut(
        id=mid, online=online, simulated=simulated,
        policies={p.mode: p.version for p in info.policies} if info else {},
        busy=info.busy if info else None,
        cabin_turn_rad=state.q[0] if state is not None else None,
    )


class AbortIn(BaseModel):
    reason: str = Field(default="operator abort", max_length=200)


class AbortOut(BaseModel):
    machine_id: str
    aborted_throw_id: str | None


@router.post("/{machine_id}/abort", response_model=AbortOut,
             responses={503: {"description": "the runtime did not answer"}})
def abort(machine_id: str, db: SessionDep, fleet: FleetDep, user: OperatorDep, body: AbortIn | None = None) -> AbortOut:
    """E-stop: the runtime ends any throw as aborted and puts the valves to neutral. Logged in the
    audit log even when the runtime does not answer."""
    reason = f"{(body or AbortIn()).reason} ({user.username})"
    try:
        ack = fleet.abort(machine_id, reason)
    except (RuntimeUnavailable, ValueError) as e:
        audit(db, user.username, "abort", machine_id, reason=reason, delivered=False, error=str(e))
        db.commit()
        raise HTTPException(503, f"abort of {machine_id} not confirmed: {e}") from e
    audit(db, user.username, "abort", machine_id, reason=reason, delivered=True, throw_id=ack.aborted_throw_id)
    db.commit()
    return AbortOut(machine_id=machine_id, aborted_throw_id=ack.aborted_throw_id)
