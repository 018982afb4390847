"""FastAPI application factory.

``create_app(settings)`` builds everything from settings (no engine or session at import time).
The lifespan: optional ``alembic upgrade head``, open the Zenoh session, start the fleet link
(subscriptions + THROW_RESULT queryable), start the viser scene; on shutdown the reverse.
"""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from pathlib import Path

import zenoh
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles
from sqlalchemy.exc import SQLAlchemyError
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

from server.adaptation import AdaptationRuns
from server.api.errors import domain_error
from server.api.routes import adaptation, auth, diagnosis, health, jobs, live, machines, policies, previews, scene, throws, users
from server.command_signer import CommandSigner
from server.config import Settings, get_settings
from server.db.migrate import upgrade
from server.db.models import Throw
from server.db.session import make_engine, make_sessionmaker
from server.diagnosis import DiagnosisRuns
from server.drift import DriftWatch
from server.errors import DomainError
from server.fleet import Fleet
from server.jobs import JobQueue, JobStore, queue_url
from server.jobs import tasks as job_tasks
from server.jobs.watch import JobWatcher
from server.live import LiveHub
from server.login_guard import LoginGuard
from server.policies import PolicyService
from server.previews import PreviewService
from server.reconcile import Reconciler
from server.results import ResultStore
from server.scene import ConsoleScene
from server.storage import StorageFault, StorageMonitor, classify, storage_response
from server.throws import ThrowService
from server.web_guard import BodySizeLimit, SecurityHeaders, inline_script_hashes

log = logging.getLogger(__name__)

ROUTE_MODULES = (health, auth, users, machines, throws, previews, policies, scene, live, diagnosis, adaptation, jobs)

WEB_DIR = next((d for d in (Path(__file__).resolve().parent / "web", Path(__file__).resolve().parent.parent / "web")
                if d.is_dir()), Path(__file__).resolve().parent.parent / "web")
"""The console pages: ``server/web`` in an installed slinger-server wheel, else the repo's web/."""


