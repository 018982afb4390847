"""Alarms (server.console.alarms): the active list and the history (viewers), acknowledge one or all,
shelve for a bounded time and unshelve (operators; every act audited). Changes reach every open
console as ``alarm`` events on /api/live."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Query
from pydantic import BaseModel, ConfigDict, Field

from server.api.deps import AlarmsDep, OperatorDep, ViewerDep
from server.api.responses import errors
from server.console.alarms import HISTORY_LIMIT, MAX_SHELVE_MIN

router = APIRouter(prefix="/api/alarms", tags=["alarms"])


class AlarmOut(BaseModel):
    """One alarm. ``state`` after ISA-18.2: ``unacked`` (active, not acknowledged), ``acked``
    (active, acknowledged), ``rtn_unacked`` (cleared, not acknowledged), ``normal`` (cleared and
    acknowledged: history only). ``shelved``: hidden from the banner until ``shelved_until``.
    ``cause``: ``host_behind_real_time``, ``runtime_not_answering``, ``link_lost``,
    ``machine_fault`` or ``drift``. Times are ISO 8601 UTC."""

    id: str
    key: str
    machine_id: str | None
    priority: Literal["high", "medium", "low"]
    cause: str
    title: str
    text: str
    todo: str
    subject: str | None
    state: Literal["unacked", "acked", "rtn_unacked", "normal"]
    active: bool
    shelved: bool
    raised_at: str
    cleared_at: str | None
    acked_at: str | None
    acked_by: str | None
    shelved_until: str | None
    shelved_by: str | None
    revision: int
    """1 when raised, one more with every change: of two records of one alarm the higher is newer."""


class AckAllIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    machine_id: str | None = Field(default=None, min_length=1, max_length=64)
    """Only this machine's alarms (None: all)."""


class ShelveIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    minutes: float = Field(gt=0, le=MAX_SHELVE_MIN)
    """How long the alarm stays off the banner (at most one shift)."""


@router.get("", response_model=list[AlarmOut])
def list_alarms(alarms: AlarmsDep, _user: ViewerDep, active: bool = True,
                machine_id: str | None = Query(default=None, max_length=64),
                limit: int = Query(default=100, ge=1, le=HISTORY_LIMIT), offset: int = Query(default=0, ge=0)) -> list[dict]:
    """``active=true`` (default): the active alarms, newest first; ``active=false``: the alarm
    history (every alarm, newest first, paged by ``limit``/``offset``)."""
    if active:
        rows = alarms.active()
        return [a for a in rows if machine_id is None or a["machine_id"] == machine_id]
    return alarms.history(machine_id, limit, offset)


@router.post("/ack-all", response_model=list[AlarmOut], responses=errors((403, "needs the operator role")))
def acknowledge_all(body: AckAllIn, alarms: AlarmsDep, user: OperatorDep) -> list[dict]:
    """Acknowledge every unacknowledged active alarm (of ``machine_id``, or all); returns those
    acknowledged now (audited as ``alarm_ack`` each)."""
    return alarms.acknowledge_all(user.username, body.machine_id)


@router.post("/{alarm_id}/ack", response_model=AlarmOut,
             responses=errors((403, "needs the operator role"), (404, "no such alarm")))
def acknowledge(alarm_id: str, alarms: AlarmsDep, user: OperatorDep) -> dict:
    """Acknowledge one alarm (who and when are kept; a drift alarm also acknowledges the drift alert)."""
    return alarms.acknowledge(alarm_id, user.username)


@router.post("/{alarm_id}/shelve", response_model=AlarmOut, responses=errors(
    (403, "needs the operator role"), (404, "no such alarm"), (409, "the alarm is no longer active"),
    (422, "minutes out of range")))
def shelve(alarm_id: str, body: ShelveIn, alarms: AlarmsDep, user: OperatorDep) -> dict:
    """Shelve an active alarm for ``minutes``: off the banner, still listed, back by itself."""
    return alarms.shelve(alarm_id, user.username, body.minutes)


@router.delete("/{alarm_id}/shelve", response_model=AlarmOut,
               responses=errors((403, "needs the operator role"), (404, "no such alarm")))
def unshelve(alarm_id: str, alarms: AlarmsDep, user: OperatorDep) -> dict:
    """End an alarm's shelving now."""
    return alarms.unshelve(alarm_id, user.username)
