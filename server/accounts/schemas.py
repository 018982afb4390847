"""API schemas of accounts and the audit log (models: server.db.models.User, AuditEntry)."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from server.accounts.auth import MAX_PASSWORD_LENGTH, MIN_PASSWORD_LENGTH

Role = Literal["viewer", "operator", "admin"]


class LoginIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    username: str = Field(min_length=1, max_length=64)
    password: str = Field(min_length=1, max_length=MAX_PASSWORD_LENGTH)


class UserOut(BaseModel):
    username: str
    role: Role
    active: bool
    created_at: datetime


class MeOut(UserOut):
    """GET /api/auth/me: the user, and when the caller's log-in ends (UTC; the E-STOP still
    works for server.accounts.auth.STOP_GRACE_S after it)."""

    session_expires_at: datetime


class LoginOut(BaseModel):
    """The session token (also set as the ``slinger_session`` cookie) and when it expires."""

    token: str
    expires_at: datetime
    user: UserOut


class UserCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    username: str = Field(min_length=1, max_length=64)
    password: str = Field(min_length=MIN_PASSWORD_LENGTH, max_length=MAX_PASSWORD_LENGTH)
    role: Role = "viewer"


class UserUpdate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    role: Role | None = None
    active: bool | None = None
    password: str | None = Field(default=None, min_length=MIN_PASSWORD_LENGTH, max_length=MAX_PASSWORD_LENGTH)


class AuditOut(BaseModel):
    id: int
    at: datetime
    username: str
    action: str
    subject: str | None
    detail: dict
