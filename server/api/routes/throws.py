"""Throws: start one (POST), read one or the history (GET), download its telemetry (MCAP)."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import FileResponse
from sqlalchemy import select

from server.api.deps import OperatorDep, SessionDep, ThrowServiceDep, ViewerDep
from server.api.schemas import Problem, ThrowCreate, ThrowCreated, ThrowOut
from server.db.models import Throw
from server.throws import ThrowRefused

router = APIRouter(prefix="/api/throws", tags=["throws"])


@router.post(
    "",
    status_code=202,
    response_model=ThrowCreated,
    responses={
        404: {"model": Problem, "description": "unknown machine"},
        422: {"description": "malformed request, target the mode cannot serve, or the runtime refused"},
        503: {"model": Problem, "description": "runtime offline or not answering"},
    },
)
def create_throw(body: ThrowCreate, service: ThrowServiceDep, user: OperatorDep) -> ThrowCreated:
    """Throw at ``target`` ([x, y, z], machine frame, m) with ``machine_id`` in ``mode``.

    202 means the runtime accepted the throw; follow it with GET /api/throws/{id}.
    On any error no throw is recorded.
    """
    try:
        row, ack = service.create(body, user.username)
    except ThrowRefused as e:
        raise HTTPException(e.status_code, e.detail) from e
    return ThrowCreated(id=row.id, status=row.status, policy_version=ack.policy_version)


@router.get("", response_model=list[ThrowOut])
def list_throws(
    db: SessionDep,
    _user: ViewerDep,
    machine_id: str | None = None,
    limit: int = Query(50, ge=1, le=500),
) -> list[ThrowOut]:
    """Throws, newest first, optionally of one machine."""
    stmt = select(Throw).order_by(Throw.requested_at.desc(), Throw.id).limit(limit)
    if machine_id is not None:
        stmt = stmt.where(Throw.machine_id == machine_id)
    return [ThrowOut.of(t) for t in db.scalars(stmt)]


@router.get("/{throw_id}", response_model=ThrowOut, responses={404: {"model": Problem}})
def get_throw(throw_id: str, db: SessionDep, _user: ViewerDep) -> ThrowOut:
    row = db.get(Throw, throw_id)
    if row is None:
        raise HTTPException(404, f"no throw {throw_id}")
    return ThrowOut.of(row)


@router.get(
    "/{throw_id}/telemetry",
    response_class=FileResponse,
    responses={200: {"content": {"application/x-mcap": {}}}, 404: {"model": Problem}},
)
def get_telemetry(throw_id: str, db: SessionDep, request: Request, _user: ViewerDep) -> FileResponse:
    """The throw's 100 Hz telemetry as an MCAP file."""
    row = db.get(Throw, throw_id)
    if row is None:
        raise HTTPException(404, f"no throw {throw_id}")
    path = request.app.state.store.telemetry_file(row)
    if path is None or not path.is_file():
        raise HTTPException(404, f"throw {throw_id} has no telemetry")
    return FileResponse(path, media_type="application/x-mcap", filename=f"throw-{throw_id}.mcap")
