"""Sim-to-real gap diagnosis runs on a machine's stored throws (files only, no database tables).

A run is a ``diagnosis`` job in a worker process (server.jobs): it exports the machine's latest
landed throws with telemetry to a dataset directory (sim_twin.diagnosis.dataset format), runs
:func:`sim_twin.diagnosis.diagnose.diagnose` and keeps everything under
``<data_dir>/diagnosis/<run_id>/`` (workers on other hosts share the data dir)::

    status.json   {"id", "job_id", "machine_id", "status": queued|running|done|failed, "error", ...}
    upload/       an uploaded rosbag2 set (server.diagnosis_upload), converted into dataset/
    dataset/      index.json + throws/*.mcap
    report/       report.json, profile_fitted.json, where.png, which.png, how_far.png

One run at a time (the diagnosis uses every core of its worker).
"""

from __future__ import annotations

import json
import logging
import re
import uuid
from datetime import UTC, datetime
from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from runtime.telemetry import read_telemetry
from server.db.models import Throw

log = logging.getLogger(__name__)

RUN_ID = re.compile(r"^[0-9]{8}T[0-9]{6}-[0-9a-f]{6}$")
REPORT_FILES = ("report.json", "profile_fitted.json", "where.png", "which.png", "how_far.png")


class DiagnosisBusy(RuntimeError):
    """A diagnosis is already running."""


