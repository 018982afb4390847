"""Request and response bodies of the per-operator console state (``/api/consoles``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from server.api.schemas import Vec3


class ReplayOut(BaseModel):
    """The recorded throw a console replays (server.console.scene_replay): the time its 3D view shows
    (s from the recording's start, as on the History page's plots) and the recording's length."""

    throw_id: str
    t_s: float
    duration_s: float


class ConsoleOut(BaseModel):
    """One console page's view state (never shared with another page or operator).

    ``target_reason`` says why the target cannot be served (None: it can); ``snapped`` is True
    when a 2D click was moved onto the throwing line; ``viser_path`` is the websocket path that
    binds the 3D view to this console (``ws://<host>:<viser_port><viser_path>``), ``<host>`` being
    ``viser_host`` (server.config.Settings.viser_public_host) or, when None, the page's choice
    (web/js/common.js viewHost); ``replay`` is
    the recorded throw the view replays instead of the live machine (None: live).
    """

    console_id: str
    machine_id: str | None
    mode: Literal["2d", "3d"]
    target: list[float] | None
    target_reason: str | None
    snapped: bool
    preview: list[str] = Field(default_factory=list)
    replay: ReplayOut | None = None
    viser_port: int | None = None
    viser_path: str | None = None
    viser_host: str | None = None


class ConsoleUpdate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    machine_id: str | None = Field(default=None, min_length=1, max_length=64)
    mode: Literal["2d", "3d"] | None = None
    target: Vec3 | None = None
    clear: bool = False
    """Drop the target, preview and drawn throw (the machine's runtime restarted: they are of
    the world before it)."""


class ConsoleShowPreview(BaseModel):
    model_config = ConfigDict(extra="forbid")

    preview_id: str = Field(min_length=1, max_length=64)


class ConsoleReplay(BaseModel):
    """Replay a recorded throw in the console's 3D view at ``t_s`` (s from the recording's start)."""

    model_config = ConfigDict(extra="forbid")

    throw_id: str = Field(min_length=1, max_length=64)
    t_s: float = Field(ge=0.0, le=3600.0, allow_inf_nan=False)


class SceneInfo(BaseModel):
    """Where the 3D view is served (each console binds its own view, see /api/consoles)."""

    viser_port: int | None
    consoles: int
