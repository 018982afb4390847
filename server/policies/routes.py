"""Policy versions: list, upload (admin), promote to machines (admin), roll back (admin),
deployments, compare (twin evaluation and logged throws per target distance)."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from fastapi import APIRouter, File, Form, Path, Query, UploadFile
from pydantic import BaseModel, Field
from sqlalchemy import select

from runtime.observation import HISTORY_STEPS, MAX_HISTORY_STEPS
from server.accounts.auth import record_audit
from server.analysis.accuracy import accuracy
from server.api.deps import AdminDep, PoliciesDep, SessionDep, SessionsDep, ViewerDep, authorised_or_audited
from server.api.report_schemas import PolicyComparisonOut, RollbackTargetOut
from server.api.responses import errors
from server.api.schemas import COORD_LIMIT_M, MAX_DB_ID, DbId
from server.db.models import PolicyDeployment, PolicyVersion
from server.errors import DomainError, found
from server.policies.versions import expire_stale_offers
from server.throws.history import ThrowFilter

router = APIRouter(prefix="/api/policies", tags=["policies"])


class PolicyOut(BaseModel):
    id: int
    name: str
    mode: str
    sha256: str
    target_range_m: list[float] | None
    created_at: datetime
    uploaded_by: str | None
    notes: str | None
    has_file: bool
    evaluation_status: str | None
    metrics: dict | None


class DeploymentOut(BaseModel):
    id: int
    machine_id: str
    mode: str
    policy_version_id: int
    policy_version: str
    status: str
    reason: str | None
    requested_by: str | None
    requested_at: datetime
    confirmed_at: datetime | None


class PromoteIn(BaseModel):
    machine_ids: list[str] = Field(min_length=1, max_length=100)


class RollbackIn(BaseModel):
    machine_id: str
    mode: Literal["2d", "3d"]


def policy_out(p: PolicyVersion) -> PolicyOut:
    return PolicyOut(id=p.id, name=p.name, mode=p.mode, sha256=p.sha256,
                     target_range_m=(p.manifest or {}).get("target_range_m"), created_at=p.created_at,
                     uploaded_by=p.uploaded_by, notes=p.notes, has_file=bool(p.onnx_path),
                     evaluation_status=p.evaluation_status, metrics=p.metrics)


def deployment_out(d: PolicyDeployment, name: str) -> DeploymentOut:
    return DeploymentOut(id=d.id, machine_id=d.machine_id, mode=d.mode, policy_version_id=d.policy_version_id,
                         policy_version=name, status=d.status, reason=d.reason, requested_by=d.requested_by,
                         requested_at=d.requested_at, confirmed_at=d.confirmed_at)


@router.get("", response_model=list[PolicyOut])
def list_policies(db: SessionDep, _user: ViewerDep) -> list[PolicyOut]:
    return [policy_out(p) for p in db.scalars(select(PolicyVersion).order_by(PolicyVersion.id.desc()))]


@router.post("", status_code=201, response_model=PolicyOut,
             responses=errors((409, "already a version"), (422, "rejected, with the reason")))
async def upload_policy(
    policies: PoliciesDep, user: AdminDep,
    file: UploadFile = File(..., description="the ONNX file (obs -> actions)"),
    mode: Literal["2d", "3d"] = Form(...),
    name: str = Form(..., min_length=1, max_length=128, pattern=r"^[A-Za-z0-9_.-]+$"),
    target_min_m: float = Form(5.0, gt=0, le=COORD_LIMIT_M, allow_inf_nan=False),
    target_max_m: float = Form(10.7, gt=0, le=COORD_LIMIT_M, allow_inf_nan=False),
    notes: str | None = Form(None, max_length=2000),
    history_steps: int = Form(HISTORY_STEPS, ge=1, le=MAX_HISTORY_STEPS,
                              description="control steps of joint history the policy reads (runtime.observation; 4, the paper's)"),
) -> PolicyOut:
    """Upload a policy version: the manifest is generated from the mode and metadata (its
    observation layout from ``history_steps``); the file is refused with the reason if it is not
    ONNX, has the wrong input/output shapes for the mode and history or produces non-finite
    actions. An accepted version is evaluated in the twin in the background
    (``evaluation_status`` pending -> running -> done, ``metrics``)."""
    data = await file.read()
    from starlette.concurrency import run_in_threadpool

    row = await run_in_threadpool(policies.upload, data, mode, name,
                                  (target_min_m, target_max_m), notes, user.username, history_steps=history_steps)
    return policy_out(row)


@router.get("/deployments", response_model=list[DeploymentOut])
def deployments(db: SessionDep, _user: ViewerDep, machine_id: str | None = None,
                limit: int = Query(50, ge=1, le=500)) -> list[DeploymentOut]:
    """Promotions and rollbacks, newest first (an offer the runtime never confirmed within
    server.policies.versions.OFFER_TIMEOUT_S is shown failed, with the reason)."""
    if expire_stale_offers(db):
        db.commit()
    stmt = select(PolicyDeployment, PolicyVersion.name).join(PolicyVersion).order_by(
        PolicyDeployment.id.desc()).limit(limit)
    if machine_id:
        stmt = stmt.where(PolicyDeployment.machine_id == machine_id)
    return [deployment_out(d, n) for d, n in db.execute(stmt)]


@router.get("/compare", response_model=list[PolicyComparisonOut], responses=errors((404, "no such policy version")))
def compare(db: SessionDep, _user: ViewerDep, ids: list[DbId] = Query(..., min_length=1, max_length=10)) -> list[dict]:
    """Per version: the twin evaluation per target distance and the logged throws' accuracy."""
    out = []
    for pid in ids:
        p = found(db.get(PolicyVersion, pid), f"no policy version {pid}")
        logged = accuracy(db, ThrowFilter(mode=p.mode, policy_sha256=p.sha256))
        out.append({"id": p.id, "name": p.name, "mode": p.mode, "sha256": p.sha256,
                    "evaluation_status": p.evaluation_status,
                    "twin": (p.metrics or {}).get("targets", []), "logged": logged})
    return out


