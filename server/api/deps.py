"""Typed dependencies, so routes read like prose (``db: SessionDep``, ``fleet: FleetDep``).

The services are built once at start-up from the settings (:func:`server.app.create_app`'s
lifespan) and kept on the application; this module is the one place that reads them from there:
routes take them as parameters of the types below and never read ``request.app.state``. The
getters are ``async`` so they run on the event loop, never waiting for a request thread (the
E-STOP route relies on that).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterator
from datetime import datetime
from typing import Annotated, TypeVar

from fastapi import Depends, Request
from sqlalchemy.orm import Session, sessionmaker

from server.accounts.auth import (
    COOKIE_NAME,
    STOP_GRACE_S,
    AuditBacklog,
    SessionMirror,
    SessionUser,
    role_at_least,
    session_for_token,
    user_for_token,
)
from server.accounts.login_guard import LoginGuard
from server.analysis.adaptation import AdaptationRuns
from server.analysis.diagnosis import DiagnosisRuns
from server.analysis.drift import DriftWatch
from server.config import Settings
from server.console.alarms import AlarmService
from server.console.live import LiveHub
from server.console.scene import ConsoleScene
from server.db.models import User
from server.db.types import utcnow
from server.errors import Denied, Unauthenticated
from server.fleet.link import Fleet
from server.fleet.results import ResultStore
from server.jobs import JobQueue
from server.jobs.watch import JobWatcher
from server.policies.versions import PolicyService
from server.site.storage import StorageMonitor
from server.throws.previews import PreviewService
from server.throws.service import ThrowService


def get_db(request: Request) -> Iterator[Session]:
    with request.app.state.sessions() as session:
        yield session


async def get_sessions(request: Request) -> sessionmaker[Session]:
    """The session factory (for work that opens its own sessions, e.g. after the reply)."""
    return request.app.state.sessions


async def get_fleet(request: Request) -> Fleet:
    return request.app.state.fleet


async def get_throw_service(request: Request) -> ThrowService:
    return request.app.state.throws


async def get_scene(request: Request) -> ConsoleScene | None:
    return request.app.state.scene


async def get_app_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_live(request: Request) -> LiveHub | None:
    """The live push hub (None before the lifespan built it)."""
    return getattr(request.app.state, "live", None)


async def get_jobs(request: Request) -> JobQueue:
    return request.app.state.jobs


async def get_job_watcher(request: Request) -> JobWatcher:
    return request.app.state.job_watcher


async def get_previews(request: Request) -> PreviewService:
    return request.app.state.previews


async def get_policies(request: Request) -> PolicyService:
    return request.app.state.policies


async def get_store(request: Request) -> ResultStore:
    return request.app.state.store


async def get_diagnosis_runs(request: Request) -> DiagnosisRuns:
    return request.app.state.diagnosis_runs


async def get_adaptation_runs(request: Request) -> AdaptationRuns:
    return request.app.state.adaptation_runs


async def get_login_guard(request: Request) -> LoginGuard:
    return request.app.state.login_guard


async def get_storage(request: Request) -> StorageMonitor:
    return request.app.state.storage


async def get_drift(request: Request) -> DriftWatch:
    return request.app.state.drift


async def get_alarms(request: Request) -> AlarmService:
    return request.app.state.alarms


async def get_audit_backlog(request: Request) -> AuditBacklog:
    return request.app.state.audit_backlog


SessionDep = Annotated[Session, Depends(get_db)]
SessionsDep = Annotated[sessionmaker[Session], Depends(get_sessions)]
FleetDep = Annotated[Fleet, Depends(get_fleet)]
ThrowServiceDep = Annotated[ThrowService, Depends(get_throw_service)]
SceneDep = Annotated[ConsoleScene | None, Depends(get_scene)]
SettingsDep = Annotated[Settings, Depends(get_app_settings)]
LiveDep = Annotated[LiveHub | None, Depends(get_live)]
JobsDep = Annotated[JobQueue, Depends(get_jobs)]
JobWatcherDep = Annotated[JobWatcher, Depends(get_job_watcher)]
PreviewsDep = Annotated[PreviewService, Depends(get_previews)]
PoliciesDep = Annotated[PolicyService, Depends(get_policies)]
StoreDep = Annotated[ResultStore, Depends(get_store)]
DiagnosisRunsDep = Annotated[DiagnosisRuns, Depends(get_diagnosis_runs)]
AdaptationRunsDep = Annotated[AdaptationRuns, Depends(get_adaptation_runs)]
LoginGuardDep = Annotated[LoginGuard, Depends(get_login_guard)]
StorageDep = Annotated[StorageMonitor, Depends(get_storage)]
DriftDep = Annotated[DriftWatch, Depends(get_drift)]
AuditBacklogDep = Annotated[AuditBacklog, Depends(get_audit_backlog)]
AlarmsDep = Annotated[AlarmService, Depends(get_alarms)]


def session_token(request: Request) -> str | None:
    """The session token: ``Authorization: Bearer <token>`` or the session cookie."""
    header = request.headers.get("authorization", "")
    if header.lower().startswith("bearer "):
        return header[7:].strip() or None
    return request.cookies.get(COOKIE_NAME)


AnyUser = TypeVar("AnyUser", bound=User | SessionUser)


def authorised(user: AnyUser | None, role: str = "viewer") -> AnyUser:
    """``user`` if it is logged in with at least ``role``.

    Raises:
        Unauthenticated: ``user`` is None (no valid, unexpired session): 401.
        Denied: the user's role is below ``role``: 403.
    """
    if user is None:
        raise Unauthenticated("log in first (session missing or expired)")
    if not role_at_least(user.role, role):
        raise Denied(f"needs the {role} role (you are {user.role})")
    return user


def authorised_or_audited(user: User, role: str, record: Callable[[str], None], action: str = "") -> User:
    """:func:`authorised` for a route that audits its refusals: a role below ``role`` is passed to
    ``record(reason)`` (the route's audit entry) before Denied is raised.

    Args:
        action: what was asked, in words, to begin the reason with (e.g. "acknowledging a drift
            alert"); "" for the plain "needs the <role> role (you are <role>)".

    Raises:
        Denied: the user's role is below ``role``: 403, the reason as its detail.
    """
    try:
        return authorised(user, role)
    except Denied as e:
        reason = f"{action} {e.detail}" if action else e.detail
        record(reason)
        raise Denied(reason) from None


def get_current_user(request: Request) -> User:
    """The logged-in user; Unauthenticated (401) without a valid, unexpired session."""
    with request.app.state.sessions() as db:
        return authorised(user_for_token(db, session_token(request)))


def user_from_memory(request: Request, role: str = "viewer") -> User | SessionUser:
    """The logged-in user of ``request`` with at least ``role``, from the in-memory session
    mirror (server.accounts.auth.SessionMirror: no storage touched); only a token the mirror does not hold
    is looked up in the database (a session of another process since the last refresh, or an
    invalid one). Used by the machine list and the deliberate commands that must answer during
    storage faults (the E-STOP: :func:`stopper_from_memory`).

    Raises:
        Unauthenticated (401), Denied (403): as :func:`authorised`.
        StorageFault: the token is not in the mirror and the database cannot be read (503).
    """
    found: User | SessionUser | None = _session_from_memory(request, 0.0)[0]
    return authorised(found, role)


async def stopper_from_memory(request: Request) -> tuple[User | SessionUser, datetime | None]:
    """The operator who presses an E-STOP, as :func:`user_from_memory`, but a session whose log-in
    expired less than server.accounts.auth.STOP_GRACE_S ago still counts (for the stop only: a
    console left open past its log-in keeps its E-STOP; docs/safety.md, row S13). The mirror
    answers without I/O; a token it does not hold (a logged-out console, a stranger) is looked up
    in the database in a worker thread, so that the lookup (up to the busy timeout of a locked
    database) never holds the event loop that serves every other stop (docs/safety.md, row S15).

    Returns:
        (the user, when the session's log-in expired (UTC) if it has, else None).

    Raises:
        Unauthenticated (401), Denied (403): no such session (logged out, account disabled or
            deleted, expired longer ago), or a role below operator.
        StorageFault: the token is not in the mirror and the database cannot be read (503).
    """
    token = session_token(request)
    held = _session_held(request, token, STOP_GRACE_S)
    found, expires = held if held is not None else await asyncio.to_thread(_session_from_storage, request, token, STOP_GRACE_S)
    user: User | SessionUser = authorised(found, "operator")
    return user, (expires if expires is not None and expires <= utcnow() else None)


def _session_from_memory(request: Request, grace_s: float) -> tuple[User | SessionUser | None, datetime | None]:
    """(user, session expiry) of the request's token with ``grace_s`` (see :func:`user_from_memory`), or (None, None)."""
    token = session_token(request)
    held = _session_held(request, token, grace_s)
    return held if held is not None else _session_from_storage(request, token, grace_s)


def _session_held(request: Request, token: str | None, grace_s: float) -> tuple[SessionUser, datetime] | None:
    """The session mirror's (user, expiry) of ``token`` with ``grace_s``; None if it does not hold it. No I/O."""
    mirror: SessionMirror | None = getattr(request.app.state, "session_mirror", None)
    return mirror.session(token, grace_s) if mirror is not None else None


def _session_from_storage(request: Request, token: str | None, grace_s: float) -> tuple[User | SessionUser | None, datetime | None]:
    """A token the mirror does not hold, from the database (dropped from the mirror if invalid)."""
    with request.app.state.sessions() as db:
        found = session_for_token(db, token, grace_s)
    if found is None:
        mirror: SessionMirror | None = getattr(request.app.state, "session_mirror", None)
        if mirror is not None:
            mirror.drop(token)
        return None, None
    return found


def require_role(role: str):
    """A dependency: the current user, Denied (403) unless their role is at least ``role``."""

    def check(user: Annotated[User, Depends(get_current_user)]) -> User:
        return authorised(user, role)

    return check


CurrentUser = Annotated[User, Depends(get_current_user)]
ViewerDep = Annotated[User, Depends(require_role("viewer"))]
OperatorDep = Annotated[User, Depends(require_role("operator"))]
AdminDep = Annotated[User, Depends(require_role("admin"))]
