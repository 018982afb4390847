"""The console's 3D view: its viser port, and the machine, mode and target picked in it."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException

from server.api.deps import OperatorDep, SceneDep, ViewerDep
from server.api.schemas import SceneState, SceneUpdate

router = APIRouter(prefix="/api/scene", tags=["scene"])


def _state(scene) -> SceneState:
    if scene is None:
        return SceneState(viser_port=None, machine_id=None, mode="2d", target=None)
    return SceneState(viser_port=scene.port, machine_id=scene.machine_id, mode=scene.mode,
                      target=scene.target, preview=list(scene.preview_names))


@router.get("", response_model=SceneState)
def get_scene(scene: SceneDep, _user: ViewerDep) -> SceneState:
    """Where the 3D view is served, and the target clicked in it (None until a click)."""
    return _state(scene)


@router.put("", response_model=SceneState)
def update_scene(update: SceneUpdate, scene: SceneDep, _user: OperatorDep) -> SceneState:
    """Pick the machine shown, the mode (draws the 2D plane) or type a target."""
    if scene is None:
        raise HTTPException(409, "the 3D view is disabled")
    if update.machine_id is not None:
        scene.machine_id = update.machine_id
    if update.mode is not None:
        scene.mode = update.mode
    if update.target is not None:
        scene.set_target(update.target)
    return _state(scene)
