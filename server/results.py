"""Writes what the fleet reports into the database and the telemetry folder.

:class:`ResultStore` is used from the fleet's single worker thread (and by the throws service for
machine rows). Every method commits its own transaction.
"""

from __future__ import annotations

import base64
import logging
import os
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta
from pathlib import Path

from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from runtime.protocol.messages import PolicyInfo, ThrowResult, ThrowStatus
from runtime.throw_geometry import impact_errors
from server.db.models import FINAL_STATUSES, Machine, PolicyVersion, Throw
from server.db.types import utcnow

log = logging.getLogger(__name__)


class UnknownThrow(LookupError):
    """A result for a throw the server never issued (forged, or from another site's database)."""


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

        Only for throws the server issued: a result whose id has no row, or whose machine, mode
        or target differ from the row's, is refused (UnknownThrow) and leaves no trace in the
        history. Idempotent: a re-delivered result rewrites the same file and the same values;
        a result for a throw marked ``lost`` replaces that status (the runtime did finish it).
        Errors are recomputed from target and impact when the runtime did not send them.

        Raises:
            UnknownThrow: not a throw the server issued.
            ValueError: the telemetry is not valid base64.
            sqlalchemy.exc.SQLAlchemyError: the commit failed (the caller acks stored=False).
        """
        outcome = self.store_results([result])[0]
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    def store_results(self, results: list[ThrowResult]) -> list[Throw | Exception]:
        """:meth:`store_result` for several results at once (the fleet link drains its queue):
        the MCAP files are written, synced together and renamed, then every row is updated in
        one commit. Returns per result the stored row or the exception that refused it
        (UnknownThrow, ValueError); a failed commit raises for the whole batch."""
        out: list[Throw | Exception | None] = [None] * len(results)
        with self.sessions() as db:
            known = {t.id: t for t in db.scalars(select(Throw).where(Throw.id.in_({r.throw_id for r in results})))}
        files: dict[int, tuple[Path, bytes]] = {}
        for i, result in enumerate(results):
            try:
                _check_issued(known.get(result.throw_id), result)
                if result.telemetry_mcap_b64:
                    data = base64.b64decode(result.telemetry_mcap_b64, validate=True)
                    files[i] = (Path("telemetry") / f"{_safe_name(result.throw_id)}.mcap", data)
            except (UnknownThrow, ValueError) as e:
                out[i] = e
        _write_all_atomic({self.data_dir / rel: data for rel, data in files.values()})
        now = utcnow()
        with self.sessions.begin() as db:
            todo = [i for i in range(len(results)) if out[i] is None]
            rows = {t.id: t for t in db.scalars(select(Throw).where(Throw.id.in_({results[i].throw_id for i in todo})))}
            for i in todo:
                row = rows.get(results[i].throw_id)
                if row is None:  # deleted meanwhile (its handshake failed)
                    out[i] = UnknownThrow(f"result for throw {results[i].throw_id!r}, which the server withdrew, refused")
                    continue
                _apply_result(row, results[i], files[i][0] if i in files else None, now)
                out[i] = row
        for r, o in zip(results, out):
            if isinstance(o, Throw):
                log.info("stored result of throw %s: %s", r.throw_id, r.status)
        return out

    def mark_lost(self, throw_id: str, reason: str) -> bool:
        """Close an open throw as ``lost`` with ``reason``; False if it is already final (or
        unknown). One conditional UPDATE, so a result stored meanwhile by another thread or
        server is never overwritten; an open throw never counts in the accuracy aggregates
        (server.db.aggregates), so they need no change."""
        with self.sessions.begin() as db:
            done = db.execute(update(Throw).where(Throw.id == throw_id, Throw.status.not_in(FINAL_STATUSES))
                              .values(status="lost", failure_reason=reason, completed_at=utcnow())
                              .execution_options(synchronize_session=False))
        return done.rowcount == 1


def _check_issued(known: Throw | None, result: ThrowResult) -> None:
    """Raise UnknownThrow unless ``known`` is the issued throw ``result`` reports on."""
    if known is None:
        raise UnknownThrow(f"result for throw {result.throw_id!r}, which the server never issued, refused")
    if (known.machine_id, known.mode) != (result.machine_id, result.mode) or any(
            abs(a - b) > 1e-6 for a, b in zip(known.target_m, result.target_m)):
        raise UnknownThrow(f"result for throw {result.throw_id!r} does not match the issued throw "
                           f"({known.machine_id} {known.mode} {known.target_m}), refused")


def _apply_result(row: Throw, result: ThrowResult, telemetry: Path | None, now) -> None:
    """Copy the outcome of ``result`` onto its throw's row (errors recomputed when missing)."""
    down, cross = result.downrange_error_m, result.crossrange_error_m
    if result.impact_m is not None and (down is None or cross is None):
        down, cross = impact_errors(result.target_m, result.impact_m)
    if row.status == "lost":
        log.warning("throw %s was lost (%s); its result arrived: %s", row.id, row.failure_reason, result.status)
        row.completed_at = None
    row.status = result.status
    row.failure_reason = result.failure_reason
    if result.impact_m is not None:
        row.impact_x_m, row.impact_y_m, row.impact_z_m = result.impact_m
    row.downrange_error_m, row.crossrange_error_m = down, cross
    row.policy_version = result.policy_version or row.policy_version
    row.policy_sha256 = result.policy_sha256 or row.policy_sha256
    row.duration_s = result.duration_s
    row.completed_at = row.completed_at or now
    if row.started_at is None:
        row.started_at = row.completed_at - timedelta(seconds=result.duration_s)
    if telemetry is not None:
        row.telemetry_path = telemetry.as_posix()


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


def _write_all_atomic(files: dict[Path, bytes]) -> None:
    """Write each file to a temporary name, fsync them concurrently (the file system commits
    them together), then rename each into place."""
    if not files:
        return
    tmps = {}
    for path, data in files.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_bytes(data)
        tmps[path] = tmp

    def sync(p: Path) -> None:
        fd = os.open(p, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    with ThreadPoolExecutor(max_workers=min(8, len(tmps))) as pool:
        list(pool.map(sync, tmps.values()))
    for path, tmp in tmps.items():
        os.replace(tmp, path)


def _write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
