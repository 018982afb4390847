"""GET /api/health: is the server up, does it reach the database, is Zenoh open."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException
from sqlalchemy import text
from sqlalchemy.exc import SQLAlchemyError

from server.api.deps import FleetDep, SessionDep
from server.api.schemas import Health

router = APIRouter(prefix="/api/health", tags=["health"])


@router.get("", response_model=Health, responses={503: {"description": "database unreachable"}})
def health(db: SessionDep, fleet: FleetDep) -> Health:
    try:
        db.execute(text("SELECT 1"))
    except SQLAlchemyError as e:
        raise HTTPException(503, f"database unreachable: {e.__class__.__name__}") from e
    return Health(zenoh=not fleet.session.is_closed(), database=True)
