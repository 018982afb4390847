"""FastAPI application factory.

``create_app(settings)`` builds the application from settings (no engine or session at import time):
its routes (each feature package's own), error handlers, middlewares and the console pages. The
lifespan builds the services (:func:`server.services.build_services`: optional ``alembic upgrade
head``, the database, the Zenoh session, the fleet link and its consumers, the viser scene), starts
them, publishes them on ``app.state`` for :mod:`server.api.deps`, and stops them at shutdown.
"""

from __future__ import annotations

from contextlib import asynccontextmanager
from pathlib import Path

import zenoh
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles
from sqlalchemy.exc import SQLAlchemyError
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

from server.accounts import auth_routes as auth
from server.accounts import user_routes as users
from server.analysis import adaptation_routes as adaptation
from server.analysis import diagnosis_routes as diagnosis
from server.api.errors import domain_error
from server.api.responses import document_errors
from server.api.web_guard import BodySizeLimit, SecurityHeaders, inline_script_hashes
from server.config import Settings, get_settings
from server.console import alarm_routes as alarms
from server.console import live_routes as live
from server.console import scene_routes as scene
from server.console.pages import PageFiles
from server.errors import DomainError
from server.fleet import routes as machines
from server.jobs import routes as jobs
from server.policies import routes as policies
from server.services import build_services
from server.site import health_routes as health
from server.site.storage import StorageFault, classify, storage_response
from server.throws import preview_routes as previews
from server.throws import routes as throws

ROUTE_MODULES = (health, auth, users, machines, throws, previews, policies, scene, live, diagnosis, adaptation, jobs, alarms)

WEB_DIR = next((d for d in (Path(__file__).resolve().parent / "web", Path(__file__).resolve().parent.parent / "web")
                if d.is_dir()), Path(__file__).resolve().parent.parent / "web")
"""The console pages: ``server/web`` in an installed slinger-server wheel, else the repo's web/."""


def create_app(settings: Settings | None = None, zenoh_session: zenoh.Session | None = None) -> FastAPI:
    """Build the app.

    Args:
        settings: defaults to :func:`server.config.get_settings`.
        zenoh_session: an already open session to use (the caller keeps ownership and closes
            it); default: the lifespan opens one from settings and closes it at shutdown.
    """
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        services = build_services(settings, zenoh_session)
        services.publish(app.state)  # server.api.deps reads them from there
        try:
            services.start()
            yield
        finally:
            services.stop()

    app = FastAPI(
        title="Slinger",
        summary="Operator console and fleet service for throwing with material handlers",
        version="0.1.0",
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
    )
    _serve_api_docs(app)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(DomainError, domain_error)  # the one mapping of domain errors to HTTP
    _document_errors(app, [m.router for m in ROUTE_MODULES])
    for exc_type in (StorageFault, SQLAlchemyError, OSError):
        app.add_exception_handler(exc_type, _storage_error)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes,
                       overrides={("POST", "/api/policies"): settings.max_policy_upload_bytes,
                                  ("POST", "/api/diagnosis/uploads"): settings.max_bag_upload_bytes})
    app.add_middleware(SecurityHeaders, script_hashes=inline_script_hashes(WEB_DIR) if WEB_DIR.is_dir() else [],
                       view_host=settings.viser_public_host)
    if settings.trusted_proxies:  # outermost: the client address is settled before anything reads it
        app.add_middleware(ProxyHeadersMiddleware, trusted_hosts=list(settings.trusted_proxies))
    for module in ROUTE_MODULES:
        app.include_router(module.router)
    if WEB_DIR.is_dir():
        app.mount("/console", PageFiles(directory=WEB_DIR, html=True), name="console")  # one head: server.console.pages

        @app.get("/", include_in_schema=False)
        def _root() -> RedirectResponse:
            return RedirectResponse("/console/")

    return app


def _serve_api_docs(app: FastAPI) -> None:
    """/docs (Swagger UI) and /redoc from files in the fastapi-offline package, not a CDN: the API
    reference works on a site without internet."""
    import fastapi_offline
    from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
    from fastapi.responses import HTMLResponse

    static = Path(fastapi_offline.__file__).resolve().parent / "static"
    app.mount("/docs-static", StaticFiles(directory=static), name="docs-static")

    @app.get("/docs", include_in_schema=False)
    def _docs() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url=app.openapi_url or "/openapi.json", title=f"{app.title}: API",
                                   swagger_js_url="/docs-static/swagger-ui-bundle.js",
                                   swagger_css_url="/docs-static/swagger-ui.css",
                                   swagger_favicon_url="/docs-static/favicon.png")

    @app.get("/redoc", include_in_schema=False)
    def _redoc() -> HTMLResponse:
        return get_redoc_html(openapi_url=app.openapi_url or "/openapi.json", title=f"{app.title}: API",
                              redoc_js_url="/docs-static/redoc.standalone.js",
                              redoc_favicon_url="/docs-static/favicon.png", with_google_fonts=False)


async def _storage_error(request: Request, exc: Exception) -> JSONResponse:
    """503 with the reason for a storage fault (server.site.storage); anything else stays a 500."""
    fault = classify(exc)
    if fault is None:
        raise exc
    storage = getattr(request.app.state, "storage", None)
    if storage is not None:
        storage.report(fault)
    return storage_response(fault.condition, fault.reason)


async def _validation_error(_request: Request, exc: Exception) -> JSONResponse:
    """422 with a sentence naming each bad field (at most three) and ``fields``, the names alone;
    never pydantic's error dump nor the input echoed back (it may be huge, hostile or not JSON).
    Registered for RequestValidationError."""
    if not isinstance(exc, RequestValidationError):
        raise TypeError(f"_validation_error handles RequestValidationError, not {type(exc).__name__}")
    errors = exc.errors()
    parts: list[str] = []
    fields: list[str] = []
    for err in errors:
        loc = [str(x) for x in err.get("loc", ()) if x not in ("body", "query", "path", "header", "cookie")]
        field = ".".join(loc) or "request body"
        fields.append(field)
        if len(parts) < 3:
            parts.append(f"{field}: {_control_free(str(err.get('msg', 'invalid value')))}")
    more = f" (and {len(errors) - 3} more)" if len(errors) > 3 else ""
    return JSONResponse(status_code=422, content={"detail": f"invalid request: {'; '.join(parts)}{more}",
                                                  "fields": fields})


def _document_errors(app: FastAPI, routers: list) -> None:
    """Make the OpenAPI document describe every error answer (server.api.responses.document_errors)."""
    build = app.openapi

    def openapi() -> dict:
        if app.openapi_schema is None:
            app.openapi_schema = document_errors(build(), routers)
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented way to extend the schema


def _control_free(text: str) -> str:
    return "".join(c if c.isprintable() else " " for c in text)[:200]
