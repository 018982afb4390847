"""Jobs (server.jobs): list, read, cancel, stream progress, submit the kinds people start by hand.

``GET /api/jobs/{id}/events`` is a Server-Sent Events stream (``EventSource`` in the browser):
one ``job`` event with the job (without its result) whenever its status, progress or message
changes, polled from the database every 0.25 s; the stream ends after the final status.
"""

from __future__ import annotations

import asyncio
import json
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from server.api.deps import AdminDep, JobsDep, OperatorDep, ViewerDep
from server.api.responses import errors
from server.db.models import FINAL_JOB_STATUSES, JobKind, JobStatus
from server.errors import found

router = APIRouter(prefix="/api/jobs", tags=["jobs"])
STREAM_POLL_S = 0.25



class JobOut(BaseModel):
    """A job: ``progress`` in [0, 1]; ``result`` only when read one at a time."""

    id: str
    kind: JobKind
    status: JobStatus
    subject: str | None
    params: dict
    progress: float
    message: str | None
    error: str | None
    cancel_requested: bool
    worker: str | None
    requested_by: str | None
    created_at: str
    started_at: str | None
    finished_at: str | None
    attempts: int = Field(0, description="how often a worker started it (a job whose worker died is re-run)")
    heartbeat_at: str | None = Field(None, description="last lease renewal by its running worker (UTC)")
    result: dict | None = None


class ProbeParams(BaseModel):
    """A probe's parameters, bounded (a probe holds a worker for ``steps * step_s`` seconds)."""

    model_config = ConfigDict(extra="forbid")

    steps: int = Field(1, ge=1, le=1000)
    step_s: float = Field(0.0, ge=0.0, le=10.0, allow_inf_nan=False)
    fail: str | None = Field(None, max_length=200, description="fail with this message")
    machine_id: str | None = Field(None, max_length=64)


class JobCreate(BaseModel):
    """Jobs started by hand: ``probe`` (check that workers run: ``steps``, ``step_s``, ``fail``).
    Previews, evaluations, diagnoses and adaptations are started by their own routes."""

    kind: Literal["probe"]
    params: ProbeParams = Field(default_factory=ProbeParams)


@router.get("", response_model=list[JobOut])
def list_jobs(jobs: JobsDep, _user: ViewerDep, kind: JobKind | None = None, subject: str | None = None,
              status: JobStatus | None = None, limit: Annotated[int, Query(ge=1, le=500)] = 50) -> list[dict]:
    """Jobs, newest first, without results."""
    return jobs.store.list(kind, subject, status, limit)


@router.post("", response_model=JobOut, status_code=202,
             responses=errors((429, "the user has their limit of jobs queued or running")))
def create_job(body: JobCreate, jobs: JobsDep, user: AdminDep) -> dict:
    """Queue a probe (a worker health check that reports progress and can be cancelled)."""
    job_id = jobs.submit(body.kind, body.params.model_dump(exclude_none=True), subject=body.params.machine_id,
                         requested_by=user.username)  # JobLimit is a Limited: 429 (server.api.errors)
    return found(jobs.store.get(job_id), f"job {job_id} vanished as it was queued")


@router.get("/{job_id}", response_model=JobOut, responses=errors((404, "no such job")))
def get_job(job_id: str, jobs: JobsDep, _user: ViewerDep) -> dict:
    return found(jobs.store.get(job_id), f"no job {job_id}")


@router.post("/{job_id}/cancel", response_model=JobOut, responses=errors((404, "no such job")))
def cancel_job(job_id: str, jobs: JobsDep, _user: OperatorDep) -> dict:
    """Cancel: a queued job at once, a running one at its next progress report."""
    return found(jobs.cancel(job_id), f"no job {job_id}")


@router.get("/{job_id}/events", responses={200: {"content": {"text/event-stream": {}}}, **errors((404, "no such job"))},
            response_class=StreamingResponse)
async def job_events(job_id: str, request: Request, jobs: JobsDep, _user: ViewerDep) -> StreamingResponse:
    """Server-Sent Events: the job on every change of status, progress or message, until it ends."""
    store = jobs.store
    first = found(await run_in_threadpool(store.get, job_id), f"no job {job_id}")

    async def stream():
        job, last = first, None
        while True:
            view = {k: v for k, v in job.items() if k != "result"}
            key = (view["status"], view["progress"], view["message"])
            if key != last:
                last = key
                yield f"event: job\ndata: {json.dumps(view)}\n\n"
            if view["status"] in FINAL_JOB_STATUSES or await request.is_disconnected():
                return
            await asyncio.sleep(STREAM_POLL_S)
            job = await run_in_threadpool(store.get, job_id) or job

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
