"""The one mapping from domain errors (server.errors) to HTTP answers."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import JSONResponse

from server.errors import Conflict, DomainError, Failed, Limited, NotFound, Refused, Unavailable

STATUS: dict[type[DomainError], int] = {NotFound: 404, Refused: 422, Conflict: 409, Limited: 429,
                                        Unavailable: 503, Failed: 500}


def status_of(error: DomainError) -> int:
    """The HTTP status of a domain error (its nearest mapped class; unmapped: 500)."""
    for cls in type(error).__mro__:
        if cls in STATUS:
            return STATUS[cls]
    return 500


async def domain_error(_request: Request, exc: DomainError) -> JSONResponse:
    """``{"detail": sentence}`` (plus ``condition``) with the mapped status; the
    ``X-Refused-Condition`` header names the condition; ``Retry-After`` for Limited/Unavailable."""
    headers = {}
    content: dict = {"detail": exc.detail}
    if exc.condition:
        headers["X-Refused-Condition"] = exc.condition
        content["condition"] = exc.condition
    if isinstance(exc, (Limited, Unavailable)):
        headers["Retry-After"] = "1" if isinstance(exc, Limited) else "5"
    return JSONResponse(status_code=status_of(exc), content=content, headers=headers or None)
