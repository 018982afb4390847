"""Previews: POST /api/previews runs the machine's active policy in the twin; GET one back."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request

from server.api.deps import OperatorDep, SceneDep, ViewerDep
from server.api.preview_schemas import PreviewCreate, PreviewOut
from server.api.schemas import Problem
from server.throws import ThrowRefused

router = APIRouter(prefix="/api/previews", tags=["previews"])


@router.post(
    "",
    response_model=PreviewOut,
    responses={
        404: {"model": Problem, "description": "unknown machine"},
        409: {"model": Problem, "description": "the server has no file of the machine's policy"},
        422: {"model": Problem, "description": "a target the mode cannot serve (the reason)"},
        503: {"model": Problem, "description": "runtime offline or no machine state"},
    },
)
def create_preview(body: PreviewCreate, request: Request, scene: SceneDep, _user: OperatorDep) -> PreviewOut:
    """Preview a throw of ``machine_id`` at ``target`` in ``mode`` from its current joint state.

    ``rollouts`` <= 1 gives the nominal rollout only (fast); more adds the Monte Carlo 1 sigma
    impact ellipse over the release-delay jitter. The 3D view draws the preview.
    """
    service = request.app.state.previews
    rollouts = body.rollouts if body.rollouts is not None else request.app.state.settings.preview_rollouts
    try:
        summary = service.preview(body.machine_id, body.mode, body.target, rollouts)
    except ThrowRefused as e:
        raise HTTPException(e.status_code, e.detail) from e
    if scene is not None and scene.machine_id in (None, body.machine_id):
        scene.show_preview(summary)
    return PreviewOut(**summary)


@router.get("/{preview_id}", response_model=PreviewOut, responses={404: {"model": Problem}})
def get_preview(preview_id: str, request: Request, _user: ViewerDep) -> PreviewOut:
    summary = request.app.state.previews.get(preview_id)
    if summary is None:
        raise HTTPException(404, f"no preview {preview_id} (previews are kept for a while only)")
    return PreviewOut(**summary)
