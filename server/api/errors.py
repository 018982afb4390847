"""The one mapping from domain errors (server.errors) to HTTP answers."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import JSONResponse

from server.errors import (
    Conflict,
    Denied,
    DomainError,
    Failed,
    Limited,
    NotFound,
    Refused,
    TooLarge,
    Unauthenticated,
    Unavailable,
)

STATUS: dict[type[DomainError], int] = {Unauthenticated: 401, Denied: 403, NotFound: 404, Refused: 422,
                                        Conflict: 409, TooLarge: 413, Limited: 429, Unavailable: 503, Failed: 500}
RETRY_AFTER_S: dict[type[DomainError], int] = {Limited: 1, Unavailable: 5}
"""Default ``Retry-After`` (s) of the kinds that are worth retrying (an error's own
``retry_after_s`` wins)."""


def status_of(error: DomainError) -> int:
    """The HTTP status of a domain error (its nearest mapped class; unmapped: 500)."""
    for cls in type(error).__mro__:
        if cls in STATUS:
            return STATUS[cls]
    return 500


async def domain_error(_request: Request, exc: Exception) -> JSONResponse:
    """``{"detail": sentence}`` (plus ``condition``) with the mapped status; the
    ``X-Refused-Condition`` header names the condition; ``Retry-After`` for Limited/Unavailable;
    ``WWW-Authenticate: Bearer`` for Unauthenticated (RFC 9110 15.5.2). Registered for
    DomainError (Starlette's handler type takes any exception).

    Raises:
        TypeError: ``exc`` is not a DomainError (a wrong registration).
    """
    if not isinstance(exc, DomainError):
        raise TypeError(f"domain_error handles DomainError, not {type(exc).__name__}")
    headers = {}
    content: dict = {"detail": exc.detail}
    if exc.condition:
        headers["X-Refused-Condition"] = exc.condition
        content["condition"] = exc.condition
    for cls, default_s in RETRY_AFTER_S.items():
        if isinstance(exc, cls):
            headers["Retry-After"] = str(exc.retry_after_s if exc.retry_after_s is not None else default_s)
    if isinstance(exc, Unauthenticated):
        headers["WWW-Authenticate"] = "Bearer"
    return JSONResponse(status_code=status_of(exc), content=content, headers=headers or None)
