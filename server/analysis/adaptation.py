"""Adaptation runs: a diagnosis result -> ``sim_twin.adaptation.adapt.adapt`` -> a new policy version (API side).

The console's flow is diagnose -> adapt -> twin-evaluate -> promote: an operator starts an
adaptation on a finished diagnosis run (its fitted profile and 1 sigma, never a profile file)
for one mode; the base policy is the version the diagnosed machine runs in that mode (or a named
version). The aim correction is computed in the CPU twin by an ``adaptation`` job in a worker
(server.analysis.adaptation_job); the result is registered through
:meth:`server.policies.versions.PolicyService.add_version`, which starts its twin evaluation on the site's
fitted profile; promotion is the Policies page's. A run is its job: the row is its only state,
its files live under the job's folder.
"""

from __future__ import annotations

import json

from sqlalchemy import select

from server.analysis.diagnosis import ACTIVE, RUN_ID, DiagnosisRuns
from server.db.models import PolicyVersion
from server.errors import Conflict, NotFound, Refused


def adaptation_view(job: dict) -> dict:
    """The run as the console shows it, from its job row.

    Returns:
        {"id", "job_id", "diagnosis_id", "machine_id", "mode", "base_version", "status":
        queued|running|done|failed, "error", "progress" (the adaptation's log lines so far),
        "policy_version_id", "policy_version", "started_at", "finished_at", "requested_by"}.
    """
    p, r = job.get("params") or {}, job.get("result") or {}
    status, error = job["status"], job.get("error")
    if status == "cancelled":
        status, error = "failed", "cancelled"
    lines = r.get("lines") or ([job["message"]] if job.get("message") else [])
    return {"id": job["id"], "job_id": job["id"], "diagnosis_id": p.get("diagnosis_id"), "machine_id": p.get("machine_id"),
            "mode": p.get("mode"), "base_version": p.get("base_version"), "status": status, "error": error,
            "progress": lines, "policy_version_id": r.get("policy_version_id"), "policy_version": r.get("policy_version"),
            "started_at": job["created_at"], "finished_at": job.get("finished_at"), "requested_by": job.get("requested_by")}


class AdaptationRuns:
    """Start, list and read adaptation runs (one at a time: it uses every core).

    Args:
        diagnosis: the diagnosis runs (fitted profiles and reports).
        policies: server.policies.versions.PolicyService (base files).
        previews: server.throws.previews.PreviewService (which version a machine runs).
        jobs: the job queue (server.jobs.JobQueue): runs are its ``adaptation`` jobs.
        workers: processes per twin evaluation (default: all cores).
    """

    def __init__(self, diagnosis: DiagnosisRuns, policies, previews, jobs, workers: int | None = None):
        self.diagnosis, self.policies, self.previews, self.jobs = diagnosis, policies, previews, jobs
        self.workers = workers
        self._job_id: str | None = None

    def start(self, diagnosis_id: str, mode: str, username: str, base_version: str | None = None, throws: int = 20,
              rounds: int = 2) -> dict:
        """Check the inputs and submit the adaptation job; returns the run.

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
        if any(j["status"] in ACTIVE for j in self.jobs.store.list(kind="adaptation", limit=20)):
            raise Conflict("an adaptation is already running; wait for it to finish")
        spec = {"diagnosis_id": diagnosis_id, "machine_id": st["machine_id"], "mode": mode, "base_version": base.name,
                "base_path": base.onnx_path, "profile": json.loads(profile.read_text()), "report": st.get("report"),
                "throws": throws, "rounds": rounds, "workers": self.workers}
        self._job_id = self.jobs.submit("adaptation", spec, subject=st["machine_id"], requested_by=username)
        run = self.get(self._job_id)
        if run is None:
            raise RuntimeError(f"adaptation job {self._job_id} not found right after it was submitted")
        return run

    def _base(self, machine_id: str, mode: str, name: str | None) -> PolicyVersion:
        with self.policies.sessions() as db:
            if name is None:
                name = self.previews.active_policy(machine_id, mode)[2]
            row = db.scalar(select(PolicyVersion).where(PolicyVersion.name == name, PolicyVersion.mode == mode)
                            .order_by(PolicyVersion.id.desc()))
        if row is None or not row.onnx_path or not (self.policies.store.data_dir / row.onnx_path).is_file():
            raise Conflict(f"the server has no file of {mode} policy {name!r} to adapt")
        return row

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until the last run started here finishes (tests)."""
        if self._job_id is not None:
            self.jobs.wait(self._job_id, timeout_s if timeout_s is not None else 3600.0)

    def list(self, limit: int = 100) -> list[dict]:
        """Runs newest first."""
        return [adaptation_view(j) for j in self.jobs.store.list(kind="adaptation", limit=limit, with_result=True)]

    def get(self, run_id: str) -> dict | None:
        """The run, or None for an unknown or malformed id."""
        if not RUN_ID.match(run_id or ""):
            return None
        job = self.jobs.store.get(run_id)
        return adaptation_view(job) if job is not None and job["kind"] == "adaptation" else None
