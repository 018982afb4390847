"""Log-in, log-out and who am I: POST /api/auth/login, POST /api/auth/logout, GET /api/auth/me."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from server.accounts.auth import (
    COOKIE_NAME,
    STOP_GRACE_S,
    BadCredentials,
    audit,
    authenticate,
    create_session,
    end_session,
    record_audit,
    session_for_token,
)
from server.accounts.login_guard import LoginBusy, LoginGuard
from server.accounts.schemas import LoginIn, LoginOut, MeOut, UserOut
from server.api.deps import LoginGuardDep, SessionsDep, SettingsDep, session_token
from server.api.responses import errors
from server.errors import Limited, Unauthenticated

router = APIRouter(prefix="/api/auth", tags=["auth"])


def user_out(user) -> UserOut:
    return UserOut(username=user.username, role=user.role, active=user.active, created_at=user.created_at)


def _check_and_start_session(sessions, username: str, password: str, ttl_s: float, address: str):
    """In the log-in pool: check the credentials, start a session. Returns (user, token, row).
    A failed check is audited (``login_failed``: the user name as typed, the address, the
    cause; never the password) in its own transaction, then re-raised."""
    try:
        with sessions.begin() as db:
            user = authenticate(db, username, password)
            token, row = create_session(db, user, ttl_s)
            audit(db, user.username, "login", address=address)
    except BadCredentials as e:
        record_audit(sessions, username, "login_failed", username, address=address, reason=e.reason)
        raise
    return user, token, row


def _audit_refusal(guard: LoginGuard, sessions, username: str, address: str, reason: str) -> None:
    """Audit a log-in refused before its check (``login_failed``), on the guard's audit thread."""
    def write(unrecorded: int) -> None:
        extra = {"unrecorded_before": unrecorded} if unrecorded else {}
        record_audit(sessions, username, "login_failed", username, address=address, reason=reason, **extra)

    guard.record_later(write)


def served_over_https(request: Request) -> bool:
    """True if the client reached us over TLS: scheme https (uvicorn applies a trusted proxy's
    ``X-Forwarded-Proto``), or ``X-Forwarded-Proto: https`` itself."""
    forwarded = request.headers.get("x-forwarded-proto", "").split(",")[0].strip().lower()
    return request.url.scheme == "https" or forwarded == "https"


@router.post("/login", response_model=LoginOut, responses=errors(
    (401, "bad credentials"),
    (429, "too many failed log-ins for this user or address, or too many log-ins in progress; the Retry-After "
          "header says in how many seconds to try again"), 503))
async def login(body: LoginIn, request: Request, response: Response, settings: SettingsDep, guard: LoginGuardDep,
                sessions: SessionsDep) -> LoginOut:
    """Check the credentials, start a session: cookie ``slinger_session`` (Secure when served over
    HTTPS) and the token in the body (send it as ``Authorization: Bearer <token>`` from scripts).

    Repeated failures hold the user name at the client address, the address, and (much later,
    sparing addresses the user logged in from) the user name for a while (429 with Retry-After);
    the password check runs in a small bounded pool (server.accounts.login_guard). The client address is
    the peer's unless the peer is a configured trusted proxy (``Settings.trusted_proxies``).
    Every failed or refused log-in is one ``login_failed`` audit entry (user name as typed,
    address, reason; never the password)."""
    address = request.client.host if request.client else "unknown"
    wait_s = guard.retry_after_s(body.username, address)
    if wait_s is not None:
        _audit_refusal(guard, sessions, body.username, address, f"held after repeated failures ({wait_s} s left)")
        raise Limited(f"too many failed log-ins: try again in {wait_s} s", retry_after_s=wait_s)
    try:
        user, token, row = await guard.run(_check_and_start_session, sessions,
                                           body.username, body.password, settings.session_ttl_s, address)
    except LoginBusy:  # a Limited: 429
        _audit_refusal(guard, sessions, body.username, address, "too many log-ins in progress")
        raise
    except BadCredentials:  # 401
        guard.failed(body.username, address)
        raise
    guard.succeeded(body.username, address)
    # the cookie outlives the session by the E-STOP's grace: a console left open past its log-in keeps its stop
    response.set_cookie(COOKIE_NAME, token, max_age=int(settings.session_ttl_s + STOP_GRACE_S), httponly=True, samesite="lax",
                        secure=settings.cookie_secure or served_over_https(request), path="/")
    return LoginOut(token=token, expires_at=row.expires_at, user=user_out(user))


@router.post("/logout", status_code=204, responses=errors(503))
def logout(request: Request, response: Response, sessions: SessionsDep) -> Response:
    """End the current session (no error without one)."""
    with sessions.begin() as db:
        end_session(db, session_token(request))
    response.delete_cookie(COOKIE_NAME, path="/")
    response.status_code = 204
    return response


@router.get("/me", response_model=MeOut, responses=errors((401, "not logged in")))
def me(request: Request, sessions: SessionsDep) -> MeOut:
    """The logged-in user and when the session's log-in ends (the console warns before it)."""
    with sessions() as db:
        found = session_for_token(db, session_token(request))
    if found is None:
        raise Unauthenticated("log in first (session missing or expired)")
    user, expires = found
    return MeOut(**user_out(user).model_dump(), session_expires_at=expires)
