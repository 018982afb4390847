"""Sim-to-real gap diagnosis runs on a machine's stored throws (files only, no database tables).

A run exports the machine's latest landed throws with telemetry to a dataset directory
(sim_twin.diagnosis.dataset format), runs :func:`sim_twin.diagnosis.diagnose.diagnose` in a
background thread and keeps everything under ``<data_dir>/diagnosis/<run_id>/``::

    status.json   {"id", "machine_id", "status": running|done|failed, "error", "started_at", ...}
    dataset/      index.json + throws/*.mcap
    report/       report.json, profile_fitted.json, where.png, traces.png, which.png, how_far.png

One run at a time (the diagnosis uses every core).
"""

from __future__ import annotations

import json
import logging
import re
import threading
import uuid
from datetime import UTC, datetime
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from runtime.telemetry import read_telemetry
from server.db.models import Throw

log = logging.getLogger(__name__)

RUN_ID = re.compile(r"^[0-9]{8}T[0-9]{6}-[0-9a-f]{6}$")
REPORT_FILES = ("report.json", "profile_fitted.json", "where.png", "traces.png", "which.png", "how_far.png")


class DiagnosisBusy(RuntimeError):
    """A diagnosis is already running."""


class DiagnosisRuns:
    """Start, list and read diagnosis runs.

    Args:
        sessions: database session factory (stored throws).
        data_dir: the server's data folder (telemetry paths are relative to it).
        workers: processes per diagnosis (default: all cores).
    """

    def __init__(self, sessions: sessionmaker[Session], data_dir: Path, workers: int | None = None):
        self.sessions = sessions
        self.workers = workers
        self.data_dir = Path(data_dir)
        self.root = self.data_dir / "diagnosis"
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    # --- export -----------------------------------------------------------------------------
    def export(self, machine_id: str, limit: int, directory: Path) -> int:
        """Write the machine's newest ``limit`` landed throws with telemetry as a dataset.

        The impact time is the telemetry's "landed" event (the executor stamps it at the
        impact report, within one 10 ms tick). Returns the number of throws written.
        """
        from sim_twin.diagnosis.dataset import write

        with self.sessions() as db:
            rows = list(db.scalars(select(Throw).where(Throw.machine_id == machine_id, Throw.status == "landed",
                                                       Throw.telemetry_path.is_not(None)).order_by(Throw.requested_at.desc()).limit(limit)))
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
    def start(self, machine_id: str, limit: int = 50, requested_by: str | None = None, workers: int | None = None) -> dict:
        """Export and diagnose in the background; returns the initial status.

        Raises:
            DiagnosisBusy: a run is in progress.
            ValueError: the machine has fewer than 4 landed throws with telemetry.
        """
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                raise DiagnosisBusy("a diagnosis is already running; wait for it to finish")
            run_id = f"{datetime.now(UTC):%Y%m%dT%H%M%S}-{uuid.uuid4().hex[:6]}"
            run_dir = self.root / run_id
            n = self.export(machine_id, limit, run_dir / "dataset")
            if n < 4:
                raise ValueError(f"machine {machine_id!r} has {n} landed throws with telemetry; a diagnosis needs at least 4")
            status = {"id": run_id, "machine_id": machine_id, "throws": n, "status": "running", "error": None,
                      "started_at": _now(), "finished_at": None, "requested_by": requested_by, "verdict": None}
            self._write_status(run_dir, status)
            args = (run_dir, status, workers or self.workers)
            self._thread = threading.Thread(target=self._run, args=args, name=f"diagnosis-{run_id}", daemon=True)
            self._thread.start()
            return status

    def _run(self, run_dir: Path, status: dict, workers: int | None) -> None:
        from sim_twin.diagnosis.diagnose import diagnose

        try:
            report = diagnose(run_dir / "dataset", run_dir / "report", workers=workers)
            status.update(status="done", verdict=report["verdict"])
        except Exception as e:  # reported in status.json for the page
            log.exception("diagnosis %s failed", status["id"])
            status.update(status="failed", error=f"{type(e).__name__}: {e}")
        status["finished_at"] = _now()
        self._write_status(run_dir, status)

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until the current run (if any) finishes (tests)."""
        if self._thread is not None:
            self._thread.join(timeout_s)

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
