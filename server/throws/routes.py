"""Throws: start one (POST); the history with filters, sorting and pagination (GET, total in the
``X-Total-Count`` header), its CSV export and accuracy statistics; one throw, its telemetry
(MCAP), its trajectory (JSON) and its replay in the 3D view."""

from __future__ import annotations

from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, Query, Response
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse

from server.analysis.accuracy import accuracy
from server.api.deps import OperatorDep, SceneDep, SessionDep, StoreDep, ThrowServiceDep, ViewerDep
from server.api.report_schemas import AccuracyGroupOut, TrajectoryOut
from server.api.responses import errors
from server.api.schemas import DISTANCE_LIMIT_M, ThrowCreate, ThrowCreated, ThrowOut, ThrowStatusName, UtcTime
from server.api.web_guard import contained_file
from server.console.scene import enabled
from server.db.models import Throw
from server.errors import found
from server.throws.history import SORTS, ThrowFilter, page, to_csv
from server.throws.service import ThrowOrder

router = APIRouter(prefix="/api/throws", tags=["throws"])
EXPORT_LIMIT = 100_000


def throw_filter(
    machine_id: str | None = None,
    policy_version: str | None = None,
    mode: Literal["2d", "3d"] | None = None,
    status: ThrowStatusName | None = None,
    min_distance_m: float | None = Query(None, ge=0, le=DISTANCE_LIMIT_M, allow_inf_nan=False),
    max_distance_m: float | None = Query(None, ge=0, le=DISTANCE_LIMIT_M, allow_inf_nan=False),
    since: UtcTime | None = None,
    until: UtcTime | None = None,
    policy_sha256: str | None = Query(None, pattern=r"^[0-9a-f]{64}$"),
) -> ThrowFilter:
    """History filters as query parameters (times ISO 8601 with a zone; distances finite, m, at
    most DISTANCE_LIMIT_M: else 422). ``policy_sha256`` names a policy version exactly;
    ``policy_version`` (a name) may match several files."""
    return ThrowFilter(machine_id, policy_version, mode, status, min_distance_m, max_distance_m, since, until,
                       policy_sha256)


@router.post(
    "",
    status_code=202,
    response_model=ThrowCreated,
    responses=errors(
        (404, "unknown machine"),
        (409, "the preview is stale, the policy changed or the machine moved since (condition in the "
              "X-Refused-Condition header)"),
        (422, "malformed request, target the mode cannot serve, no/failed/other preview (X-Refused-Condition), "
              "unconfirmed 3D throw, or the runtime refused"),
        (503, "runtime offline or not answering, or no command key"),
    ),
)
def create_throw(body: ThrowCreate, service: ThrowServiceDep, user: OperatorDep) -> ThrowCreated:
    """Throw at ``target`` ([x, y, z], machine frame, m) with ``machine_id`` in ``mode``, as
    previewed (``preview_id``: a fresh OK preview of the same machine, mode, target and policy
    from about the machine's current state; see server.throws.gate). 3D throws need
    ``confirm_clearance: true``.

    202 means the runtime accepted the throw; follow it with GET /api/throws/{id}. On a refusal
    no throw is recorded; on 503 after the request was sent the throw stays until its runtime
    reports it or the reconciliation marks it ``lost``.
    """
    order = ThrowOrder(body.machine_id, body.mode, list(body.target), body.preview_id, body.confirm_clearance)
    row, ack = service.create(order, user.username)  # domain errors: server.api.errors
    return ThrowCreated(id=row.id, status=row.status, policy_version=ack.policy_version, policy_sha256=row.policy_sha256)