def open_zenoh(settings: Settings) -> zenoh.Session:
    """Open the server's Zenoh session from settings (runtime.zenoh_session builds the config)."""
    from runtime.zenoh_acl import machines_in_site, site_acl
    from runtime.zenoh_session import TlsFiles, open_session

    tls_dir = settings.zenoh_tls_dir
    return open_session(
        mode=settings.zenoh_mode,
        listen=tuple(settings.zenoh_listen),
        connect=tuple(settings.zenoh_connect),
        multicast_scouting=settings.zenoh_multicast_scouting,
        tls=TlsFiles.from_site(tls_dir, "server") if tls_dir else None,
        access_control=site_acl(machines_in_site(tls_dir)) if tls_dir else None,
    )


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
        app.state.storage = storage = StorageMonitor(settings.database_url, settings.storage_min_free_bytes)
        if settings.auto_migrate:
            _migrate(settings.database_url, storage)
        engine = make_engine(settings.database_url, settings.database_busy_timeout_s)
        storage.guard(engine)
        sessions = make_sessionmaker(engine, before_use=storage.before_use)
        store = ResultStore(sessions, settings.data_dir)
        own_session = zenoh_session is None
        zsession = open_zenoh(settings) if own_session else zenoh_session
        fleet = Fleet(zsession, store, settings.query_timeout_s, signer=CommandSigner(settings.resolved_site_dir))
        app.state.live = live_hub = LiveHub(zsession, fleet)
        app.state.login_guard = LoginGuard(settings.login_failures_per_user, settings.login_failures_per_address,
                                           settings.login_workers, settings.login_max_pending,
                                           per_user_address=settings.login_failures_per_user_address)
        app.state.throws = ThrowService(fleet, sessions, settings.keep_out_zones,
                                        previews=lambda pid: app.state.previews.get(pid),
                                        gate=settings.gate_limits(), machine_status=live_hub.status)
        scene_obj = _make_scene(app, fleet, settings) if settings.viser_enabled else None
        app.state.settings, app.state.sessions, app.state.store = settings, sessions, store
        app.state.fleet, app.state.scene = fleet, scene_obj
        app.state.reconciler = Reconciler(fleet, sessions, store.mark_lost, settings.result_grace_s,
                                          settings.runtime_gone_s, settings.reconcile_period_s,
                                          handshake_s=settings.query_timeout_s + 2.0)
        app.state.jobs = JobQueue(queue_url(settings), JobStore(sessions), job_tasks.execute)
        if app.state.jobs.url == "immediate":  # tests: jobs run in this process
            job_tasks.bind(job_tasks.WorkerContext(sessions, settings.data_dir, settings, app.state.jobs))
        app.state.policies = PolicyService(fleet, sessions, store, settings, app.state.jobs)
        app.state.previews = PreviewService(fleet, sessions, app.state.throws, app.state.jobs, settings.data_dir,
                                            settings.clearance_radius_m, settings.preview_profile,
                                            settings.release_check_radius_m)
        app.state.job_watcher = job_watcher = JobWatcher(app.state.jobs.store, live_hub.publish)
        app.state.diagnosis_runs = DiagnosisRuns(sessions, app.state.jobs, settings.data_dir)
        app.state.adaptation_runs = AdaptationRuns(app.state.diagnosis_runs, app.state.policies, app.state.previews,
                                                   app.state.jobs)
        app.state.drift = live_hub.drift = DriftWatch(sessions, settings.data_dir, app.state.diagnosis_runs,
                                                      webhook_url=settings.drift_webhook_url, publish=live_hub.publish)
        fleet.result_listeners.append(app.state.drift.on_result)
        try:
            fleet.start()
            app.state.reconciler.start()
            live_hub.start()
            job_watcher.start()
            app.state.policies.start()
            if scene_obj is not None:
                scene_obj.start()
                fleet.result_listeners.append(lambda tid: _show_result(app, tid))
            yield
        finally:
            if scene_obj is not None:
                scene_obj.stop()
            app.state.policies.stop()
            job_watcher.stop()
            app.state.reconciler.stop()
            live_hub.stop()
            fleet.stop()
            if own_session:
                zsession.close()
            storage.release(engine)  # disposes it, unless its files are unwritable (server.storage)
            app.state.login_guard.close()

    app = FastAPI(
        title="Slinger",
        summary="Operator console and fleet service for throwing with material handlers",
        version="0.1.0",
        lifespan=lifespan,
    )
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(DomainError, domain_error)  # the one mapping of domain errors to HTTP
    _document_validation_errors(app, [m.router for m in ROUTE_MODULES])
    for exc_type in (StorageFault, SQLAlchemyError, OSError):
        app.add_exception_handler(exc_type, _storage_error)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes,
                       overrides={("POST", "/api/policies"): settings.max_policy_upload_bytes,
                                  ("POST", "/api/diagnosis/uploads"): settings.max_bag_upload_bytes})
    app.add_middleware(SecurityHeaders, script_hashes=inline_script_hashes(WEB_DIR) if WEB_DIR.is_dir() else [])
    if settings.trusted_proxies:  # outermost: the client address is settled before anything reads it
        app.add_middleware(ProxyHeadersMiddleware, trusted_hosts=list(settings.trusted_proxies))
    for module in ROUTE_MODULES:
        app.include_router(module.router)
    if WEB_DIR.is_dir():
        app.mount("/console", StaticFiles(directory=WEB_DIR, html=True), name="console")

        @app.get("/", include_in_schema=False)
        def _root() -> RedirectResponse:
            return RedirectResponse("/console/")

    return app


def _make_scene(app: FastAPI, fleet: Fleet, settings: Settings) -> ConsoleScene:
    """The 3D view, judging clicked targets like a throw request would (mode geometry, the
    policy's trained range, keep-out zones) and pushing console changes live."""
    from server.targets import serve_refusal

    def refusal(machine_id: str, mode: str, target) -> str | None:
        state = fleet.latest_state(machine_id)
        if state is None:
            return f"no state from machine {machine_id}"
        return serve_refusal(mode, target, state.q[0], app.state.throws._target_range(machine_id, mode),  # noqa: SLF001
                             settings.keep_out_zones)

    return ConsoleScene(
        fleet, settings.viser_host, settings.viser_port, refusal=refusal,
        band=lambda mid, mode: app.state.throws._target_range(mid, mode),  # noqa: SLF001
        zones=settings.keep_out_zones,
        on_console_change=lambda con: app.state.live.publish("console", con, console_id=con["console_id"]),
    )


