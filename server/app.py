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
from sqlalchemy.orm import Session, sessionmaker
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

from server.accounts import auth_routes as auth
from server.accounts import user_routes as users
from server.accounts.auth import AuditBacklog, SessionMirror
from server.accounts.login_guard import LoginGuard
from server.analysis import adaptation_routes as adaptation
from server.analysis import diagnosis_routes as diagnosis
from server.analysis.adaptation import AdaptationRuns
from server.analysis.diagnosis import DiagnosisRuns
from server.analysis.drift import DriftWatch
from server.api.errors import domain_error
from server.api.responses import document_errors
from server.api.web_guard import BodySizeLimit, SecurityHeaders, inline_script_hashes
from server.config import Settings, get_settings
from server.console import alarm_routes as alarms
from server.console import live_routes as live
from server.console import scene_routes as scene
from server.console.alarms import AlarmService
from server.console.live import LiveHub
from server.console.pages import PageFiles
from server.console.scene import ConsoleScene
from server.db.migrate import upgrade
from server.db.models import Throw
from server.db.session import make_engine, make_sessionmaker
from server.errors import DomainError
from server.fleet import routes as machines
from server.fleet.command_signer import CommandSigner
from server.fleet.events import on_results
from server.fleet.link import Fleet
from server.fleet.reconcile import Reconciler
from server.fleet.results import ResultStore
from server.jobs import JobQueue, JobStore, queue_url
from server.jobs import routes as jobs
from server.jobs import tasks as job_tasks
from server.jobs.watch import JobWatcher
from server.policies import routes as policies
from server.policies.versions import PolicyService
from server.site import health_routes as health
from server.site.storage import StorageFault, StorageMonitor, classify, storage_response
from server.throws import preview_routes as previews
from server.throws import routes as throws
from server.throws.gate import GateLimits
from server.throws.previews import PreviewService
from server.throws.service import ThrowService

log = logging.getLogger(__name__)

ESTOP_LATCH_FILE = "estop_latches.json"
"""The server's E-STOP latches (server.fleet.estop), in the data directory."""

ROUTE_MODULES = (health, auth, users, machines, throws, previews, policies, scene, live, diagnosis, adaptation, jobs, alarms)

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
        # the E-STOP and the machine list authorise from memory and audit later (docs/safety.md)
        app.state.audit_backlog = audit_backlog = AuditBacklog(sessions)
        app.state.session_mirror = session_mirror = SessionMirror(sessions, on_tick=audit_backlog.flush)
        session_mirror.watch(sessions)
        session_mirror.start()
        store = ResultStore(sessions, settings.data_dir)
        own_session = zenoh_session is None
        zsession = zenoh_session if zenoh_session is not None else open_zenoh(settings)
        fleet = Fleet(zsession, store, settings.query_timeout_s, signer=CommandSigner(settings.resolved_site_dir),
                      estop_latch_file=settings.data_dir / ESTOP_LATCH_FILE)
        app.state.live = live_hub = LiveHub(fleet)
        app.state.login_guard = LoginGuard(settings.login_failures_per_user, settings.login_failures_per_address,
                                           settings.login_workers, settings.login_max_pending,
                                           per_user_address=settings.login_failures_per_user_address)
        app.state.throws = throws = ThrowService(fleet, sessions, settings.keep_out_zones,
                                                 gate=GateLimits.from_settings(settings), machine_status=live_hub.status)
        scene_obj = _make_scene(fleet, throws, live_hub, settings, sessions) if settings.viser_enabled else None
        app.state.settings, app.state.sessions, app.state.store = settings, sessions, store
        app.state.fleet, app.state.scene = fleet, scene_obj
        app.state.reconciler = Reconciler(fleet, sessions, store.mark_lost, settings.result_grace_s,
                                          settings.runtime_gone_s, settings.reconcile_period_s,
                                          handshake_s=settings.query_timeout_s + 2.0)
        fleet.add_consumer(app.state.reconciler.on_event)  # passes follow the fleet's events
        app.state.jobs = JobQueue(queue_url(settings), JobStore(sessions), job_tasks.execute)
        if app.state.jobs.url == "immediate":  # tests: jobs run in this process
            job_tasks.bind(job_tasks.WorkerContext(sessions, settings.data_dir, settings, app.state.jobs))
        app.state.policies = PolicyService(fleet, sessions, store, settings, app.state.jobs)
        app.state.previews = PreviewService(fleet, sessions, app.state.throws, app.state.jobs, settings.data_dir,
                                            settings.clearance_radius_m, settings.preview_profile,
                                            settings.release_check_radius_m)
        throws.previews = app.state.previews.get  # a throw looks its preview up (built after the throws)
        app.state.job_watcher = job_watcher = JobWatcher(app.state.jobs.store, live_hub.publish)
        app.state.diagnosis_runs = DiagnosisRuns(sessions, app.state.jobs, settings.data_dir)
        app.state.adaptation_runs = AdaptationRuns(app.state.diagnosis_runs, app.state.policies, app.state.previews,
                                                   app.state.jobs)
        app.state.alarms = alarm_service = AlarmService(sessions, publish=live_hub.publish,
                                                        simulated=lambda mid: _simulated(fleet, mid))

        def publish_drift(event: str, data: dict) -> None:  # a drift alert is also an alarm
            live_hub.publish(event, data)
            alarm_service.on_drift(data)

        app.state.drift = live_hub.drift = DriftWatch(sessions, settings.data_dir, app.state.diagnosis_runs,
                                                      webhook_url=settings.drift_webhook_url, publish=publish_drift)
        alarm_service.drift_ack = app.state.drift.acknowledge
        fleet.add_consumer(on_results(app.state.drift.on_result))
        fleet.add_consumer(alarm_service.on_event)
        try:
            live_hub.start()  # a consumer before the fleet's subscribers exist: it hears every event
            fleet.start()
            app.state.reconciler.start()
            job_watcher.start()
            app.state.policies.start()
            if scene_obj is not None:
                scene_obj.start()
                fleet.add_consumer(on_results(ResultDrawer(scene_obj, sessions, store)))
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
            app.state.login_guard.close()  # its pending audit entries are written first
            session_mirror.stop()
            audit_backlog.flush()
            storage.release(engine)  # disposes it, unless its files are unwritable (server.site.storage)

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
    app.add_middleware(SecurityHeaders, script_hashes=inline_script_hashes(WEB_DIR) if WEB_DIR.is_dir() else [])
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


