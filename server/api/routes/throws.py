"""Throws: start one (POST); the history with filters, sorting and pagination (GET, total in the
``X-Total-Count`` header), its CSV export and accuracy statistics; one throw, its telemetry
(MCAP), its trajectory (JSON) and its replay in the 3D view."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.responses import FileResponse, PlainTextResponse

from server.api.deps import OperatorDep, SceneDep, SessionDep, ThrowServiceDep, ViewerDep
from server.api.schemas import Problem, ThrowCreate, ThrowCreated, ThrowOut
from server.db.models import Throw
from server.history import SORTS, ThrowFilter, accuracy, page, to_csv
from server.throws import ThrowRefused

router = APIRouter(prefix="/api/throws", tags=["throws"])
EXPORT_LIMIT = 100_000


def throw_filter(
    machine_id: str | None = None,
    policy_version: str | None = None,
    mode: Literal["2d", "3d"] | None = None,
    status: str | None = None,
    min_distance_m: float | None = Query(None, ge=0),
    max_distance_m: float | None = Query(None, ge=0),
    since: datetime | None = None,
    until: datetime | None = None,
) -> ThrowFilter:
    """History filters as query parameters (times ISO 8601 with a zone)."""
    return ThrowFilter(machine_id, policy_version, mode, status, min_distance_m, max_distance_m, since, until)


@router.post(
    "",
    status_code=202,
    response_model=ThrowCreated,
    responses={
        404: {"model": Problem, "description": "unknown machine"},
        422: {"description": "malformed request, target the mode cannot serve, unconfirmed 3D throw, or the runtime refused"},
        503: {"model": Problem, "description": "runtime offline or not answering"},
    },
)
def create_throw(body: ThrowCreate, service: ThrowServiceDep, user: OperatorDep) -> ThrowCreated:
    """Throw at ``target`` ([x, y, z], machine frame, m) with ``machine_id`` in ``mode``, as
    previewed (``preview_id``). 3D throws need ``confirm_clearance: true``.

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
    response: Response,
    _user: ViewerDep,
    flt: ThrowFilter = Depends(throw_filter),
    sort: Literal[tuple(SORTS)] = "requested_at",  # type: ignore[valid-type]
    order: Literal["asc", "desc"] = "desc",
    limit: int = Query(50, ge=1, le=500),
    offset: int = Query(0, ge=0),
) -> list[ThrowOut]:
    """Throws matching the filters, sorted (default newest first), one page; the number of all
    matching throws is in the ``X-Total-Count`` header."""
    rows, total = page(db, flt, sort, order, limit, offset)
    response.headers["X-Total-Count"] = str(total)
    return [ThrowOut.of(t) for t in rows]


@router.get("/export.csv", response_class=PlainTextResponse, responses={200: {"content": {"text/csv": {}}}})
def export_csv(db: SessionDep, _user: ViewerDep, flt: ThrowFilter = Depends(throw_filter)) -> Response:
    """All throws matching the filters as CSV (newest first)."""
    rows, _ = page(db, flt, limit=EXPORT_LIMIT)
    return Response(to_csv(rows), media_type="text/csv",
                    headers={"Content-Disposition": 'attachment; filename="throws.csv"'})


@router.get("/accuracy")
def get_accuracy(db: SessionDep, _user: ViewerDep, flt: ThrowFilter = Depends(throw_filter)) -> list[dict]:
    """Accuracy of the landed throws matching the filters, per mode, policy version and target
    distance (0.5 m bins): mean impact distance, bias, 1 sigma downrange/crossrange, error ellipse."""
    rows, _ = page(db, flt, limit=EXPORT_LIMIT)
    return accuracy(rows)


def _row(db, throw_id: str) -> Throw:
    row = db.get(Throw, throw_id)
    if row is None:
        raise HTTPException(404, f"no throw {throw_id}")
    return row


@router.get("/{throw_id}", response_model=ThrowOut, responses={404: {"model": Problem}})
def get_throw(throw_id: str, db: SessionDep, _user: ViewerDep) -> ThrowOut:
    return ThrowOut.of(_row(db, throw_id))


@router.get(
    "/{throw_id}/telemetry",
    response_class=FileResponse,
    responses={200: {"content": {"application/x-mcap": {}}}, 404: {"model": Problem}},
)
def get_telemetry(throw_id: str, db: SessionDep, request: Request, _user: ViewerDep) -> FileResponse:
    """The throw's 100 Hz telemetry as an MCAP file."""
    row = _row(db, throw_id)
    path = request.app.state.store.telemetry_file(row)
    if path is None or not path.is_file():
        raise HTTPException(404, f"throw {throw_id} has no telemetry")
    return FileResponse(path, media_type="application/x-mcap", filename=f"throw-{throw_id}.mcap")


@router.get("/{throw_id}/trajectory", responses={404: {"model": Problem}})
def get_trajectory(throw_id: str, db: SessionDep, request: Request, _user: ViewerDep) -> dict:
    """The recorded trajectory (from the MCAP telemetry, at most 300 points): time, gripper-centre
    path (forward kinematics of the joints), payload path, phase events; with the preview."""
    from runtime.machine import forward_kinematics
    from runtime.telemetry import read_telemetry

    row = _row(db, throw_id)
    path = request.app.state.store.telemetry_file(row)
    if path is None or not path.is_file():
        raise HTTPException(404, f"throw {throw_id} has no telemetry")
    tel = read_telemetry(path)
    n = len(tel["t_s"])
    idx = np.unique(np.linspace(0, n - 1, min(n, 300)).astype(int)) if n else np.array([], dtype=int)
    gripper = [forward_kinematics(np, tel["q"][i], tel["qd"][i]).gripper_centre.round(4).tolist() for i in idx]
    payload = np.asarray(tel["payload_pos_m"])
    return {
        "throw_id": throw_id, "t_s": np.round(np.asarray(tel["t_s"])[idx], 4).tolist(),
        "gripper_path_m": gripper, "payload_path_m": np.round(payload, 4).tolist() if payload.size else [],
        "events": [{"t_s": float(t), "phase": str(p)} for t, p in zip(tel.get("event_t_s", []), tel.get("event_phase", []))],
        "target_m": row.target_m, "impact_m": row.impact_m, "preview": row.preview,
    }


@router.post("/{throw_id}/replay", status_code=204, responses={404: {"model": Problem}, 409: {"model": Problem}})
def replay(throw_id: str, db: SessionDep, request: Request, scene: SceneDep, _user: ViewerDep) -> Response:
    """Draw the throw's recorded trajectory and impact in the 3D view."""
    row = _row(db, throw_id)
    if scene is None:
        raise HTTPException(409, "the 3D view is disabled")
    scene.show_throw(request.app.state.store.telemetry_file(row), row.impact_m, row.target_m)
    return Response(status_code=204)
