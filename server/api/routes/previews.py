"""Previews: POST /api/previews runs the machine's active policy in the twin; GET one back."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException
from fastapi.concurrency import run_in_threadpool

from server.api.deps import JobWatcherDep, OperatorDep, PreviewsDep, SettingsDep, ViewerDep
from server.api.preview_schemas import PreviewCreate, PreviewOut
from server.api.schemas import Problem

router = APIRouter(prefix="/api/previews", tags=["previews"])


@router.post(
    "",
    response_model=PreviewOut,
    responses={
        404: {"model": Problem, "description": "unknown machine"},
        409: {"model": Problem, "description": "the server has no file of the machine's policy, or it does not load"},
        422: {"model": Problem, "description": "a target the mode cannot serve (the reason)"},
        429: {"model": Problem, "description": "the user has their limit of previews queued or running"},
        503: {"model": Problem, "description": "runtime offline, no machine state, or no worker answered in 3 s"},
    },
)
async def create_preview(body: PreviewCreate, service: PreviewsDep, settings: SettingsDep, watcher: JobWatcherDep,
                         user: OperatorDep) -> PreviewOut:
    """Preview a throw of ``machine_id`` at ``target`` in ``mode`` from its current joint state.

    ``rollouts`` <= 1 gives the nominal rollout only (fast); more adds the Monte Carlo 1 sigma
    impact ellipse over the release-delay jitter. The twin runs in a worker (a ``preview`` job;
    its id is the preview id); this route awaits it without holding a request thread. The console
    draws it in its own 3D view (POST /api/consoles/{id}/preview).
    """
    rollouts = body.rollouts if body.rollouts is not None else settings.preview_rollouts
    job_id = await run_in_threadpool(service.submit, body.machine_id, body.mode, body.target, rollouts,
                                     user.username)
    timeout_s = settings.preview_timeout_s
    job = await watcher.wait(job_id, timeout_s)
    summary = await run_in_threadpool(service.outcome, job, timeout_s)  # domain errors: server.api.errors
    return PreviewOut(**summary)


@router.get("/{preview_id}", response_model=PreviewOut, responses={404: {"model": Problem}})
def get_preview(preview_id: str, service: PreviewsDep, _user: ViewerDep) -> PreviewOut:
    summary = service.get(preview_id)
    if summary is None:
        raise HTTPException(404, f"no preview {preview_id} (previews are kept for a while only)")
    return PreviewOut(**summary)