def _make_scene(fleet: Fleet, throws: ThrowService, live_hub: LiveHub, settings: Settings,
                sessions: sessionmaker[Session]) -> ConsoleScene:
    """The 3D view, judging clicked targets like a throw request would (mode geometry, the
    policy's trained range, keep-out zones), pushing console changes live, and binding a view to a
    console only for the console's owner (the session cookie of its websocket)."""
    from server.accounts.auth import user_for_token
    from server.throws.targets import serve_refusal

    def refusal(machine_id: str, mode: str, target) -> str | None:
        state = fleet.latest_state(machine_id)
        if state is None:
            return f"no state from machine {machine_id}"
        return serve_refusal(mode, target, state.q[0], throws.target_range(machine_id, mode), settings.keep_out_zones)

    def console_changed(con: dict) -> None:
        live_hub.publish("console", con, console_id=con["console_id"])

    def authorise(token: str | None) -> str | None:
        with sessions() as db:
            user = user_for_token(db, token)
            return user.username if user is not None else None

    return ConsoleScene(fleet, settings.viser_host, settings.viser_port, refusal=refusal, band=throws.target_range,
                        zones=settings.keep_out_zones, on_console_change=console_changed, authorise=authorise)


class ResultDrawer:
    """The 3D scene's consumer of stored results: draws each stored throw in the views showing
    its machine (called with the throw id, :func:`server.fleet.events.on_results`)."""

    def __init__(self, scene: ConsoleScene, sessions, store: ResultStore):
        self.scene, self.sessions, self.store = scene, sessions, store

    def __call__(self, throw_id: str) -> None:
        with self.sessions() as db:
            row = db.get(Throw, throw_id)
            if row is None:
                return
            self.scene.show_throw(row.machine_id, self.store.telemetry_file(row), row.impact_m, row.target_m)


def _simulated(fleet: Fleet, machine_id: str) -> bool:
    """Whether the fleet knows ``machine_id`` as a simulated machine (RuntimeInfo or MachineState)."""
    info, state = fleet.last_info(machine_id), fleet.latest_state(machine_id)
    return bool((info is not None and info.simulated) or (state is not None and state.simulated))


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
