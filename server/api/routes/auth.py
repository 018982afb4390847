"""Log-in, log-out and who am I: POST /api/auth/login, POST /api/auth/logout, GET /api/auth/me."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request, Response

from server.api.account_schemas import LoginIn, LoginOut, UserOut
from server.api.deps import CurrentUser, LoginGuardDep, SessionsDep, SettingsDep, session_token
from server.auth import COOKIE_NAME, AuthError, audit, authenticate, create_session, end_session
from server.login_guard import LoginBusy

router = APIRouter(prefix="/api/auth", tags=["auth"])


def user_out(user) -> UserOut:
    return UserOut(username=user.username, role=user.role, active=user.active, created_at=user.created_at)


def _check_and_start_session(sessions, username: str, password: str, ttl_s: float):
    """In the log-in pool: check the credentials, start a session. Returns (user, token, row)."""
    with sessions.begin() as db:
        user = authenticate(db, username, password)
        token, row = create_session(db, user, ttl_s)
        audit(db, user.username, "login")
    return user, token, row


def served_over_https(request: Request) -> bool:
    """True if the client reached us over TLS: scheme https (uvicorn applies a trusted proxy's
    ``X-Forwarded-Proto``), or ``X-Forwarded-Proto: https`` itself."""
    forwarded = request.headers.get("x-forwarded-proto", "").split(",")[0].strip().lower()
    return request.url.scheme == "https" or forwarded == "https"


def _too_many(detail: str, retry_after_s: int) -> HTTPException:
    return HTTPException(429, detail, headers={"Retry-After": str(retry_after_s)})


@router.post("/login", response_model=LoginOut, responses={
    401: {"description": "bad credentials"},
    429: {"description": "too many failed log-ins for this user or address, or too many log-ins in "
                         "progress; the Retry-After header says in how many seconds to try again"}})
async def login(body: LoginIn, request: Request, response: Response, settings: SettingsDep, guard: LoginGuardDep,
                sessions: SessionsDep) -> LoginOut:
    """Check the credentials, start a session: cookie ``slinger_session`` (Secure when served over
    HTTPS) and the token in the body (send it as ``Authorization: Bearer <token>`` from scripts).

    Repeated failures hold the user name at the client address, the address, and (much later,
    sparing addresses the user logged in from) the user name for a while (429 with Retry-After);
    the password check runs in a small bounded pool (server.login_guard). The client address is
    the peer's unless the peer is a configured trusted proxy (``Settings.trusted_proxies``)."""
    address = request.client.host if request.client else "unknown"
    wait_s = guard.retry_after_s(body.username, address)
    if wait_s is not None:
        raise _too_many(f"too many failed log-ins: try again in {wait_s} s", wait_s)
    try:
        user, token, row = await guard.run(_check_and_start_session, sessions,
                                           body.username, body.password, settings.session_ttl_s)
    except LoginBusy as e:
        raise _too_many(str(e), 1) from e
    except AuthError as e:
        guard.failed(body.username, address)
        raise HTTPException(401, str(e)) from e
    guard.succeeded(body.username, address)
    response.set_cookie(COOKIE_NAME, token, max_age=int(settings.session_ttl_s), httponly=True, samesite="lax",
                        secure=settings.cookie_secure or served_over_https(request), path="/")
    return LoginOut(token=token, expires_at=row.expires_at, user=user_out(user))


@router.post("/logout", status_code=204)
def logout(request: Request, response: Response, sessions: SessionsDep) -> Response:
    """End the current session (no error without one)."""
    with sessions.begin() as db:
        end_session(db, session_token(request))
    response.delete_cookie(COOKIE_NAME, path="/")
    response.status_code = 204
    return response


@router.get("/me", response_model=UserOut, responses={401: {"description": "not logged in"}})
def me(user: CurrentUser) -> UserOut:
    return user_out(user)
