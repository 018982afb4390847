"""Users (admin only): list, add, change role / active / password; and the audit log."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import delete, select

from server.accounts.auth import MAX_PASSWORD_LENGTH, MIN_PASSWORD_LENGTH, audit, check_password, create_user, hash_password, verify_password
from server.accounts.auth_routes import user_out
from server.accounts.schemas import AuditOut, UserCreate, UserOut, UserUpdate
from server.api.deps import AdminDep, SessionDep, ViewerDep
from server.api.responses import errors
from server.db.models import AuditEntry, AuthSession, User
from server.errors import Denied, NotFound, Refused

router = APIRouter(prefix="/api", tags=["users"])


@router.get("/users", response_model=list[UserOut])
def list_users(db: SessionDep, _admin: AdminDep) -> list[UserOut]:
    return [user_out(u) for u in db.scalars(select(User).order_by(User.username))]


@router.post("/users", status_code=201, response_model=UserOut, responses=errors((409, "exists"), (422, "a weak password, an unknown role or a malformed name")))
def add_user(body: UserCreate, db: SessionDep, admin: AdminDep) -> UserOut:
    user = create_user(db, body.username, body.password, body.role)  # AuthError: 422, UserExists: 409
    audit(db, admin.username, "user_add", body.username, role=body.role)
    db.commit()
    return user_out(user)


@router.patch("/users/{username}", response_model=UserOut, responses=errors((404, "no such user"), (422, "a weak password, or demoting oneself")))
def update_user(username: str, body: UserUpdate, db: SessionDep, admin: AdminDep) -> UserOut:
    """Change a user's role, deactivate them (ends their sessions) or set a new password."""
    user = db.scalar(select(User).where(User.username == username))
    if user is None:
        raise NotFound(f"no user {username!r}")
    if user.id == admin.id and (body.active is False or (body.role and body.role != "admin")):
        raise Refused("you cannot demote or deactivate yourself")
    changes: dict[str, object] = {}
    if body.role is not None:
        user.role = changes["role"] = body.role
    if body.active is not None:
        user.active = changes["active"] = body.active
    if body.password is not None:
        user.password_hash = hash_password(check_password(body.password))  # AuthError: 422
        changes["password"] = "changed"
    if body.active is False or body.password is not None:
        db.execute(delete(AuthSession).where(AuthSession.user_id == user.id))
    audit(db, admin.username, "user_update", username, **changes)
    db.commit()
    return user_out(user)


class PasswordChange(BaseModel):
    """A user's own password change: the current password, then the new one."""

    model_config = ConfigDict(extra="forbid")

    current_password: Annotated[str, Field(min_length=1, max_length=MAX_PASSWORD_LENGTH)]
    new_password: Annotated[str, Field(min_length=MIN_PASSWORD_LENGTH, max_length=MAX_PASSWORD_LENGTH)]


@router.post("/account/password", status_code=204,
             responses=errors((403, "the current password is wrong"), (422, "the new one is too weak")))
def change_own_password(body: PasswordChange, db: SessionDep, user: ViewerDep) -> None:
    """Change one's own password (any role). Ends every session of the user, this one included:
    log in again with the new password. Audited (``password_change``), failed attempts too."""
    row = db.get(User, user.id)
    if row is None or not verify_password(row.password_hash, body.current_password):
        audit(db, user.username, "password_change", user.username, changed=False, reason="wrong current password")
        db.commit()
        raise Denied("the current password is wrong")
    row.password_hash = hash_password(check_password(body.new_password))  # AuthError: 422
    db.execute(delete(AuthSession).where(AuthSession.user_id == row.id))
    audit(db, user.username, "password_change", user.username, changed=True)
    db.commit()


@router.get("/audit", response_model=list[AuditOut])
def audit_log(db: SessionDep, _admin: AdminDep, action: str | None = None,
              limit: int = Query(100, ge=1, le=1000)) -> list[AuditOut]:
    """The audit log, newest first (optionally one action: throw, abort, promote, rollback, ...)."""
    stmt = select(AuditEntry).order_by(AuditEntry.at.desc(), AuditEntry.id.desc()).limit(limit)
    if action:
        stmt = stmt.where(AuditEntry.action == action)
    return [AuditOut(id=a.id, at=a.at, username=a.username, action=a.action, subject=a.subject,
                     detail=a.detail or {}) for a in db.scalars(stmt)]