class DiagnosisRuns:
    """Start, list and read diagnosis runs.

    Args:
        sessions: database session factory (stored throws).
        data_dir: the server's data folder (telemetry paths are relative to it).
        workers: processes per diagnosis (default: all cores).
        jobs: the job queue (server.jobs.JobQueue) runs are submitted to; needed by :meth:`start`.
    """

    def __init__(self, sessions: sessionmaker[Session], data_dir: Path, workers: int | None = None, jobs=None):
        self.sessions = sessions
        self.workers = workers
        self.jobs = jobs
        self.data_dir = Path(data_dir)
        self.root = self.data_dir / "diagnosis"
        self._job_id: str | None = None

    # --- export -----------------------------------------------------------------------------
    def export(self, machine_id: str, limit: int, directory: Path) -> int:
        """Write the machine's newest ``limit`` landed throws with telemetry as a dataset.

        The impact time is the telemetry's "landed" event (the executor stamps it at the
        impact report, within one 10 ms tick). Returns the number of throws written.
        """
        from sim_twin.diagnosis.dataset import write

        with self.sessions() as db:
            rows = list(db.scalars(select(Throw).where(*self._landed_with_telemetry(machine_id))
                                   .order_by(Throw.requested_at.desc()).limit(limit)))
        out = []
        for t in rows:
            path = self.data_dir / t.telemetry_path
            try:
                data = path.read_bytes()
                tel = read_telemetry(data)
            except Exception as e:  # noqa: BLE001  a missing or corrupt file drops that throw, not the run
                log.warning("throw %s: telemetry %s unusable (%s), skipped", t.id, path, e)
                continue
            landed = [s for s, p in zip(tel["event_t_s"], tel["event_phase"]) if p == "landed"]
            out.append(({"throw_id": t.id, "mode": t.mode, "target_m": t.target_m, "impact_m": t.impact_m,
                         "impact_stamp_s": float(landed[0]) if landed else None, "status": t.status,
                         "policy_version": t.policy_version}, data))
        write(directory, out, machine_id=machine_id, source={"exported_from": "slinger server", "limit": limit})
        return len(out)

    # --- runs -------------------------------------------------------------------------------
    def _landed_with_telemetry(self, machine_id: str):
        return (Throw.machine_id == machine_id, Throw.status == "landed", Throw.telemetry_path.is_not(None))

    def start(self, machine_id: str, limit: int = 50, requested_by: str | None = None, workers: int | None = None) -> dict:
        """Submit a diagnosis job (export + diagnose in a worker); returns the initial status.

        Raises:
            DiagnosisBusy: a run is queued or in progress.
            ValueError: the machine has fewer than 4 landed throws with telemetry.
        """
        if any(st.get("status") in ("queued", "running") for st in self.list()):
            raise DiagnosisBusy("a diagnosis is already running; wait for it to finish")
        with self.sessions() as db:
            n = db.scalar(select(func.count()).select_from(Throw).where(*self._landed_with_telemetry(machine_id)))
        n = min(int(n or 0), limit)
        if n < 4:
            raise ValueError(f"machine {machine_id!r} has {n} landed throws with telemetry; a diagnosis needs at least 4")
        run_id = f"{datetime.now(UTC):%Y%m%dT%H%M%S}-{uuid.uuid4().hex[:6]}"
        status = {"id": run_id, "job_id": None, "machine_id": machine_id, "throws": n, "status": "queued",
                  "error": None, "started_at": _now(), "finished_at": None, "requested_by": requested_by,
                  "verdict": None}
        self._write_status(self.root / run_id, status)
        self._job_id = self.jobs.submit("diagnosis", {"run_id": run_id, "machine_id": machine_id, "limit": limit,
                                                      "workers": workers or self.workers},
                                        subject=machine_id, requested_by=requested_by)
        status = self._read_status(self.root / run_id) or status
        if status.get("job_id") is None:
            status["job_id"] = self._job_id
        return status

    def start_upload(self, machine_id: str, bags: list[tuple[str, bytes]], mapping: tuple[str, bytes], impacts: bytes,
                     requested_by: str | None = None, workers: int | None = None, max_bytes: int | None = None) -> dict:
        """Store an uploaded set of rosbag2 bags (server.diagnosis_upload) and submit a diagnosis
        job that converts and diagnoses them; returns the initial status.

        Raises:
            DiagnosisBusy: a run is queued or in progress.
            server.diagnosis_upload.UploadError: the upload cannot be used (nothing is kept).
        """
        from server.diagnosis_upload import store_upload

        if any(st.get("status") in ("queued", "running") for st in self.list()):
            raise DiagnosisBusy("a diagnosis is already running; wait for it to finish")
        run_id = f"{datetime.now(UTC):%Y%m%dT%H%M%S}-{uuid.uuid4().hex[:6]}"
        ids = store_upload(self.root / run_id / "upload", bags, mapping, impacts, max_bytes=max_bytes)
        status = {"id": run_id, "job_id": None, "machine_id": machine_id, "throws": len(ids), "status": "queued",
                  "error": None, "started_at": _now(), "finished_at": None, "requested_by": requested_by,
                  "verdict": None, "source": "rosbag2 upload"}
        self._write_status(self.root / run_id, status)
        self._job_id = self.jobs.submit("diagnosis", {"run_id": run_id, "machine_id": machine_id, "limit": len(ids),
                                                      "workers": workers or self.workers, "upload": True},
                                        subject=machine_id, requested_by=requested_by)
        status = self._read_status(self.root / run_id) or status
        if status.get("job_id") is None:
            status["job_id"] = self._job_id
        return status

    def run(self, run_id: str, machine_id: str, limit: int, workers: int | None, progress, upload: bool = False) -> dict:
        """The job's body (in a worker): export (or, for an upload, convert the bags:
        sim_twin.diagnosis.rosbag), diagnose, write status.json; returns the status.

        Raises:
            server.jobs.JobCancelled: from ``progress`` (status.json says failed: cancelled).
        """
        from server.jobs.store import JobCancelled
        from sim_twin.diagnosis.diagnose import diagnose

        run_dir = self.root / run_id
        status = self._read_status(run_dir) or {"id": run_id, "machine_id": machine_id, "requested_by": None}
        status.update(status="running", error=None)
        self._write_status(run_dir, status)
        try:
            if upload:
                from server.diagnosis_upload import uploaded
                from sim_twin.diagnosis import rosbag

                progress(0.0, "converting the uploaded bags")
                rosbag.convert(*uploaded(run_dir / "upload"), run_dir / "dataset")
            else:
                progress(0.0, "exporting throws")
                status["throws"] = self.export(machine_id, limit, run_dir / "dataset")
            progress(0.1, f"diagnosing {status['throws']} throws")
            report = diagnose(run_dir / "dataset", run_dir / "report", workers=workers)
            status.update(status="done", verdict=report["verdict"])
        except JobCancelled:
            status.update(status="failed", error="cancelled")
            raise
        except Exception as e:  # reported in status.json for the page
            log.exception("diagnosis %s failed", run_id)
            status.update(status="failed", error=f"{type(e).__name__}: {e}")
        finally:
            status["finished_at"] = _now()
            self._write_status(run_dir, status)
        return status

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until the last run started here finishes (tests)."""
        if self._job_id is not None:
            self.jobs.wait(self._job_id, timeout_s if timeout_s is not None else 3600.0)

    def list(self, machine_id: str | None = None) -> list[dict]:
        """Statuses of all runs, newest first."""
        if not self.root.is_dir():
            return []
        out = []
        for d in sorted(self.root.iterdir(), reverse=True):
            st = self._read_status(d)
            if st and (machine_id is None or st.get("machine_id") == machine_id):
                out.append(st)
        return out

    def get(self, run_id: str) -> dict | None:
        """Status plus the report (when done) of one run, or None."""
        d = self.run_dir(run_id)
        st = self._read_status(d) if d else None
        if st is None:
            return None
        report = d / "report" / "report.json"
        if st.get("status") == "done" and report.is_file():
            st = {**st, "report": json.loads(report.read_text())}
        return st

    def run_dir(self, run_id: str) -> Path | None:
        """The run's folder, None for a malformed id (no path tricks)."""
        return self.root / run_id if RUN_ID.match(run_id or "") else None

    def file(self, run_id: str, name: str) -> Path | None:
        """A report file of a run, or None."""
        d = self.run_dir(run_id)
        if d is None or name not in REPORT_FILES:
            return None
        p = d / "report" / name
        return p if p.is_file() else None

    @staticmethod
    def _write_status(run_dir: Path, status: dict) -> None:
        run_dir.mkdir(parents=True, exist_ok=True)
        tmp = run_dir / "status.json.tmp"
        tmp.write_text(json.dumps(status, indent=1))
        tmp.replace(run_dir / "status.json")

    @staticmethod
    def _read_status(run_dir: Path) -> dict | None:
        try:
            return json.loads((run_dir / "status.json").read_text())
        except (OSError, json.JSONDecodeError):
            return None


def _now() -> str:
    return datetime.now(UTC).isoformat()
