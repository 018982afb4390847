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

from server.api.routes import auth, diagnosis, health, machines, policies, previews, scene, throws, users
from server.config import Settings, get_settings
from server.db.migrate import upgrade
from server.db.models import Throw
from server.db.session import make_engine, make_sessionmaker
from server.fleet import Fleet
from server.results import ResultStore
from server.scene import ConsoleScene
from server.policies import PolicyService
from server.previews import PreviewService
from server.throws import ThrowService

log = logging.getLogger(__name__)

WEB_DIR = Path(__file__).resolve().parent.parent / "web"


def open_zenoh(settings: Settings) -> zenoh.Session:
    """Open the server's Zenoh session from settings (runtime.zenoh_session builds the config)."""
    from runtime.zenoh_session import open_session

    return open_session(
        mode=settings.zenoh_mode,
        listen=tuple(settings.zenoh_listen),
        connect=tuple(settings.zenoh_connect),
        multicast_scouting=settings.zenoh_multicast_scouting,
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
        fleet = Fleet(zsession, store, settings.query_timeout_s)
        scene_obj = ConsoleScene(fleet, settings.viser_host, settings.viser_port) if settings.viser_enabled else None
        app.state.settings, app.state.sessions, app.state.store = settings, sessions, store
        app.state.fleet, app.state.scene = fleet, scene_obj
        app.state.throws = ThrowService(fleet, sessions, settings.keep_out_zones,
                                        previews=lambda pid: app.state.previews.get(pid))
        app.state.policies = PolicyService(fleet, sessions, store, settings)
        app.state.previews = PreviewService(fleet, sessions, app.state.throws, settings.data_dir,
                                            settings.clearance_radius_m)
        try:
            fleet.start()
            app.state.policies.start()
            if scene_obj is not None:
                scene_obj.start()
                fleet.result_listeners.append(lambda tid: _show_result(app, tid))
            yield
        finally:
            if scene_obj is not None:
                scene_obj.stop()
            app.state.policies.stop()
            fleet.stop()
            if own_session:
                zsession.close()
            engine.dispose()

    app = FastAPI(
        title="Slinger",
        summary="Operator console and fleet service for throwing with material handlers",
        version="0.1.0",
        lifespan=lifespan,
    )
    app.add_exception_handler(RequestValidationError, _validation_error)
    for module in (health, auth, users, machines, throws, previews, policies, scene, diagnosis):
        app.include_router(module.router)
    if WEB_DIR.is_dir():
        app.mount("/console", StaticFiles(directory=WEB_DIR, html=True), name="console")

        @app.get("/", include_in_schema=False)
        def _root() -> RedirectResponse:
            return RedirectResponse("/console/")

    return app


def _show_result(app: FastAPI, throw_id: str) -> None:
    """Fleet result listener: draw the stored throw in the 3D view if it is on the shown machine."""
    scene_obj: ConsoleScene = app.state.scene
    with app.state.sessions() as db:
        row = db.get(Throw, throw_id)
        if row is None or (scene_obj.machine_id not in (None, row.machine_id)):
            return
        scene_obj.show_throw(app.state.store.telemetry_file(row), row.impact_m, row.target_m)


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