@router.get("", response_model=list[ThrowOut])
def list_throws(
    db: SessionDep,
    response: Response,
    _user: ViewerDep,
    flt: ThrowFilter = Depends(throw_filter),
    sort: Literal[tuple(SORTS)] = "requested_at",  # type: ignore[valid-type]
    order: Literal["asc", "desc"] = "desc",
    limit: int = Query(50, ge=1, le=500),
    offset: int = Query(0, ge=0, le=1_000_000_000),
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


@router.get("/accuracy", response_model=list[AccuracyGroupOut])
def get_accuracy(db: SessionDep, _user: ViewerDep, flt: ThrowFilter = Depends(throw_filter)) -> JSONResponse:
    """Accuracy of the landed throws matching the filters, per mode, policy version (SHA-256) and
    target distance (0.5 m bins): mean impact distance, bias, 1 sigma downrange/crossrange, error
    ellipse, and for the scatter plot up to 200 errors per group, the group's newest among the
    newest 1000 matching landed throws (server.analysis.accuracy.SCATTER_SAMPLE). Plain JSON (floats and
    lists only), so the response skips FastAPI's encoder.

    Answered from the incremental aggregates (``throw_accuracy``, updated in the transaction
    that stores each result) for the machine, mode, policy, status and time filters (times
    inside a day add a row scan of that partial day); ``min_distance_m``/``max_distance_m``
    fall back to a scan of every matching landed row (see server.analysis.accuracy)."""
    return JSONResponse(accuracy(db, flt))


def _row(db, throw_id: str) -> Throw:
    return found(db.get(Throw, throw_id), f"no throw {throw_id}")


def _telemetry(store, row: Throw):
    """The path of the throw's telemetry file (inside the data folder); NotFound without one."""
    return found(contained_file(store.data_dir / "telemetry", store.telemetry_file(row)),
                 f"throw {row.id} has no telemetry")


@router.get("/{throw_id}", response_model=ThrowOut, responses=errors((404, "no such throw")))
def get_throw(throw_id: str, db: SessionDep, _user: ViewerDep) -> ThrowOut:
    return ThrowOut.of(_row(db, throw_id))


@router.get(
    "/{throw_id}/telemetry",
    response_class=FileResponse,
    responses={200: {"content": {"application/x-mcap": {}}}, **errors((404, "no such throw, or no telemetry"))},
)
def get_telemetry(throw_id: str, db: SessionDep, store: StoreDep, _user: ViewerDep) -> FileResponse:
    """The throw's 100 Hz telemetry as an MCAP file."""
    path = _telemetry(store, _row(db, throw_id))
    return FileResponse(path, media_type="application/x-mcap", filename=f"throw-{throw_id}.mcap")


@router.get("/{throw_id}/trajectory", response_model=TrajectoryOut, responses=errors((404, "no such throw, or no telemetry")))
def get_trajectory(throw_id: str, db: SessionDep, store: StoreDep, _user: ViewerDep) -> dict:
    """The recorded trajectory (from the MCAP telemetry, at most 300 points): time, gripper-centre
    path (forward kinematics of the joints), joint velocities ``qd`` (N, 6) and their references
    ``qd_ref`` (N, 4), valve commands ``valve_u`` (N, 4), passive angles (``q`` columns 4-5),
    payload path with its own times ``payload_t_s``, phase events; with the preview."""
    from runtime.machine import forward_kinematics
    from runtime.telemetry import read_telemetry

    row = _row(db, throw_id)
    tel = read_telemetry(_telemetry(store, row))
    n = len(tel["t_s"])
    idx = np.unique(np.linspace(0, n - 1, min(n, 300)).astype(int)) if n else np.array([], dtype=int)
    gripper = [forward_kinematics(np, tel["q"][i], tel["qd"][i]).gripper_centre.round(4).tolist() for i in idx]
    payload = np.asarray(tel["payload_pos_m"])
    pidx = np.unique(np.linspace(0, len(payload) - 1, min(len(payload), 300)).astype(int)) if len(payload) else idx[:0]

    def cols(key: str) -> list:
        a = np.asarray(tel[key])
        return np.round(a[idx], 4).tolist() if len(a) == n else []

    return {
        "throw_id": throw_id, "t_s": np.round(np.asarray(tel["t_s"])[idx], 4).tolist(),
        "q": cols("q"), "qd": cols("qd"), "qd_ref": cols("qd_ref"), "valve_u": cols("valve_u"),
        "payload_t_s": np.round(np.asarray(tel["payload_t_s"])[pidx], 4).tolist(),
        "gripper_path_m": gripper, "payload_path_m": np.round(payload[pidx], 4).tolist() if payload.size else [],
        "events": [{"t_s": float(t), "phase": str(p)} for t, p in zip(tel.get("event_t_s", []), tel.get("event_phase", []))],
        "target_m": row.target_m, "impact_m": row.impact_m, "preview": row.preview,
    }


@router.post("/{throw_id}/replay", status_code=204,
             responses=errors((404, "no such throw"), (409, "the 3D view is disabled")))
def replay(throw_id: str, db: SessionDep, store: StoreDep, scene: SceneDep, _user: OperatorDep) -> Response:
    """Draw the throw's recorded trajectory and impact in the 3D view (operators: the view is
    shared by every console, a viewer may not change it)."""
    row = _row(db, throw_id)
    enabled(scene).show_throw(row.machine_id, store.telemetry_file(row), row.impact_m, row.target_m)
    return Response(status_code=204)
