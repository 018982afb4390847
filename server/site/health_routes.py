"""GET /api/health: is the server up, can it use its database (storage faults named), is Zenoh open."""

from __future__ import annotations

from fastapi import APIRouter
from sqlalchemy import text

from server.api.deps import FleetDep, SessionsDep, StorageDep
from server.api.responses import errors
from server.api.schemas import Health
from server.site.storage import classify, storage_response

router = APIRouter(prefix="/api/health", tags=["health"])


@router.get("", response_model=Health, responses=errors((503, (
        "a storage fault: ``condition`` is disk_full, database_locked, database_read_only, "
        "database_unreadable or database_unavailable, ``detail`` says what (server.site.storage)"))))
def health(fleet: FleetDep, storage: StorageDep, sessions: SessionsDep):
    """200 when the database answers and its storage has no fault; else 503 naming the fault.
    The server stays up through storage faults: everything not needing the database still works."""
    zenoh_open = not fleet.session.is_closed()
    fault = storage.check()
    if fault is None:
        try:
            with sessions() as db:
                db.execute(text("SELECT 1"))
        except Exception as e:  # noqa: BLE001  any failure here is the answer
            fault = classify(e)
            if fault is None:
                return storage_response("database_unavailable", f"the database does not answer: {e.__class__.__name__}",
                                        zenoh=zenoh_open)
            storage.report(fault)
    current = storage.fault() if fault is None else fault
    if current is not None:
        return storage_response(current.condition or "database_unavailable", current.reason, zenoh=zenoh_open)
    return Health(zenoh=zenoh_open, database=True)
