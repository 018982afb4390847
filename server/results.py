"""Writes what the fleet reports into the database and the telemetry folder.

:class:`ResultStore` is used from the fleet's single worker thread (and by the throws service for
machine rows). Every method commits its own transaction.
"""

from __future__ import annotations

import base64
import logging
import os
from datetime import timedelta
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from runtime.protocol.messages import PolicyInfo, ThrowResult, ThrowStatus
from runtime.throw_geometry import impact_errors
from server.db.models import FINAL_STATUSES, Machine, PolicyVersion, Throw
from server.db.types import utcnow

log = logging.getLogger(__name__)


class ResultStore:
    """Database + telemetry writer.

    Args:
        sessions: session factory.
        data_dir: data folder; telemetry goes to ``<data_dir>/telemetry/<throw_id>.mcap`` and the
            row stores the path relative to ``data_dir``.
    """

    def __init__(self, sessions: sessionmaker[Session], data_dir: Path):
        self.sessions = sessions
        self.data_dir = Path(data_dir)

    def telemetry_file(self, throw: Throw) -> Path | None:
        """Absolute path of a throw's MCAP file, or None if it has none."""
        return self.data_dir / throw.telemetry_path if throw.telemetry_path else None

    # --- machines and policies ----------------------------------------------------------------
    def upsert_machine(
        self, machine_id: str, simulated: bool, policies: list[PolicyInfo] | None = None
    ) -> None:
        """Create or refresh a machine row and register the policy versions its runtime reports."""
        with self.sessions.begin() as db:
            ensure_machine(db, machine_id, simulated)
            for p in policies or []:
                if db.scalar(select(PolicyVersion).where(PolicyVersion.sha256 == p.sha256)) is None:
                    db.add(PolicyVersion(name=p.version, mode=p.mode, sha256=p.sha256, manifest={}))

    def register_policy(self, manifest: dict, onnx_path: Path | None = None) -> None:
        """Record a policy version from its manifest (``slinger up`` registers what it deploys);
        with ``onnx_path`` the server keeps a copy of the file (previews, promotions, rollbacks)
        at ``<data_dir>/policies/<sha256>.onnx`` with its manifest beside it."""
        rel = self.store_policy_file(manifest, onnx_path) if onnx_path is not None else None
        with self.sessions.begin() as db:
            row = db.scalar(select(PolicyVersion).where(PolicyVersion.sha256 == manifest["onnx_sha256"]))
            if row is None:
                db.add(PolicyVersion(name=manifest["name"], mode=manifest["mode"],
                                     sha256=manifest["onnx_sha256"], manifest=manifest, onnx_path=rel))
            else:
                row.manifest = row.manifest or manifest
                row.onnx_path = row.onnx_path or rel

    def store_policy_file(self, manifest: dict, onnx_path: Path) -> str:
        """Copy a policy file and write its manifest into ``<data_dir>/policies``; returns the
        ONNX path relative to the data dir."""
        import json

        rel = Path("policies") / f"{manifest['onnx_sha256']}.onnx"
        _write_atomic(self.data_dir / rel, Path(onnx_path).read_bytes())
        _write_atomic(self.data_dir / rel.with_suffix(".json"), (json.dumps(manifest, indent=2) + "\n").encode())
        return rel.as_posix()

    # --- throws --------------------------------------------------------------------------------
    def apply_status(self, status: ThrowStatus) -> None:
        """Follow a ThrowStatus: the phase becomes ``status``; the first phase stamps
        ``started_at``, ``released`` stamps ``released_at``.

        Final phases (landed/failed/aborted) are NOT applied here: only the stored ThrowResult
        makes a row final, so a client that sees a final status also sees the impact, errors and
        telemetry. A final row is never changed by a late status."""
        with self.sessions.begin() as db:
            row = db.get(Throw, status.throw_id)
            if row is None:
                log.debug("status for unknown throw %s dropped", status.throw_id)
                return
            now = utcnow()
            if row.started_at is None:
                row.started_at = now
            if status.phase == "released" and row.released_at is None:
                row.released_at = now
            if row.status in FINAL_STATUSES or status.phase in FINAL_STATUSES:
                return
            row.status = status.phase

    def store_result(self, result: ThrowResult) -> Throw:
        """Store a ThrowResult: MCAP file first (atomic rename), then the row, one commit.

        Idempotent: a re-delivered result rewrites the same file and the same values. A result
        for a throw the server has no row for (its ack was lost) creates the row, so nothing the
        runtime's outbox delivers is dropped. Errors are recomputed from target and impact when
        the runtime did not send them.

        Raises:
            ValueError: the telemetry is not valid base64.
            sqlalchemy.exc.SQLAlchemyError: the commit failed (the caller acks stored=False).
        """
        rel = None
        if result.telemetry_mcap_b64:
            data = base64.b64decode(result.telemetry_mcap_b64, validate=True)
            rel = Path("telemetry") / f"{_safe_name(result.throw_id)}.mcap"
            _write_atomic(self.data_dir / rel, data)
        down, cross = result.downrange_error_m, result.crossrange_error_m
        if result.impact_m is not None and (down is None or cross is None):
            down, cross = impact_errors(result.target_m, result.impact_m)
        now = utcnow()
        with self.sessions.begin() as db:
            row = db.get(Throw, result.throw_id)
            if row is None:
                log.warning("result for unknown throw %s: creating its row", result.throw_id)
                ensure_machine(db, result.machine_id, simulated=False)
                row = Throw(id=result.throw_id, machine_id=result.machine_id, mode=result.mode,
                            target_x_m=result.target_m[0], target_y_m=result.target_m[1],
                            target_z_m=result.target_m[2], requested_at=now)
                db.add(row)
            row.status = result.status
            row.failure_reason = result.failure_reason
            if result.impact_m is not None:
                row.impact_x_m, row.impact_y_m, row.impact_z_m = result.impact_m
            row.downrange_error_m, row.crossrange_error_m = down, cross
            row.policy_version = result.policy_version or row.policy_version
            row.duration_s = result.duration_s
            row.completed_at = row.completed_at or now
            if row.started_at is None:
                row.started_at = row.completed_at - timedelta(seconds=result.duration_s)
            if rel is not None:
                row.telemetry_path = rel.as_posix()
        log.info("stored result of throw %s: %s", result.throw_id, result.status)
        return row


def ensure_machine(db: Session, machine_id: str, simulated: bool) -> Machine:
    """Get or add the machine row inside ``db``'s transaction, refreshing last_seen_at."""
    row = db.get(Machine, machine_id)
    if row is None:
        row = Machine(id=machine_id, simulated=simulated)
        db.add(row)
    else:
        row.last_seen_at = utcnow()
        row.simulated = simulated or row.simulated
    return row


def _safe_name(throw_id: str) -> str:
    """Throw ids become file names: keep only [A-Za-z0-9_-] (they are UUIDs in practice)."""
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in throw_id)


def _write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
