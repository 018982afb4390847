"""Live push: ``GET /api/live`` is a Server-Sent Events stream of machine states, throw progress,
live throw samples, stored results, heartbeats and (with ``?console=<id>``) that console's own
changes. Event names and data: see server.console.live.LiveHub. The stream ends when the server stops
(sse-starlette ends open streams on uvicorn's shutdown), and within SESSION_CHECK_S of its session
ending (a log-out, a disabled or deleted account) or of its log-in expiring more than
server.accounts.auth.STOP_GRACE_S ago (until then an open stream goes on: the console that may still
stop the machine still shows it); browsers reconnect by themselves, and a refused reconnection shows
the console's LOGGED OUT banner (web/js/live.js).
"""

from __future__ import annotations

import asyncio
import json
import time

from fastapi import APIRouter, Request
from sse_starlette.sse import EventSourceResponse

from server.accounts.auth import STOP_GRACE_S, SessionMirror
from server.api.deps import LiveDep, SceneDep, ViewerDep, session_token
from server.api.responses import errors
from server.errors import NotFound, Unavailable

router = APIRouter(tags=["live"])

SESSION_CHECK_S = 1.0
"""How often an open stream asks the session mirror whether its session still stands, s."""


@router.get("/api/live", response_class=EventSourceResponse,
            responses={200: {"content": {"text/event-stream": {}}},
                       **errors((404, "no such console of this user"), (503, "live push is not running"))})
async def live(request: Request, hub: LiveDep, scene: SceneDep, user: ViewerDep, console: str | None = None) -> EventSourceResponse:
    """The event stream (text/event-stream); starts with every machine's state."""
    if hub is None:
        raise Unavailable("live push is not running")
    if console is not None and scene is not None:
        con = scene.get_console(console)
        if con is None or con.username != user.username:
            raise NotFound(f"no console {console} of yours (reload the page)")
    token = session_token(request)
    mirror: SessionMirror | None = getattr(request.app.state, "session_mirror", None)

    def ended() -> bool:  # no I/O; a mirror that could not read storage yet knows nothing
        return mirror is not None and mirror.loaded and mirror.session(token, STOP_GRACE_S) is None

    sub = hub.subscribe(console)

    async def events():
        checked = time.monotonic()
        try:
            while True:
                try:
                    name, data = await asyncio.wait_for(sub.queue.get(), timeout=SESSION_CHECK_S)
                except TimeoutError:
                    name = None
                if time.monotonic() - checked >= SESSION_CHECK_S:
                    checked = time.monotonic()
                    if ended():
                        return
                if name is not None:
                    yield {"event": name, "data": json.dumps(data, separators=(",", ":"))}
        finally:
            hub.unsubscribe(sub)

    return EventSourceResponse(events(), ping=15, headers={"Cache-Control": "no-store"})
