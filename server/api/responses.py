"""OpenAPI documentation of the error answers: :func:`errors` builds every route's ``responses=``,
:func:`document_errors` adds the answers that do not depend on the route's own code.

Every error body is ``{"detail": sentence}`` (server.api.errors, server.site.storage), plus
``condition`` when the error names one (also in the ``X-Refused-Condition`` header); a 422 of a
malformed request adds ``fields`` (server.app's validation handler). The schemas:
``Problem`` (server.api.schemas) and ``HTTPValidationError`` (:data:`VALIDATION_ERROR_SCHEMA`).

What :func:`document_errors` adds to every operation (answered outside the route's code):

* 401 on routes that need a session, 403 on those that need the operator or admin role (found
  from their dependencies: server.api.deps.get_current_user / require_role);
* 503 on routes that need a session (the session is read from storage: a storage fault answers
  503 with its condition, server.site.storage);
* 400 (a body that does not parse) and 413 (a body over its limit, server.api.web_guard) on routes
  that take a body.
"""

from __future__ import annotations

from typing import Any

from server.api.schemas import Problem

DESCRIPTIONS: dict[int, str] = {
    401: "log in first (session missing or expired), or bad credentials",
    403: "the user's role or ownership does not allow it",
    404: "not found",
    409: "the current state does not allow it",
    413: "the body is larger than its limit",
    422: "invalid request, or refused as asked (the X-Refused-Condition header names why, when set)",
    429: "over a limit; the Retry-After header says in how many seconds to try again",
    500: "the work itself failed",
    503: "something it needs does not answer now (runtime, worker, storage); Retry-After in s",
}
"""The default description of each error status."""

_RETRY_AFTER = {"Retry-After": {"description": "seconds to wait before trying again", "schema": {"type": "integer"}}}
_AUTHENTICATE = {"WWW-Authenticate": {"description": "the scheme to authenticate with: Bearer (RFC 9110 11.6.1)",
                                      "schema": {"type": "string"}}}
_CONDITION = {"X-Refused-Condition": {"description": "the failed condition's name, when the error names one",
                                      "schema": {"type": "string"}}}

VALIDATION_ERROR_SCHEMA: dict[str, Any] = {
    "title": "HTTPValidationError", "type": "object", "required": ["detail"],
    "properties": {"detail": {"type": "string", "title": "Detail"},
                   "fields": {"type": "array", "items": {"type": "string"}, "title": "Fields"},
                   "condition": {"anyOf": [{"type": "string"}, {"type": "null"}], "title": "Condition"}},
}
"""The 422 body: a malformed request (``detail`` and ``fields``) or a refusal (``detail`` and
``condition``)."""

_VALIDATION_CONTENT = {"application/json": {"schema": {"$ref": "#/components/schemas/HTTPValidationError"}}}
_PROBLEM_CONTENT = {"application/json": {"schema": {"$ref": "#/components/schemas/Problem"}}}


def errors(*codes: int | tuple[int, str]) -> dict[int | str, dict[str, Any]]:
    """``responses=`` of a route: each error status it answers from its own code, with the error
    body's schema and headers.

    Args:
        codes: statuses (default description from :data:`DESCRIPTIONS`) or (status, description).

    Returns:
        {status: OpenAPI response object} for FastAPI's ``responses=``.

    Raises:
        KeyError: a bare status with no default description.
    """
    out: dict[int | str, dict[str, Any]] = {}
    for item in codes:
        code, text = item if isinstance(item, tuple) else (item, DESCRIPTIONS[item])
        entry: dict[str, Any] = {"description": text, "headers": dict(_CONDITION)}
        if code == 422:
            entry["content"] = _VALIDATION_CONTENT
        else:
            entry["model"] = Problem
        if code in (429, 503):
            entry["headers"].update(_RETRY_AFTER)
        if code == 401:
            entry["headers"].update(_AUTHENTICATE)
        out[code] = entry
    return out


BODY_NOT_PARSED = {"description": "the body could not be parsed (not JSON, or not in its declared encoding)",
                   "content": _VALIDATION_CONTENT}


def document_errors(schema: dict, routers: list) -> dict:
    """Complete the OpenAPI ``schema`` of ``routers`` in place (see the module docstring); returns it."""
    schema.setdefault("components", {}).setdefault("schemas", {})["HTTPValidationError"] = VALIDATION_ERROR_SCHEMA
    if "Problem" not in schema["components"]["schemas"]:
        schema["components"]["schemas"]["Problem"] = Problem.model_json_schema()
    for path in schema.get("paths", {}).values():
        for operation in path.values():
            if isinstance(operation, dict) and "requestBody" in operation:
                responses = operation.setdefault("responses", {})
                responses.setdefault("400", BODY_NOT_PARSED)
                responses.setdefault("413", _documented(413))
    _document_auth_errors(routers, schema)
    return schema


def _documented(code: int) -> dict[str, Any]:
    """:func:`errors`' entry of ``code`` as written into the OpenAPI document (schema by reference)."""
    entry = dict(errors(code)[code])
    if entry.pop("model", None) is not None:
        entry["content"] = _PROBLEM_CONTENT
    return entry


def _auth_needs(dependant) -> tuple[bool, bool]:
    """(needs a session, needs more than the viewer role) of a route, from its dependencies
    (server.api.deps.get_current_user and require_role)."""
    from server.api.deps import get_current_user

    session, role = False, False
    for dep in dependant.dependencies:
        if dep.call is get_current_user:
            session = True
        closure = getattr(dep.call, "__closure__", None) or ()
        if getattr(dep.call, "__qualname__", "").startswith("require_role."):
            session = True
            role = role or any(c.cell_contents in ("operator", "admin") for c in closure
                               if isinstance(c.cell_contents, str))
        s, r = _auth_needs(dep)
        session, role = session or s, role or r
    return session, role


def _document_auth_errors(routers: list, schema: dict) -> None:
    """401 and 503 on every route that needs a session, 403 on those that need the operator or
    admin role (what server.api.deps answers); routes that check the session themselves (the
    E-STOP) list these in their own ``responses=``."""
    from fastapi.routing import APIRoute

    for route in (r for router in routers for r in router.routes):
        if not isinstance(route, APIRoute) or route.path not in schema.get("paths", {}):
            continue
        session, role = _auth_needs(route.dependant)
        for method in route.methods or ():
            operation = schema["paths"][route.path].get(method.lower())
            if operation is None:
                continue
            responses = operation.setdefault("responses", {})
            for code, needed in ((401, session), (403, role), (503, session)):
                if needed:
                    responses.setdefault(str(code), _documented(code))
