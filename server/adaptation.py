"""Adaptation runs: a diagnosis result -> ``sim_twin.adapt.adapt`` -> a new policy version.

The console's flow is diagnose -> adapt -> twin-evaluate -> promote: an operator starts an
adaptation on a finished diagnosis run (its fitted profile and 1 sigma, never a profile file)
for one mode; the base policy is the version the diagnosed machine runs in that mode (or a named
version). The aim correction is computed in the CPU twin by an ``adaptation`` job in a worker
process (server.jobs; the heavy part), the result is registered through
:meth:`server.policies.PolicyService.add_version`, which starts its twin evaluation on the site's
fitted profile; promotion is the Policies page's. Files live under
``<data_dir>/adaptation/<run_id>/`` (status.json, the version, its adaptation.json).
"""

from __future__ import annotations

import json
import logging
import uuid
from datetime import UTC, datetime
from pathlib import Path

from sqlalchemy import select

from server.db.models import PolicyVersion
from server.diagnosis import RUN_ID, DiagnosisRuns
from server.errors import Conflict, NotFound, Refused

log = logging.getLogger(__name__)


class AdaptationRuns:
    """Start, list and read adaptation runs (one at a time: it uses every core).

    Args:
        diagnosis: the diagnosis runs (fitted profiles and reports).
        policies: server.policies.PolicyService (base files, new versions).
        previews: server.previews.PreviewService (which version a machine runs).
        data_dir: the server's data folder.
        workers: processes per twin evaluation (default: all cores).
        jobs: the job queue (server.jobs.JobQueue) runs are submitted to.
    """

    def __init__(self, diagnosis: DiagnosisRuns, policies, previews, data_dir: Path, workers: int | None = None,
                 jobs=None):
        self.diagnosis, self.policies, self.previews, self.jobs = diagnosis, policies, previews, jobs
        self.data_dir = Path(data_dir)
        self.root = self.data_dir / "adaptation"
        self.workers = workers
        self._job_id: str | None = None

    def start(self, diagnosis_id: str, mode: str, username: str, base_version: str | None = None, throws: int = 20,
              rounds: int = 2) -> dict:
        """Check the inputs and submit the adaptation job; returns the initial status.

        Raises:
            NotFound: no such diagnosis. Refused: a bad mode. Conflict: diagnosis not done / adaptation running /
                no base policy file, 422 bad mode.
        """
        if mode not in ("2d", "3d"):
            raise Refused(f"mode must be '2d' or '3d', got {mode!r}")
        st = self.diagnosis.get(diagnosis_id)
        if st is None:
            raise NotFound(f"no diagnosis run {diagnosis_id}")
        profile = self.diagnosis.file(diagnosis_id, "profile_fitted.json")
        if st.get("status") != "done" or profile is None:
            raise Conflict(f"diagnosis {diagnosis_id} is {st.get('status')}; adapt a finished one")
        base = self._base(st["machine_id"], mode, base_version)
        if any(s.get("status") in ("queued", "running") for s in self.list()):
            raise Conflict("an adaptation is already running; wait for it to finish")
        run_id = f"{datetime.now(UTC):%Y%m%dT%H%M%S}-{uuid.uuid4().hex[:6]}"
        status = {"id": run_id, "diagnosis_id": diagnosis_id, "machine_id": st["machine_id"], "mode": mode,
                  "base_version": base.name, "status": "queued", "error": None, "progress": [],
                  "policy_version_id": None, "policy_version": None, "started_at": _now(), "finished_at": None,
                  "requested_by": username}
        self._write(run_id, status)
        params = {"run_id": run_id, "profile": json.loads(profile.read_text()), "report": st.get("report"),
                  "base_path": base.onnx_path, "throws": throws, "rounds": rounds, "workers": self.workers}
        self._job_id = self.jobs.submit("adaptation", params, subject=st["machine_id"], requested_by=username)
        return {**(self.get(run_id) or status), "job_id": self._job_id}

    def _base(self, machine_id: str, mode: str, name: str | None) -> PolicyVersion:
        with self.policies.sessions() as db:
            if name is None:
                name = self.previews.active_policy(machine_id, mode)[2]
            row = db.scalar(select(PolicyVersion).where(PolicyVersion.name == name, PolicyVersion.mode == mode)
                            .order_by(PolicyVersion.id.desc()))
        if row is None or not row.onnx_path or not (self.policies.store.data_dir / row.onnx_path).is_file():
            raise Conflict(f"the server has no file of {mode} policy {name!r} to adapt")
        return row

    def run(self, params: dict, progress) -> dict:
        """The job's body (in a worker): adapt, register the version (its evaluation is another
        job), write status.json; returns the status. ``progress(fraction, message)`` per line.

        Raises:
            server.jobs.JobCancelled: from ``progress`` (status.json says failed: cancelled).
        """
        from server.jobs.store import JobCancelled
        from sim_twin.adapt import adapt

        status = self.get(params["run_id"])
        status.update(status="running")
        self._write(status["id"], status)

        def line(text: str) -> None:
            status["progress"].append(text)
            self._write(status["id"], status)
            progress(min(0.95, 0.05 * len(status["progress"])), text)

        try:
            name = f"{status['base_version']}-{status['machine_id']}-{status['id'][-6:]}"
            res = adapt(params["profile"], self.data_dir / params["base_path"], self.root / status["id"], name=name,
                        method="aim", diagnosis_report=params["report"], throws=params["throws"],
                        rounds=params["rounds"], workers=params["workers"], progress=line)
            row = self.policies.add_version(res["manifest"], Path(res["policy"]), status["requested_by"],
                                            notes=f"adapted to diagnosis {status['diagnosis_id']} of {status['machine_id']}",
                                            action="policy_adapt")
            status.update(status="done", policy_version_id=row.id, policy_version=row.name)
        except JobCancelled:
            status.update(status="failed", error="cancelled")
            raise
        except Exception as e:  # reported in status.json for the page
            log.exception("adaptation %s failed", status["id"])
            status.update(status="failed", error=f"{type(e).__name__}: {e}")
        finally:
            status["finished_at"] = _now()
            self._write(status["id"], status)
        return status

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until the last run started here finishes (tests)."""
        if self._job_id is not None:
            self.jobs.wait(self._job_id, timeout_s if timeout_s is not None else 3600.0)

    def list(self) -> list[dict]:
        """Statuses of all runs, newest first."""
        if not self.root.is_dir():
            return []
        return [s for d in sorted(self.root.iterdir(), reverse=True) if (s := self.get(d.name))]

    def get(self, run_id: str) -> dict | None:
        if not RUN_ID.match(run_id or ""):
            return None
        try:
            return json.loads((self.root / run_id / "status.json").read_text())
        except (OSError, json.JSONDecodeError):
            return None

    def _write(self, run_id: str, status: dict) -> None:
        d = self.root / run_id
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / "status.json.tmp"
        tmp.write_text(json.dumps(status, indent=1))
        tmp.replace(d / "status.json")


def _now() -> str:
    return datetime.now(UTC).isoformat()
