"""Previews: POST /api/previews runs the machine's active policy in the twin; GET one back."""

from __future__ import annotations

from datetime import datetime

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, ConfigDict

from server.api.deps import FleetDep, JobWatcherDep, OperatorDep, PreviewsDep, SettingsDep, ThrowServiceDep, ViewerDep
from server.api.responses import errors
from server.api.schemas import Vec3
from server.db.types import utcnow
from server.throws.gate import preview_refusal
from server.throws.preview_schemas import PreviewCreate, PreviewOut

router = APIRouter(prefix="/api/previews", tags=["previews"])


@router.post(
    "",
    response_model=PreviewOut,
    responses=errors(
        (404, "unknown machine"),
        (409, "the server has no file of the machine's policy, or it does not load"),
        (422, "a target the mode cannot serve (the reason)"),
        (429, "the user has their limit of previews queued or running"),
        (500, "the preview job failed"),
        (503, "runtime offline, no machine state, or no worker answered in 3 s"),
    ),
)
async def create_preview(body: PreviewCreate, service: PreviewsDep, settings: SettingsDep, watcher: JobWatcherDep,
                         user: OperatorDep) -> PreviewOut:
    """Preview a throw of ``machine_id`` at ``target`` in ``mode`` from its current joint state.

    ``rollouts`` <= 1 gives the nominal rollout only (fast); more adds the Monte Carlo 1 sigma
    impact ellipse over the release-delay jitter; ``extends`` names the nominal-only preview an
    ellipse completes (its start state and nominal rollout are reused). The twin runs in a
    worker (a ``preview`` job; its id is the preview id); this route awaits it without holding a
    request thread. The console draws it in its own 3D view (POST /api/consoles/{id}/preview).
    """
    rollouts = body.rollouts if body.rollouts is not None else settings.preview_rollouts
    job_id = await run_in_threadpool(service.submit, body.machine_id, body.mode, body.target, rollouts,
                                     user.username, body.extends)
    timeout_s = settings.preview_timeout_s
    job = await watcher.wait(job_id, timeout_s)
    summary = await run_in_threadpool(service.outcome, job, timeout_s)  # domain errors: server.api.errors
    return PreviewOut(**summary)


@router.get("/{preview_id}", response_model=PreviewOut, responses=errors((404, "no such preview, or no longer kept")))
def get_preview(preview_id: str, service: PreviewsDep, _user: ViewerDep) -> PreviewOut:
    return PreviewOut(**service.require(preview_id))


class PreviewCheckIn(BaseModel):
    """The throw the console would send with the preview: machine, mode, target (3,) m."""

    model_config = ConfigDict(extra="forbid")

    machine_id: str
    mode: str
    target: Vec3


class PreviewCheckOut(BaseModel):
    """Whether a throw with this preview would pass the preview gate now (server.throws.gate).

    ``condition``/``reason``: the failed gate condition and its message (None when valid); besides
    server.throws.gate's conditions, ``no_state`` (no MachineState heard) and ``machine_not_ready``
    (the runtime's last RuntimeInfo says it would refuse a throw now, e.g. "no payload loaded"
    between a landing and the next load: a preview made then starts from a pose the machine
    is about to leave); ``age_s``: the preview's age, s; ``max_age_s``: the age at which it goes stale, s."""

    valid: bool
    condition: str | None = None
    reason: str | None = None
    age_s: float | None = None
    max_age_s: float | None = None


@router.post("/{preview_id}/check", response_model=PreviewCheckOut)
def check_preview(preview_id: str, body: PreviewCheckIn, previews: PreviewsDep, fleet: FleetDep,
                  throws: ThrowServiceDep, _user: ViewerDep) -> PreviewCheckOut:
    """Would a throw with this preview pass the gate now? The console asks while a preview is on
    screen, so Throw is enabled only with a valid one. Reads the fleet's latest state and cached
    runtime info only (no query to the machine); the throw itself checks again."""
    summary = previews.get(preview_id)
    limits = throws.gate  # the gate the throw itself passes (GateLimits.from_settings, None when off)
    now = utcnow()
    age = (now - datetime.fromisoformat(summary["created_at"])).total_seconds() if summary else None
    max_age = limits.max_age_s if limits else None
    if summary is None:
        return PreviewCheckOut(valid=False, condition="preview_unknown",
                               reason=f"unknown or expired preview {preview_id!r}: preview again")
    if limits is None:
        return PreviewCheckOut(valid=summary is not None and summary.get("status") == "ok", age_s=age)
    state = fleet.latest_state(body.machine_id)
    if state is None:
        return PreviewCheckOut(valid=False, condition="no_state", reason=f"no state from machine {body.machine_id}",
                               age_s=age, max_age_s=max_age)
    info = fleet.cached_info(body.machine_id)
    if info is not None and not info.ready:
        # judged before the preview itself: a machine that cannot throw now gets no Throw button,
        # whatever its pose (the runtime would refuse; a reload may move it, sim_twin.twin.twin_machine).
        # A throw still running in the last info counts too: the page may ask as soon as the
        # throw's result is in, before the runtime's next info (no payload, about to be reloaded)
        # arrives, and a short swing leaves the machine at the preview's pose
        why = info.not_ready_reason or "not ready"
        return PreviewCheckOut(valid=False, condition="machine_not_ready", reason=f"the machine is not ready ({why})",
                               age_s=age, max_age_s=max_age)
    sha = next((p.sha256 for p in (info.policies if info else []) if p.mode == body.mode), None)
    refusal = preview_refusal(summary, preview_id, body.machine_id, body.mode, list(body.target), list(state.q), sha,
                              now, limits, throws.keep_out_zones)
    if refusal is None:
        return PreviewCheckOut(valid=True, age_s=age, max_age_s=max_age)
    return PreviewCheckOut(valid=False, condition=refusal.condition, reason=refusal.message, age_s=age, max_age_s=max_age)