def _show_result(app: FastAPI, throw_id: str) -> None:
    """Fleet result listener: draw the stored throw in the views showing its machine."""
    scene_obj: ConsoleScene = app.state.scene
    with app.state.sessions() as db:
        row = db.get(Throw, throw_id)
        if row is None:
            return
        scene_obj.show_throw(row.machine_id, app.state.store.telemetry_file(row), row.impact_m, row.target_m)


def _migrate(database_url: str, storage: StorageMonitor) -> None:
    """``alembic upgrade head`` unless the storage has a fault (then the server starts in the
    fault state, /api/health names it, and the migration runs at the next start)."""
    fault = storage.check_files()
    if fault is not None:
        log.error("database not migrated: %s", fault.reason)
        return
    try:
        upgrade(database_url)
    except Exception as e:
        fault = classify(e)
        if fault is None:
            raise
        storage.report(fault)
        log.error("database not migrated: %s", fault.reason)


async def _storage_error(request: Request, exc: Exception) -> JSONResponse:
    """503 with the reason for a storage fault (server.storage); anything else stays a 500."""
    fault = classify(exc)
    if fault is None:
        raise exc
    storage = getattr(request.app.state, "storage", None)
    if storage is not None:
        storage.report(fault)
    return storage_response(fault.condition, fault.reason)


async def _validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 with a sentence naming each bad field (at most three) and ``fields``, the names alone;
    never pydantic's error dump nor the input echoed back (it may be huge, hostile or not JSON)."""
    errors = exc.errors()
    parts, fields = [], []
    for err in errors:
        loc = [str(x) for x in err.get("loc", ()) if x not in ("body", "query", "path", "header", "cookie")]
        field = ".".join(loc) or "request body"
        fields.append(field)
        if len(parts) < 3:
            parts.append(f"{field}: {_control_free(str(err.get('msg', 'invalid value')))}")
    more = f" (and {len(errors) - 3} more)" if len(errors) > 3 else ""
    return JSONResponse(status_code=422, content={"detail": f"invalid request: {'; '.join(parts)}{more}",
                                                  "fields": fields})


VALIDATION_ERROR_SCHEMA = {
    "title": "HTTPValidationError", "type": "object", "required": ["detail"],
    "properties": {"detail": {"type": "string", "title": "Detail"},
                   "fields": {"type": "array", "items": {"type": "string"}, "title": "Fields"}},
}


BODY_NOT_PARSED = {"description": "the body could not be parsed (not JSON, or not in its declared encoding)",
                   "content": {"application/json": {"schema": {"$ref": "#/components/schemas/HTTPValidationError"}}}}


def _document_validation_errors(app: FastAPI, routers: list) -> None:
    """Make the OpenAPI document describe the 422 body :func:`_validation_error` writes (and the
    answers that carry only ``detail``), and the 400 FastAPI gives a body it cannot parse."""
    build = app.openapi

    def openapi() -> dict:
        if app.openapi_schema is None:
            schema = build()
            schema.get("components", {}).get("schemas", {})["HTTPValidationError"] = VALIDATION_ERROR_SCHEMA
            for path in schema.get("paths", {}).values():
                for operation in path.values():
                    if isinstance(operation, dict) and "requestBody" in operation:
                        operation.setdefault("responses", {}).setdefault("400", BODY_NOT_PARSED)
            _document_auth_errors(routers, schema)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi


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
    """Document 401 on every route that needs a session and 403 on those that need the operator
    or admin role (what server.api.deps answers)."""
    from fastapi.routing import APIRoute

    problem = {"content": {"application/json": {"schema": {"$ref": "#/components/schemas/Problem"}}}}
    for route in (r for router in routers for r in router.routes):
        if not isinstance(route, APIRoute) or route.path not in schema.get("paths", {}):
            continue
        session, role = _auth_needs(route.dependant)
        for method in route.methods:
            operation = schema["paths"][route.path].get(method.lower())
            if operation is None:
                continue
            responses = operation.setdefault("responses", {})
            if session:
                responses.setdefault("401", {"description": "log in first (session missing or expired)", **problem})
            if role:
                responses.setdefault("403", {"description": "needs a higher role", **problem})


def _control_free(text: str) -> str:
    return "".join(c if c.isprintable() else " " for c in text)[:200]
