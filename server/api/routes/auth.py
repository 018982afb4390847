"""Log-in, log-out and who am I: POST /api/auth/login, POST /api/auth/logout, GET /api/auth/me."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request, Response

from server.api.account_schemas import LoginIn, LoginOut, UserOut
from server.api.deps import CurrentUser, SettingsDep, session_token
from server.auth import COOKIE_NAME, AuthError, audit, authenticate, create_session, end_session

router = APIRouter(prefix="/api/auth", tags=["auth"])


def user_out(user) -> UserOut:
    return UserOut(username=user.username, role=user.role, active=user.active, created_at=user.created_at)


@router.post("/login", response_model=LoginOut, responses={401: {"description": "bad credentials"}})
def login(body: LoginIn, request: Request, response: Response, settings: SettingsDep) -> LoginOut:
    """Check the credentials, start a session: cookie ``slinger_session`` and the token in the body
    (send it as ``Authorization: Bearer <token>`` from scripts)."""
    sessions = request.app.state.sessions
    try:
        with sessions.begin() as db:
            user = authenticate(db, body.username, body.password)
            token, row = create_session(db, user, settings.session_ttl_s)
            audit(db, user.username, "login")
    except AuthError as e:
        raise HTTPException(401, str(e)) from e
    response.set_cookie(COOKIE_NAME, token, max_age=int(settings.session_ttl_s), httponly=True,
                        samesite="lax", secure=settings.cookie_secure, path="/")
    return LoginOut(token=token, expires_at=row.expires_at, user=user_out(user))


@router.post("/logout", status_code=204)
def logout(request: Request, response: Response) -> Response:
    """End the current session (no error without one)."""
    with request.app.state.sessions.begin() as db:
        end_session(db, session_token(request))
    response.delete_cookie(COOKIE_NAME, path="/")
    response.status_code = 204
    return response


@router.get("/me", response_model=UserOut, responses={401: {"description": "not logged in"}})
def me(user: CurrentUser) -> UserOut:
    return user_out(user)
