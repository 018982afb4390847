"""Sim-to-real gap diagnosis: run one on a machine's stored throws or on uploaded rosbag2 bags of a
ROS 2 machine (POST /uploads), list runs, read a report and its plots (a run is a ``diagnosis`` job: server.analysis.diagnosis; progress and completion are ``job``
events on /api/live)."""

from __future__ import annotations

from fastapi import APIRouter, File, Form, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from server.accounts.auth import record_audit
from server.api.deps import DiagnosisRunsDep, JobsDep, JobWatcherDep, OperatorDep, SessionsDep, SettingsDep, ViewerDep
from server.api.report_schemas import DiagnosisRunOut, EffectOut
from server.api.responses import errors
from server.api.web_guard import contained_file
from server.errors import DomainError, TooLarge, Unavailable, found

router = APIRouter(prefix="/api/diagnosis", tags=["diagnosis"])


RunsDep = DiagnosisRunsDep


class DiagnosisCreate(BaseModel):
    machine_id: str = Field(min_length=1, max_length=64)
    limit: int = Field(50, ge=4, le=500, description="newest landed throws to diagnose")


@router.get("/effects", response_model=dict[str, EffectOut], responses=errors((503, "no worker answered")))
async def effects(runs: RunsDep, jobs: JobsDep, watcher: JobWatcherDep, _user: ViewerDep) -> dict:
    """The effects library: name, physical meaning, parameters with units, prior ranges, sources
    (a ``catalog`` job: the twin lives in the workers; kept once fetched)."""
    cached = runs.effects_catalog
    if cached is None:
        job_id = await run_in_threadpool(jobs.submit, "catalog", {})
        job = await watcher.wait(job_id, 10.0)
        if job is None or job["status"] != "done":
            if job is not None and job["status"] in ("queued", "running"):
                await run_in_threadpool(jobs.cancel, job_id)
            raise Unavailable(f"no worker described the effects library: {(job or {}).get('error') or 'timeout'}")
        cached = runs.effects_catalog = job["result"]["effects"]
    return cached


@router.get("/runs", response_model=list[DiagnosisRunOut])
def list_runs(runs: RunsDep, _user: ViewerDep, machine_id: str | None = None) -> list[dict]:
    """Diagnosis runs, newest first (status, verdict)."""
    return runs.list(machine_id)


@router.post("/runs", status_code=202, response_model=DiagnosisRunOut, responses=errors((409, "a diagnosis is running"), (422, "too few throws")))
def create_run(body: DiagnosisCreate, runs: RunsDep, user: OperatorDep, sessions: SessionsDep) -> dict:
    """Export the machine's newest landed throws and diagnose them in the background (audited,
    refusals too: ``diagnosis_run``)."""
    try:
        st = runs.start(body.machine_id, body.limit, requested_by=user.username)
    except DomainError as e:  # DiagnosisBusy: 409; TooFewThrows, JobSpecError: 422
        record_audit(sessions, user.username, "diagnosis_run", body.machine_id[:64], started=False, reason=str(e))
        raise
    record_audit(sessions, user.username, "diagnosis_run", body.machine_id, started=True, run_id=st.get("id"), limit=body.limit)
    return st


@router.post("/uploads", status_code=202, response_model=DiagnosisRunOut, responses=errors((409, "a diagnosis is running"), (413, "upload too large"),
                                                            (422, "unusable upload (the detail says why)")))
async def upload_bags(
    settings: SettingsDep,
    runs: RunsDep,
    user: OperatorDep,
    bags: list[UploadFile] = File(..., description="one bag per throw: .mcap, .db3, or a .zip of a rosbag2 directory; "
                                                   "the file's stem is the throw id"),
    mapping: UploadFile = File(..., description="the ROS 2 mapping (.toml, .json, .yaml; sim_twin.diagnosis.rosbag)"),
    impacts: UploadFile = File(..., description="CSV: throw_id, target_x_m, target_y_m, impact_x_m, impact_y_m"),
    machine_id: str = Form("external", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$",
                           description="whose throws (a label of the run; need not be a machine of this fleet)"),
) -> dict:
    """Diagnose a ROS 2 machine's rosbag2 recordings: store them, then convert and diagnose in a
    worker (GET /runs/{id} follows it; a conversion problem fails the run with its reason)."""
    limit, total = settings.max_bag_upload_bytes, 0

    async def read(f: UploadFile) -> bytes:
        nonlocal total
        data = await f.read(limit + 1 - total)
        total += len(data)
        if total > limit:
            raise TooLarge(f"upload larger than {limit} bytes")
        return data

    files = [(b.filename or "", await read(b)) for b in bags]
    mapping_file = (mapping.filename or "", await read(mapping))
    impacts_data = await read(impacts)
    return await run_in_threadpool(runs.start_upload, machine_id, files, mapping_file, impacts_data, user.username,
                                   max_bytes=limit)  # DiagnosisBusy: 409, UploadError: 422


@router.get("/runs/{run_id}", response_model=DiagnosisRunOut, responses=errors((404, "no such run")))
def get_run(run_id: str, runs: RunsDep, _user: ViewerDep) -> dict:
    """Status of a run, with the full report once it is done."""
    return found(runs.get(run_id), f"no diagnosis run {run_id}")


@router.get("/runs/{run_id}/files/{name}", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}, "application/json": {}}}, **errors((404, "no such file"))})
def get_file(run_id: str, name: str, runs: RunsDep, _user: ViewerDep) -> FileResponse:
    """A report file: report.json, profile_fitted.json or a plot (where, traces, which, how_far .png)."""
    path = runs.file(run_id, name)
    path = contained_file(path.parent, path) if path is not None else None  # no link out of the report folder
    path = found(path, f"no file {name} in diagnosis run {run_id}")
    return FileResponse(path, media_type="image/png" if name.endswith(".png") else "application/json")
