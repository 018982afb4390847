"""Writes what the fleet reports into the database and the telemetry folder.

:class:`ResultStore` is used from the fleet's single worker thread (and by the throws service for
machine rows); only :meth:`ResultStore.stage_telemetry` runs on other threads. Every method
commits its own transaction.
"""

from __future__ import annotations

import base64
import logging
import os
import uuid
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta
from pathlib import Path

from sqlalchemy import ColumnElement, case, func, literal, select, update
from sqlalchemy.orm import Session, sessionmaker

from runtime.protocol.messages import PolicyInfo, ThrowResult, ThrowStatus
from runtime.throw_geometry import impact_errors
from server.db.models import FINAL_STATUSES, Machine, PolicyVersion, Throw
from server.db.session import rowcount
from server.db.types import UTCDateTime, utcnow
from server.db.upsert import insert_if_absent
from server.errors import NotFound

log = logging.getLogger(__name__)


class UnknownThrow(NotFound, LookupError):
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
                insert_if_absent(db, PolicyVersion, ["sha256"], name=p.version, mode=p.mode, sha256=p.sha256, manifest={})

    def register_policy(self, manifest: dict, onnx_path: Path | None = None) -> None:
        """Record a policy version from its manifest (``slinger up`` registers what it deploys);
        with ``onnx_path`` the server keeps a copy of the file (previews, promotions, rollbacks)
        at ``<data_dir>/policies/<sha256>.onnx`` with its manifest beside it."""
        rel = self.store_policy_file(manifest, onnx_path) if onnx_path is not None else None
        with self.sessions.begin() as db:
            sha = manifest["onnx_sha256"]
            if not insert_if_absent(db, PolicyVersion, ["sha256"], name=manifest["name"], mode=manifest["mode"],
                                    sha256=sha, manifest=manifest, onnx_path=rel):
                # known (e.g. reported by its runtime first, without manifest or file): fill in what it lacks
                row = db.scalars(select(PolicyVersion).where(PolicyVersion.sha256 == sha)
                                 .execution_options(populate_existing=True)).one()
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
        telemetry. A final row's status is never changed by a late status. One conditional
        UPDATE (one round trip; a result stored meanwhile by another transaction is never
        overwritten; the accuracy aggregates, which only final rows enter, need no change)."""
        now = literal(utcnow(), UTCDateTime)
        values: dict[str, ColumnElement] = {"started_at": func.coalesce(Throw.started_at, now)}
        if status.phase == "released":
            values["released_at"] = func.coalesce(Throw.released_at, now)
        if status.phase not in FINAL_STATUSES:
            values["status"] = case((Throw.status.in_(FINAL_STATUSES), Throw.status), else_=literal(status.phase))
        with self.sessions.begin() as db:
            done = db.execute(update(Throw).where(Throw.id == status.throw_id).values(**values)
                              .execution_options(synchronize_session=False))
        if rowcount(done) == 0:
            log.debug("status for unknown throw %s dropped", status.throw_id)

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

    def stage_telemetry(self, result: ThrowResult) -> Path | None:
        """Decode ``result``'s MCAP telemetry and write it, fsynced, to a temporary file of a
        unique name beside its final place (any thread; the fleet link stages results as they
        arrive, off the database thread). :meth:`store_results` renames it into place only if
        the result is accepted, so a refused (forged) result never replaces a throw's file.

        Returns:
            the temporary file, or None if the result carries no telemetry.
        Raises:
            ValueError: the telemetry is not valid base64.
            OSError: the file could not be written.
        """
        if not result.telemetry_mcap_b64:
            return None
        data = base64.b64decode(result.telemetry_mcap_b64, validate=True)
        path = self.data_dir / self._telemetry_rel(result.throw_id)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{uuid.uuid4().hex}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        finally:
            os.close(fd)
        return tmp

    @staticmethod
    def _telemetry_rel(throw_id: str) -> Path:
        return Path("telemetry") / f"{_safe_name(throw_id)}.mcap"

    def store_results(self, results: list[ThrowResult],
                      staged: list[Path | None | Exception] | None = None) -> list[Throw | Exception]:
        """:meth:`store_result` for several results at once (the fleet link drains its queue):
        in one transaction the issued rows are read (locked on PostgreSQL), each accepted
        result's telemetry, staged and fsynced before (``staged``: per result what
        :meth:`stage_telemetry` returned or raised; None: staged here, concurrently), is renamed
        into place, every row and the accuracy aggregates are updated, then one commit. Returns
        per result the stored row or the exception that refused it (UnknownThrow, ValueError,
        OSError); a failed commit raises for the whole batch (the telemetry files stay: a
        re-delivery rewrites them)."""
        if staged is None:
            staged = _stage_all(self, results)
        if len(staged) != len(results):
            raise ValueError(f"{len(staged)} staged telemetry entries for {len(results)} results")
        out: list[Throw | Exception | None] = [None] * len(results)
        try:
            with self.sessions.begin() as db:
                rows = {t.id: t for t in db.scalars(select(Throw).where(
                    Throw.id.in_({r.throw_id for r in results})).with_for_update())}
                now = utcnow()
                for i, (result, tmp) in enumerate(zip(results, staged)):
                    try:
                        _check_issued(rows.get(result.throw_id), result)
                    except UnknownThrow as e:
                        out[i] = e
                        continue
                    if isinstance(tmp, Exception):
                        out[i] = tmp
                        continue
                    rel = None
                    if tmp is not None:
                        rel = self._telemetry_rel(result.throw_id)
                        os.replace(tmp, self.data_dir / rel)
                    _apply_result(rows[result.throw_id], result, rel, now)
                    out[i] = rows[result.throw_id]
        finally:
            for tmp, o in zip(staged, out):
                if isinstance(tmp, Path) and not isinstance(o, Throw):
                    tmp.unlink(missing_ok=True)
        for r, o in zip(results, out):
            if isinstance(o, Throw):
                log.info("stored result of throw %s: %s", r.throw_id, r.status)
        return [o for o in out if o is not None]  # every slot is filled: one per result

    def mark_lost(self, throw_id: str, reason: str) -> bool:
        """Close an open throw as ``lost`` with ``reason``; False if it is already final (or
        unknown). One conditional UPDATE, so a result stored meanwhile by another thread or
        server is never overwritten; an open throw never counts in the accuracy aggregates
        (server.db.aggregates), so they need no change."""
        with self.sessions.begin() as db:
            done = db.execute(update(Throw).where(Throw.id == throw_id, Throw.status.not_in(FINAL_STATUSES))
                              .values(status="lost", failure_reason=reason, completed_at=utcnow())
                              .execution_options(synchronize_session=False))
        return rowcount(done) == 1


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
    """Get or add the machine row inside ``db``'s transaction, refreshing last_seen_at. Safe
    against a concurrent first sighting of the same machine (the fleet's thread and an API
    request): :func:`server.db.upsert.insert_if_absent`.

    Raises:
        RuntimeError: the row was neither inserted nor found (machine rows are never deleted).
    """
    inserted = insert_if_absent(db, Machine, ["id"], id=machine_id, simulated=simulated)
    row = db.get(Machine, machine_id, populate_existing=True)
    if row is None:  # machine rows are never deleted: a row that conflicted is there once committed
        raise RuntimeError(f"machine row {machine_id!r} neither inserted nor found")
    if not inserted:
        row.last_seen_at = utcnow()
        row.simulated = simulated or row.simulated
    return row


def _safe_name(throw_id: str) -> str:
    """Throw ids become file names: keep only [A-Za-z0-9_-] (they are UUIDs in practice)."""
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in throw_id)


def _stage_all(store: ResultStore, results: list[ThrowResult]) -> list[Path | None | Exception]:
    """:meth:`ResultStore.stage_telemetry` of each result, concurrently (the fsyncs overlap)."""
    def stage(result: ThrowResult) -> Path | None | Exception:
        try:
            return store.stage_telemetry(result)
        except (ValueError, OSError) as e:
            return e

    if sum(1 for r in results if r.telemetry_mcap_b64) < 2:
        return [stage(r) for r in results]
    with ThreadPoolExecutor(max_workers=min(8, len(results))) as pool:
        return list(pool.map(stage, results))


def _write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