@router.get("/rollback-targets", response_model=dict[Literal["2d", "3d"], RollbackTargetOut | None])
def rollback_targets(policies: PoliciesDep, _user: ViewerDep,
                     machine_id: str = Query(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_-]+$")) -> dict:
    """Per mode, the version a rollback of ``machine_id`` would go back to ({"id", "name"}), or
    None: the Fleet page offers a rollback only where there is one."""
    out = {}
    for mode in ("2d", "3d"):
        prev = policies.rollback_target(machine_id, mode)
        out[mode] = {"id": prev.id, "name": prev.name} if prev is not None else None
    return out


@router.get("/{policy_id}", response_model=PolicyOut, responses=errors((404, "no such policy version")))
def get_policy(db: SessionDep, _user: ViewerDep, policy_id: int = Path(ge=1, le=MAX_DB_ID)) -> PolicyOut:
    return policy_out(found(db.get(PolicyVersion, policy_id), f"no policy version {policy_id}"))


@router.post("/{policy_id}/evaluate", response_model=PolicyOut, responses=errors(
    (404, "no such version"), (409, "its evaluation runs")))
def evaluate(policies: PoliciesDep, user: AdminDep, policy_id: int = Path(ge=1, le=MAX_DB_ID)) -> PolicyOut:
    """Evaluate a stored version in the twin (again): any version, deployed ones included."""
    return policy_out(policies.evaluate(policy_id, user.username))


@router.post("/{policy_id}/promote", response_model=list[DeploymentOut], responses=errors(
    (404, "no such policy version"), (409, "no file of the version, or it has not passed its validation")))
def promote(body: PromoteIn, policies: PoliciesDep, sessions: SessionsDep, user: AdminDep,
            policy_id: int = Path(ge=1, le=MAX_DB_ID)) -> list[DeploymentOut]:
    """Offer the version to the machines; each runtime fetches it, checks it, loads it between
    throws and confirms (the deployment turns ``active``; GET /api/machines shows it)."""
    deps = policies.promote(policy_id, body.machine_ids, user.username)
    with sessions() as db:
        name = db.get_one(PolicyVersion, policy_id).name
    return [deployment_out(d, name) for d in deps]


@router.post("/rollback", response_model=DeploymentOut, responses=errors(
    (403, "needs the admin role"), (409, "nothing to roll back to")))
def rollback(body: RollbackIn, policies: PoliciesDep, sessions: SessionsDep, user: ViewerDep) -> DeploymentOut:
    """Go back to the version the machine ran before its last promotion for that mode (admins).
    Every attempt is audited: done ones as ``rollback``, refused ones (a role below admin
    included) as ``rollback_refused`` with the reason."""
    authorised_or_audited(user, "admin", lambda reason: record_audit(
        sessions, user.username, "rollback_refused", body.machine_id[:64], mode=body.mode, reason=reason))
    try:
        d = policies.rollback(body.machine_id, body.mode, user.username)
    except DomainError as e:  # a refused attempt is audited too (a done one by server.policies.versions)
        record_audit(sessions, user.username, "rollback_refused", body.machine_id[:64], mode=body.mode, reason=e.detail)
        raise
    with sessions() as db:
        name = db.get_one(PolicyVersion, d.policy_version_id).name
    return deployment_out(d, name)
