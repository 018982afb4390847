"""The console's 3D view and each console page's own state (machine, mode, target, preview).

``POST /api/consoles`` opens a console for the page (one per page load); the page embeds the 3D
view bound to it and changes it with ``PUT /api/consoles/{id}``. A click in the view changes only
that console; the page hears it over live push (``GET /api/live?console=<id>``). A console belongs
to the user who opened it (403 for anyone else). ``PUT /api/consoles/{id}/replay`` replays a
recorded throw in its view at a time of the recording (the History page's timeline).
"""

from __future__ import annotations

from fastapi import APIRouter

from server.api.deps import CurrentUser, OperatorDep, PreviewsDep, SceneDep, SessionDep, StoreDep, ViewerDep
from server.api.responses import errors
from server.api.web_guard import contained_file
from server.console.scene import ConsoleScene, enabled
from server.console.scene_replay import Replay
from server.console.schemas import ConsoleOut, ConsoleReplay, ConsoleShowPreview, ConsoleUpdate, SceneInfo
from server.db.models import Throw
from server.errors import Conflict, Denied, NotFound, Refused

router = APIRouter(tags=["scene"])


@router.get("/api/scene", response_model=SceneInfo)
def get_scene(scene: SceneDep, _user: ViewerDep) -> SceneInfo:
    """Where the 3D view is served."""
    return SceneInfo(viser_port=scene.port if scene else None, consoles=len(scene.consoles) if scene else 0)


def _out(scene, con) -> ConsoleOut:
    return ConsoleOut(**con.public(), viser_port=scene.port, viser_path=f"/c/{con.console_id}/{con.view_token}",
                      viser_host=scene.public_host)


def _console(scene: ConsoleScene | None, console_id: str, user):
    return enabled(scene).owned_console(console_id, user.username)


@router.post("/api/consoles", response_model=ConsoleOut, status_code=201,
             responses=errors((409, "the 3D view is disabled"), (429, "the server holds its limit of consoles")))
def open_console(scene: SceneDep, user: ViewerDep) -> ConsoleOut:
    """Open a console (one per page load): its own machine, mode, target and 3D view. A user who
    holds server.console.scene.MAX_CONSOLES_PER_USER consoles loses their own least recently used one."""
    scene = enabled(scene)
    return _out(scene, scene.open_console(user.username))  # ConsoleLimit is a Limited: 429


@router.get("/api/consoles/{console_id}", response_model=ConsoleOut, responses=errors(
    (403, "the console belongs to another user"), (404, "no such console"), (409, "the 3D view is disabled")))
def get_console(console_id: str, scene: SceneDep, user: CurrentUser) -> ConsoleOut:
    return _out(scene, _console(scene, console_id, user))


@router.put("/api/consoles/{console_id}", response_model=ConsoleOut,
            responses=errors((403, "another user's console, or a viewer setting a target"), (404, "no such console"),
                             (409, "the 3D view is disabled")))
def update_console(console_id: str, update: ConsoleUpdate, scene: SceneDep, user: ViewerDep) -> ConsoleOut:
    """Pick the machine or mode shown (viewers too), or type a target (operators). A target in 2D
    snaps to the throwing line; ``target_reason`` says why it cannot be served. ``clear`` drops
    the target, preview and drawn throw (after a runtime restart)."""
    scene = enabled(scene)
    con = _console(scene, console_id, user)
    if update.target is not None and user.role == "viewer":
        raise Denied("needs the operator role to set a target (you are viewer)")
    scene.update_console(con, update.machine_id, update.mode, update.target, clear=update.clear)
    return _out(scene, con)


@router.post("/api/consoles/{console_id}/preview", response_model=ConsoleOut,
             responses=errors((404, "no such console or preview"), (409, "the 3D view is disabled"),
                              (422, "the preview is of another machine or another target than the console's")))
def show_preview(console_id: str, body: ConsoleShowPreview, previews: PreviewsDep, scene: SceneDep,
                 user: OperatorDep) -> ConsoleOut:
    """Draw a preview (POST /api/previews) of the console's machine and target in its 3D view."""
    scene = enabled(scene)
    con = _console(scene, console_id, user)
    summary = previews.require(body.preview_id)
    if summary["machine_id"] != con.machine_id:
        raise Refused(f"the preview is of {summary['machine_id']}, this console shows {con.machine_id}")
    t, pt = con.target, summary.get("target_m")
    if t is None or pt is None or abs(t[0] - pt[0]) > 1e-3 or abs(t[1] - pt[1]) > 1e-3:
        # one target on screen: a preview of another point is never drawn over the console's target
        raise Refused("the preview is of another target than this console's" +
                      (f" (x {pt[0]:.2f} y {pt[1]:.2f} m, the console aims at x {t[0]:.2f} y {t[1]:.2f} m)" if t and pt else ""))
    scene.show_preview(con, summary)
    return _out(scene, con)


@router.put("/api/consoles/{console_id}/replay", response_model=ConsoleOut,
            responses=errors((403, "another user's console"), (404, "no such console or throw"),
                             (409, "the 3D view is disabled, or the throw has no usable telemetry")))
def seek_replay(console_id: str, body: ConsoleReplay, scene: SceneDep, db: SessionDep, store: StoreDep,
                user: ViewerDep) -> ConsoleOut:
    """Show the recorded throw in this console's 3D view (viewers too: the view is the page's
    own), its machine posed from the recording at ``t_s`` (clamped to the recording) and drawn
    before the answer; the first call for a throw loads its telemetry and draws its paths.
    ``replay.t_s`` in the answer is the time the view shows."""
    scene = enabled(scene)
    con = _console(scene, console_id, user)
    if con.replay is None or con.replay.throw_id != body.throw_id:
        row = db.get(Throw, body.throw_id)
        if row is None:
            raise NotFound(f"no throw {body.throw_id}")
        path = contained_file(store.data_dir / "telemetry", store.telemetry_file(row))
        if path is None:
            raise Conflict(f"throw {body.throw_id} has no telemetry to replay")
        try:
            replay = Replay.load(row.id, row.machine_id, path, row.impact_m, row.target_m)
        except ValueError as e:
            raise Conflict(str(e)) from e
        scene.start_replay(con, replay)
    scene.seek_replay(con, body.t_s)
    return _out(scene, con)


@router.delete("/api/consoles/{console_id}/replay", response_model=ConsoleOut,
               responses=errors((403, "another user's console"), (404, "no such console"), (409, "the 3D view is disabled")))
def stop_replay(console_id: str, scene: SceneDep, user: ViewerDep) -> ConsoleOut:
    """Back to the live machine in this console's 3D view."""
    scene = enabled(scene)
    con = _console(scene, console_id, user)
    scene.stop_replay(con)
    return _out(scene, con)
