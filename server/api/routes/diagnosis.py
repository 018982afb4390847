"""Sim-to-real gap diagnosis: run one on a machine's stored throws, list runs, read a report and
its plots (server.diagnosis keeps everything as files under the data dir)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse
from pydantic import BaseModel, Field

from server.api.deps import OperatorDep, ViewerDep
from server.auth import record_audit
from server.diagnosis import DiagnosisBusy, DiagnosisRuns

router = APIRouter(prefix="/api/diagnosis", tags=["diagnosis"])


def get_runs(request: Request) -> DiagnosisRuns:
    runs = getattr(request.app.state, "diagnosis_runs", None)
    if runs is None:
        runs = DiagnosisRuns(request.app.state.sessions, request.app.state.settings.data_dir, jobs=request.app.state.jobs)
        request.app.state.diagnosis_runs = runs
    return runs


RunsDep = Annotated[DiagnosisRuns, Depends(get_runs)]


class DiagnosisCreate(BaseModel):
    machine_id: str = Field(min_length=1, max_length=64)
    limit: int = Field(50, ge=4, le=500, description="newest landed throws to diagnose")


@router.get("/effects", responses={503: {"description": "no worker answered"}})
async def effects(request: Request, _user: ViewerDep) -> dict:
    """The effects library: name, physical meaning, parameters with units, prior ranges, sources
    (a ``catalog`` job: the twin lives in the workers; kept once fetched)."""
    cached = getattr(request.app.state, "effects_catalog", None)
    if cached is None:
        jobs = request.app.state.jobs
        job_id = await run_in_threadpool(jobs.submit, "catalog", {})
        job = await jobs.wait_async(job_id, 10.0)
        if job is None or job["status"] != "done":
            if job is not None and job["status"] in ("queued", "running"):
                await run_in_threadpool(jobs.cancel, job_id)
            raise HTTPException(503, f"no worker described the effects library: {(job or {}).get('error') or 'timeout'}")
        cached = request.app.state.effects_catalog = job["result"]["effects"]
    return cached


@router.get("/runs")
def list_runs(runs: RunsDep, _user: ViewerDep, machine_id: str | None = None) -> list[dict]:
    """Diagnosis runs, newest first (status, verdict)."""
    return runs.list(machine_id)


@router.post("/runs", status_code=202, responses={409: {"description": "a diagnosis is running"}, 422: {"description": "too few throws"}})
def create_run(body: DiagnosisCreate, runs: RunsDep, user: OperatorDep, request: Request) -> dict:
    """Export the machine's newest landed throws and diagnose them in the background (audited,
    refusals too: ``diagnosis_run``)."""
    sessions = request.app.state.sessions
    try:
        st = runs.start(body.machine_id, body.limit, requested_by=user.username)
    except DiagnosisBusy as e:
        record_audit(sessions, user.username, "diagnosis_run", body.machine_id[:64], started=False, reason=str(e))
        raise HTTPException(409, str(e)) from e
    except ValueError as e:
        record_audit(sessions, user.username, "diagnosis_run", body.machine_id[:64], started=False, reason=str(e))
        raise HTTPException(422, str(e)) from e
    record_audit(sessions, user.username, "diagnosis_run", body.machine_id, started=True, run_id=st.get("id"), limit=body.limit)
    return st


@router.get("/runs/{run_id}", responses={404: {"description": "no such run"}})
def get_run(run_id: str, runs: RunsDep, _user: ViewerDep) -> dict:
    """Status of a run, with the full report once it is done."""
    st = runs.get(run_id)
    if st is None:
        raise HTTPException(404, f"no diagnosis run {run_id}")
    return st


@router.get("/runs/{run_id}/files/{name}", response_class=FileResponse, responses={404: {"description": "no such file"}})
def get_file(run_id: str, name: str, runs: RunsDep, _user: ViewerDep) -> FileResponse:
    """A report file: report.json, profile_fitted.json or a plot (where, traces, which, how_far .png)."""
    path = runs.file(run_id, name)
    if path is None:
        raise HTTPException(404, f"no file {name} in diagnosis run {run_id}")
    return FileResponse(path, media_type="image/png" if name.endswith(".png") else "application/json")
