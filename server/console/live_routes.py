"""Live push: ``GET /api/live`` is a Server-Sent Events stream of machine states, throw progress,
live throw samples, stored results, heartbeats and (with ``?console=<id>``) that console's own
changes. Event names and data: see server.console.live.LiveHub. The stream ends when the server stops
(sse-starlette ends open streams on uvicorn's shutdown); browsers reconnect by themselves.
"""

from __future__ import annotations

import asyncio
import json

from fastapi import APIRouter
from sse_starlette.sse import EventSourceResponse

from server.api.deps import LiveDep, SceneDep, ViewerDep
from server.api.responses import errors
from server.errors import NotFound, Unavailable

router = APIRouter(tags=["live"])


@router.get("/api/live", response_class=EventSourceResponse,
            responses={200: {"content": {"text/event-stream": {}}},
                       **errors((404, "no such console of this user"), (503, "live push is not running"))})
async def live(hub: LiveDep, scene: SceneDep, user: ViewerDep, console: str | None = None) -> EventSourceResponse:
    """The event stream (text/event-stream); starts with every machine's state."""
    if hub is None:
        raise Unavailable("live push is not running")
    if console is not None and scene is not None:
        con = scene.get_console(console)
        if con is None or con.username != user.username:
            raise NotFound(f"no console {console} of yours (reload the page)")
    sub = hub.subscribe(console)

    async def events():
        try:
            while True:
                try:
                    name, data = await asyncio.wait_for(sub.queue.get(), timeout=5.0)
                except TimeoutError:
                    continue
                yield {"event": name, "data": json.dumps(data, separators=(",", ":"))}
        finally:
            hub.unsubscribe(sub)

    return EventSourceResponse(events(), ping=15, headers={"Cache-Control": "no-store"})
