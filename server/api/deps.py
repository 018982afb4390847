"""Dependencies with aliases so routes read like prose (``db: SessionDep``)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from sqlalchemy.orm import Session

from server.auth import COOKIE_NAME, role_at_least, user_for_token
from server.config import Settings
from server.db.models import User
from server.fleet import Fleet
from server.scene import ConsoleScene
from server.throws import ThrowService


def get_db(request: Request) -> Iterator[Session]:
    with request.app.state.sessions() as session:
        yield session


def get_fleet(request: Request) -> Fleet:
    return request.app.state.fleet


def get_throw_service(request: Request) -> ThrowService:
    return request.app.state.throws


def get_scene(request: Request) -> ConsoleScene | None:
    return request.app.state.scene


def get_app_settings(request: Request) -> Settings:
    return request.app.state.settings


SessionDep = Annotated[Session, Depends(get_db)]
FleetDep = Annotated[Fleet, Depends(get_fleet)]
ThrowServiceDep = Annotated[ThrowService, Depends(get_throw_service)]
SceneDep = Annotated[ConsoleScene | None, Depends(get_scene)]
SettingsDep = Annotated[Settings, Depends(get_app_settings)]


def session_token(request: Request) -> str | None:
    """The session token: ``Authorization: Bearer <token>`` or the session cookie."""
    header = request.headers.get("authorization", "")
    if header.lower().startswith("bearer "):
        return header[7:].strip() or None
    return request.cookies.get(COOKIE_NAME)


def get_current_user(request: Request) -> User:
    """The logged-in user; 401 without a valid, unexpired session."""
    with request.app.state.sessions() as db:
        user = user_for_token(db, session_token(request))
    if user is None:
        raise HTTPException(401, "log in first (session missing or expired)",
                            headers={"WWW-Authenticate": "Bearer"})
    return user


def require_role(role: str):
    """A dependency: the current user, 403 unless their role is at least ``role``."""

    def check(user: Annotated[User, Depends(get_current_user)]) -> User:
        if not role_at_least(user.role, role):
            raise HTTPException(403, f"needs the {role} role (you are {user.role})")
        return user

    return check


CurrentUser = Annotated[User, Depends(get_current_user)]
ViewerDep = Annotated[User, Depends(require_role("viewer"))]
OperatorDep = Annotated[User, Depends(require_role("operator"))]
AdminDep = Annotated[User, Depends(require_role("admin"))]
