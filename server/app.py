"""FastAPI application factory.

``create_app(settings)`` builds everything from settings (no engine or session at import time).
The lifespan: optional ``alembic upgrade head``, open the Zenoh session, start the fleet link
(subscriptions + THROW_RESULT queryable), start the viser scene; on shutdown the reverse.
"""

from __future__ import annotations

import logging
import math
from contextlib import asynccontextmanager
from pathlib import Path

import zenoh
from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from server.api.routes import adaptation, auth, diagnosis, health, jobs, live, machines, policies, previews, scene, throws, users
from server.config import Settings, get_settings
from server.db.migrate import upgrade
from server.db.models import Throw
from server.db.session import make_engine, make_sessionmaker
from server.command_signer import CommandSigner
from server.fleet import Fleet
from server.reconcile import Reconciler
from server.jobs import JobQueue, JobStore, queue_url
from server.jobs import tasks as job_tasks
from server.login_guard import LoginGuard
from server.live import LiveHub
from server.results import ResultStore
from server.scene import ConsoleScene
from server.policies import PolicyService
from server.previews import PreviewService
from server.throws import ThrowService
from server.web_guard import BodySizeLimit, SecurityHeaders, inline_script_hashes

log = logging.getLogger(__name__)

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
        if settings.auto_migrate:
            upgrade(settings.database_url)
        engine = make_engine(settings.database_url)
        sessions = make_sessionmaker(engine)
        store = ResultStore(sessions, settings.data_dir)
        own_session = zenoh_session is None
        zsession = open_zenoh(settings) if own_session else zenoh_session
        fleet = Fleet(zsession, store, settings.query_timeout_s, signer=CommandSigner(settings.resolved_site_dir))
        app.state.live = live_hub = LiveHub(zsession, fleet)
        app.state.login_guard = LoginGuard(settings.login_failures_per_user, settings.login_failures_per_address,
                                           settings.login_workers, settings.login_max_pending)
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
                                            settings.clearance_radius_m, settings.preview_profile)
        try:
            fleet.start()
            app.state.reconciler.start()
            live_hub.start()
            app.state.policies.start()
            if scene_obj is not None:
                scene_obj.start()
                fleet.result_listeners.append(lambda tid: _show_result(app, tid))
            yield
        finally:
            if scene_obj is not None:
                scene_obj.stop()
            app.state.policies.stop()
            app.state.reconciler.stop()
            live_hub.stop()
            fleet.stop()
            if own_session:
                zsession.close()
            engine.dispose()
            app.state.login_guard.close()

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
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes,
                       overrides={("POST", "/api/policies"): settings.max_policy_upload_bytes})
    app.add_middleware(SecurityHeaders, script_hashes=inline_script_hashes(WEB_DIR) if WEB_DIR.is_dir() else [])
    for module in (health, auth, users, machines, throws, previews, policies, scene, live, diagnosis, adaptation, jobs):
        app.include_router(module.router)
    if WEB_DIR.is_dir():
        app.mount("/console", StaticFiles(directory=WEB_DIR, html=True), name="console")

        @app.get("/", include_in_schema=False)
        def _root() -> RedirectResponse:
            return RedirectResponse("/console/")

    return app


def _serve_api_docs(app: FastAPI) -> None:
    """/docs (Swagger UI) and /redoc from files in the fastapi-offline package, not a CDN: the API
    reference works on a site without internet."""
    from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
    from fastapi.responses import HTMLResponse
    import fastapi_offline

    static = Path(fastapi_offline.__file__).resolve().parent / "static"
    app.mount("/docs-static", StaticFiles(directory=static), name="docs-static")

    @app.get("/docs", include_in_schema=False)
    def _docs() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url=app.openapi_url, title=f"{app.title}: API",
                                   swagger_js_url="/docs-static/swagger-ui-bundle.js",
                                   swagger_css_url="/docs-static/swagger-ui.css",
                                   swagger_favicon_url="/docs-static/favicon.png")

    @app.get("/redoc", include_in_schema=False)
    def _redoc() -> HTMLResponse:
        return get_redoc_html(openapi_url=app.openapi_url, title=f"{app.title}: API",
                              redoc_js_url="/docs-static/redoc.standalone.js",
                              redoc_favicon_url="/docs-static/favicon.png", with_google_fonts=False)


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


async def _validation_error(_request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 with FastAPI's usual body, but JSON-safe: a NaN/inf in the request (which JSON cannot
    carry back) is echoed as a string instead of crashing the error response with a 500."""
    return JSONResponse(status_code=422, content={"detail": _json_safe(jsonable_encoder(exc.errors()))})


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value
