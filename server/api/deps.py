"""Dependencies with aliases so routes read like prose (``db: SessionDep``)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from server.config import Settings
from server.fleet import Fleet
from server.scene import ConsoleScene
from server.throws import ThrowService


def get_db(request: Request) -> Iterator[Session]:
    with request.app.state.sessions() as session:
        yield session


def get_fleet(request: Request) -> Fleet:
    return request.app.state.fleet


def get_throw_service(request: Request) -> ThrowService:
    return request.app.state.throws


def get_scene(request: Request) -> ConsoleScene | None:
    return request.app.state.scene


def get_app_settings(request: Request) -> Settings:
    return request.app.state.settings


SessionDep = Annotated[Session, Depends(get_db)]
FleetDep = Annotated[Fleet, Depends(get_fleet)]
ThrowServiceDep = Annotated[ThrowService, Depends(get_throw_service)]
SceneDep = Annotated[ConsoleScene | None, Depends(get_scene)]
SettingsDep = Annotated[Settings, Depends(get_app_settings)]
