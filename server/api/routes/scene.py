"""The console's 3D view and each console page's own state (machine, mode, target, preview).

``POST /api/consoles`` opens a console for the page (one per page load); the page embeds the 3D
view bound to it and changes it with ``PUT /api/consoles/{id}``. A click in the view changes only
that console; the page hears it over live push (``GET /api/live?console=<id>``). A console belongs
to the user who opened it (403 for anyone else).
"""

from __future__ import annotations

from fastapi import APIRouter, HTTPException

from server.api.console_schemas import ConsoleOut, ConsoleShowPreview, ConsoleUpdate, SceneInfo
from server.api.deps import CurrentUser, OperatorDep, PreviewsDep, SceneDep, ViewerDep
from server.api.schemas import Problem
from server.scene import ConsoleScene

router = APIRouter(tags=["scene"])


@router.get("/api/scene", response_model=SceneInfo)
def get_scene(scene: SceneDep, _user: ViewerDep) -> SceneInfo:
    """Where the 3D view is served."""
    return SceneInfo(viser_port=scene.port if scene else None, consoles=len(scene.consoles) if scene else 0)


def _out(scene, con) -> ConsoleOut:
    return ConsoleOut(**con.public(), viser_port=scene.port, viser_path=f"/c/{con.console_id}")


def _enabled(scene: ConsoleScene | None) -> ConsoleScene:
    """The console scene; HTTP 409 when the 3D view is disabled."""
    if scene is None:
        raise HTTPException(409, "the 3D view is disabled")
    return scene


def _console(scene, console_id: str, user):
    con = _enabled(scene).get_console(console_id)
    if con is None:
        raise HTTPException(404, f"no console {console_id} (reload the page)")
    if con.username != user.username:
        raise HTTPException(403, "this console belongs to another user")
    return con


@router.post("/api/consoles", response_model=ConsoleOut, status_code=201,
             responses={409: {"model": Problem, "description": "the 3D view is disabled"},
                        429: {"model": Problem, "description": "the server holds its limit of consoles"}})
def open_console(scene: SceneDep, user: ViewerDep) -> ConsoleOut:
    """Open a console (one per page load): its own machine, mode, target and 3D view. A user who
    holds server.scene.MAX_CONSOLES_PER_USER consoles loses their own least recently used one."""
    if scene is None:
        raise HTTPException(409, "the 3D view is disabled")
    return _out(scene, scene.open_console(user.username))  # ConsoleLimit is a Limited: 429


@router.get("/api/consoles/{console_id}", response_model=ConsoleOut, responses={404: {"model": Problem},
                                                                                 409: {"model": Problem, "description": "the 3D view is disabled"}})
def get_console(console_id: str, scene: SceneDep, user: CurrentUser) -> ConsoleOut:
    return _out(scene, _console(scene, console_id, user))


@router.put("/api/consoles/{console_id}", response_model=ConsoleOut,
            responses={403: {"model": Problem}, 404: {"model": Problem}, 409: {"model": Problem, "description": "the 3D view is disabled"}})
def update_console(console_id: str, update: ConsoleUpdate, scene: SceneDep, user: ViewerDep) -> ConsoleOut:
    """Pick the machine or mode shown (viewers too), or type a target (operators). A target in 2D
    snaps to the throwing line; ``target_reason`` says why it cannot be served."""
    scene = _enabled(scene)
    con = _console(scene, console_id, user)
    if update.target is not None and user.role == "viewer":
        raise HTTPException(403, "needs the operator role to set a target (you are viewer)")
    scene.update_console(con, update.machine_id, update.mode, update.target)
    return _out(scene, con)


@router.post("/api/consoles/{console_id}/preview", response_model=ConsoleOut,
             responses={404: {"model": Problem}, 409: {"model": Problem, "description": "the 3D view is disabled"}, 422: {"model": Problem}})
def show_preview(console_id: str, body: ConsoleShowPreview, previews: PreviewsDep, scene: SceneDep,
                 user: OperatorDep) -> ConsoleOut:
    """Draw a preview (POST /api/previews) in this console's 3D view."""
    scene = _enabled(scene)
    con = _console(scene, console_id, user)
    summary = previews.get(body.preview_id)
    if summary is None:
        raise HTTPException(404, f"no preview {body.preview_id} (previews are kept for a while only)")
    if summary["machine_id"] != con.machine_id:
        raise HTTPException(422, f"the preview is of {summary['machine_id']}, this console shows {con.machine_id}")
    scene.show_preview(con, summary)
    return _out(scene, con)
