"""Sim-to-real gap diagnosis runs on a machine's stored throws or on uploaded rosbag2 bags (API side).

A run is a ``diagnosis`` job (server.jobs): its row is the run's only state (status, progress,
error, result), its id is the run id, and its files (dataset, report and plots) live under the
job's folder ``<data_dir>/jobs/<job_id>/`` (server.analysis.diagnosis_job, in a worker; workers on
other hosts share the data dir). One run at a time (the diagnosis uses every core of its worker).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from server.analysis.diagnosis_job import landed_with_telemetry
from server.db.models import Throw
from server.errors import Conflict, Refused
from server.jobs.specs import job_dir

RUN_ID = re.compile(r"^[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}$")
"""A run id is its job's id (a UUID): nothing else reaches the file system."""
REPORT_FILES = ("report.json", "profile_fitted.json", "where.png", "which.png", "how_far.png")
ACTIVE = ("queued", "running")


class DiagnosisBusy(Conflict, RuntimeError):
    """A diagnosis is already queued or running."""


class TooFewThrows(Refused, ValueError):
    """The machine has too few landed throws with telemetry for a diagnosis."""


def run_view(job: dict) -> dict:
    """The run as the console shows it, from its job row (server.jobs.store.as_dict).

    Returns:
        {"id", "job_id", "machine_id", "throws", "status": queued|running|done|failed, "error",
        "progress" (0..1), "message", "started_at", "finished_at", "requested_by", "verdict", "source"
        ("stored throws" or "rosbag2 upload")}; a
        cancelled job reads as failed with error "cancelled".
    """
    result, params = job.get("result") or {}, job.get("params") or {}
    status, error = job["status"], job.get("error")
    if status == "cancelled":
        status, error = "failed", "cancelled"
    return {"id": job["id"], "job_id": job["id"], "machine_id": params.get("machine_id"),
            "throws": result.get("throws", params.get("limit")), "status": status, "error": error,
            "progress": job.get("progress"), "message": job.get("message"), "started_at": job["created_at"],
            "finished_at": job.get("finished_at"), "requested_by": job.get("requested_by"),
            "verdict": result.get("verdict"), "source": "rosbag2 upload" if params.get("upload") else "stored throws"}


class DiagnosisRuns:
    """Start, list and read diagnosis runs.

    Args:
        sessions: database session factory (stored throws).
        jobs: the job queue (server.jobs.JobQueue): runs are its ``diagnosis`` jobs.
        data_dir: the server's data folder.
        workers: processes per diagnosis (default: all cores of the worker).
    """

    def __init__(self, sessions: sessionmaker[Session], jobs, data_dir: Path, workers: int | None = None):
        self.sessions, self.jobs, self.workers = sessions, jobs, workers
        self.data_dir = Path(data_dir)
        self._job_id: str | None = None
        self.effects_catalog: dict | None = None
        """The effects library as a worker described it (GET /api/diagnosis/effects), kept once fetched."""

    def start(self, machine_id: str, limit: int = 50, requested_by: str | None = None, workers: int | None = None) -> dict:
        """Submit a diagnosis job (export + diagnose in a worker); returns the run.

        Raises:
            DiagnosisBusy: a run is queued or in progress.
            TooFewThrows (a ValueError): the machine has fewer than 4 landed throws with telemetry.
            server.jobs.specs.JobSpecError (a Refused): bad job parameters.
        """
        if any(j["status"] in ACTIVE for j in self.jobs.store.list(kind="diagnosis", limit=20)):
            raise DiagnosisBusy("a diagnosis is already running; wait for it to finish")
        with self.sessions() as db:
            n = db.scalar(select(func.count()).select_from(Throw).where(*landed_with_telemetry(machine_id)))
        n = min(int(n or 0), limit)
        if n < 4:
            raise TooFewThrows(f"machine {machine_id!r} has {n} landed throws with telemetry; a diagnosis needs at least 4")
        self._job_id = self.jobs.submit("diagnosis", {"machine_id": machine_id, "limit": limit,
                                                      "workers": workers or self.workers},
                                        subject=machine_id, requested_by=requested_by)
        return self._submitted(self._job_id)

    def start_upload(self, machine_id: str, bags: list[tuple[str, bytes]], mapping: tuple[str, bytes], impacts: bytes,
                     requested_by: str | None = None, workers: int | None = None, max_bytes: int | None = None) -> dict:
        """Store an uploaded set of rosbag2 bags (server.analysis.diagnosis_upload) and submit a diagnosis
        job that converts and diagnoses them; returns the run.

        Raises:
            DiagnosisBusy: a run is queued or in progress.
            server.analysis.diagnosis_upload.UploadError: the upload cannot be used (nothing is kept).
        """
        from server.analysis.diagnosis_upload import new_upload_id, store_upload, upload_dir

        if any(j["status"] in ACTIVE for j in self.jobs.store.list(kind="diagnosis", limit=20)):
            raise DiagnosisBusy("a diagnosis is already running; wait for it to finish")
        upload = new_upload_id()
        ids = store_upload(upload_dir(self.data_dir, upload), bags, mapping, impacts, max_bytes=max_bytes)
        self._job_id = self.jobs.submit("diagnosis", {"machine_id": machine_id, "limit": len(ids), "upload": upload,
                                                      "workers": workers or self.workers},
                                        subject=machine_id, requested_by=requested_by)
        return self._submitted(self._job_id)

    def _submitted(self, job_id: str) -> dict:
        """The run just submitted (without its report).

        Raises:
            RuntimeError: the job store does not have it (a bug: it was just written).
        """
        run = self.get(job_id, with_report=False)
        if run is None:
            raise RuntimeError(f"diagnosis job {job_id} not found right after it was submitted")
        return run

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until the last run started here finishes (tests)."""
        if self._job_id is not None:
            self.jobs.wait(self._job_id, timeout_s if timeout_s is not None else 3600.0)

    def list(self, machine_id: str | None = None, limit: int = 100) -> list[dict]:
        """Runs newest first (without reports)."""
        return [run_view(j) for j in self.jobs.store.list(kind="diagnosis", subject=machine_id, limit=limit,
                                                                      with_result=True)]

    def get(self, run_id: str, with_report: bool = True) -> dict | None:
        """The run, plus its report once it is done; None for an unknown or malformed id."""
        if not RUN_ID.match(run_id or ""):
            return None
        job = self.jobs.store.get(run_id)
        if job is None or job["kind"] != "diagnosis":
            return None
        view = run_view(job)
        report = job_dir(self.data_dir, run_id) / "report" / "report.json"
        if with_report and view["status"] == "done" and report.is_file():
            view["report"] = json.loads(report.read_text())
        return view

    def file(self, run_id: str, name: str) -> Path | None:
        """A report file of a run (a regular file inside the run's report folder), or None."""
        if not RUN_ID.match(run_id or "") or name not in REPORT_FILES:
            return None
        folder = job_dir(self.data_dir, run_id) / "report"
        p = folder / name
        if p.is_symlink() or not p.is_file() or p.resolve().parent != folder.resolve():
            return None
        return p
