"""Previews: run the machine's active policy in the CPU twin (sim_twin.preview.preview) from its current
joint state, as a ``preview`` job in a worker (the API process never imports MuJoCo), and keep
the result in the job's row so that a throw can be sent "as previewed", also after a restart.

The policy file comes from the server's copy of the policy version the runtime reports
(RuntimeInfo sha256 -> policy_versions.onnx_path); workers cache loaded runners by SHA-256.
"""

from __future__ import annotations

import logging
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from runtime.release_check import DEFAULT_RADIUS_M
from server.db.models import PolicyVersion
from server.db.types import utcnow
from server.errors import KINDS, Conflict, Failed, Refused, Unavailable, found
from server.fleet.link import Fleet
from server.jobs import JobQueue
from server.throws.gate import preview_refusal
from server.throws.service import ThrowService

log = logging.getLogger(__name__)


class PreviewService:
    """Makes and remembers previews.

    Args:
        fleet: machine states and runtime infos.
        sessions: database sessions (policy versions).
        throws: the throw service (its target checks are the previews' too).
        jobs: the job queue (previews run on its fast lane).
        data_dir: where policy files live (policy_versions.onnx_path is relative to it).
        clearance_radius_m: see server.config.Settings.
        profile_path: the site's reality profile with its uncertainty (Settings.preview_profile;
            None: sim_twin.preview.preview.DEFAULT_SITE_PROFILE); a policy version's own fitted profile
            takes precedence (sim_twin.preview.preview.site_profile).

    Raises:
        ValueError / OSError: the site profile cannot be read (checked at start).
    """

    def __init__(self, fleet: Fleet, sessions: sessionmaker[Session], throws: ThrowService, jobs: JobQueue,
                 data_dir: Path, clearance_radius_m: float = 12.0, profile_path: Path | None = None,
                 release_check_radius_m: float | None = DEFAULT_RADIUS_M):
        self.fleet, self.sessions, self.throws, self.jobs = fleet, sessions, throws, jobs
        self.data_dir = Path(data_dir)
        self.clearance_radius_m = clearance_radius_m
        self.release_check_radius_m = release_check_radius_m
        self.profile_path = profile_path

    def get(self, preview_id: str) -> dict | None:
        """The stored summary of a finished preview, None if unknown or not a finished preview."""
        return _summary(self.jobs.store.get(preview_id))

    def require(self, preview_id: str) -> dict:
        """:meth:`get`, for a preview that must exist.

        Raises:
            NotFound: unknown, expired or not a finished preview.
        """
        return found(self.get(preview_id), f"no preview {preview_id} (previews are kept for a while only)")

    def active_policy(self, machine_id: str, mode: str) -> tuple[str, str, str]:
        """(ONNX path relative to the data dir, SHA-256, version name) of the policy
        ``machine_id`` runs for ``mode``.

        Raises:
            Refused: no policy for the mode. Conflict: the server has no file of it.
        """
        info = self.fleet.fresh_info(machine_id, max_age_s=2.0, timeout_s=1.0)
        pol = next((p for p in (info.policies if info else []) if p.mode == mode), None)
        if pol is None:
            raise Refused(f"machine {machine_id} runs no {mode} policy")
        with self.sessions() as db:
            row = db.scalar(select(PolicyVersion).where(PolicyVersion.sha256 == pol.sha256))
        if row is None or not row.onnx_path or not (self.data_dir / row.onnx_path).is_file():
            raise Conflict(f"the server has no file of policy {pol.version} ({pol.sha256[:12]}…): "
                                    "upload that version to preview it")
        return row.onnx_path, pol.sha256, pol.version

    def submit(self, machine_id: str, mode: str, target: list[float], rollouts: int,
               requested_by: str | None = None, extends: str | None = None) -> str:
        """Check the target (as a throw would be checked) and submit the preview job; returns
        its id (= the preview id).

        ``extends``: the id of a preview of the same request (machine, mode, target) to complete,
        the console's nominal-only preview before its ellipse: this preview then starts from that
        one's machine state, so that the worker reuses its nominal rollout (sim_twin.preview.preview
        .NominalCache) and the nominal shown does not change, as long as the throw gate would still
        accept that preview for this request (server.throws.gate.preview_refusal: same policy, not
        stale, the machine not moved beyond the gate's bounds); else, or with the gate off, from
        the machine's current state. Its ``created_at`` (the age the gate judges) is then that
        preview's.

        Raises:
            DomainError: as ThrowService.checked_state and :meth:`active_policy`; Limited: the user
                has their limit of previews queued or running (server.jobs.store.JobLimit, a Limited).
        """
        state = self.throws.checked_state(machine_id, mode, target)
        onnx_path, sha, version = self.active_policy(machine_id, mode)
        q, qd, state_at = list(state.q), list(state.qd), None
        base = self._extendable(extends, machine_id, mode, list(target), list(state.q), sha) if extends else None
        if base is not None:
            q, qd, state_at = base
        request = dict(mode=mode, target_m=list(target), q=q, qd=qd, rollouts=rollouts,
                       clearance_radius_m=self.clearance_radius_m, release_check_radius_m=self.release_check_radius_m)
        meta = dict(machine_id=machine_id, mode=mode, target_m=list(target), policy_version=version,
                    policy_sha256=sha, start_q=q, **({"extends": extends, "state_at": state_at} if base else {}))
        profile = str(self.profile_path) if self.profile_path else None
        return self.jobs.submit("preview", {"onnx_path": onnx_path, "sha256": sha, "request": request, "meta": meta,
                                            "profile_path": profile}, subject=machine_id, requested_by=requested_by)

    def _extendable(self, preview_id: str, machine_id: str, mode: str, target: list[float], current_q: list[float],
                    sha: str) -> tuple[list[float], list[float], str] | None:
        """(q (6,), qd (6,), created_at ISO 8601) of preview ``preview_id``'s start state if a
        preview of this request may start from it (:meth:`submit`, ``extends``), else None."""
        limits = self.throws.gate
        job = self.jobs.store.get(preview_id)
        summary = _summary(job)
        if limits is None or job is None or summary is None or list(summary["target_m"]) != target:
            return None
        if preview_refusal(summary, preview_id, machine_id, mode, target, current_q, sha, utcnow(), limits) is not None:
            return None
        request = job["params"]["request"]
        return list(request["q"]), list(request["qd"]), summary["created_at"]

    def outcome(self, job: dict | None, timeout_s: float) -> dict:
        """The summary of a finished preview job.

        Raises:
            Unavailable: no worker answered within ``timeout_s`` (the job is cancelled);
                the job's own refusal (Conflict: the policy does not load on the worker), or
                Failed when the job failed.
        """
        if job is None or job["status"] in ("queued", "running"):
            if job is not None:
                self.jobs.cancel(job["id"])
            raise Unavailable(f"no worker finished the preview within {timeout_s:.0f} s: is a worker running "
                                    "(slinger worker)?")
        if job["status"] != "done":
            error = KINDS.get((job.get("result") or {}).get("refused") or "", Failed)
            raise error(f"preview failed: {job['error'] or job['status']}")
        summary = self.get(job["id"])
        if summary is None:
            raise RuntimeError(f"preview job {job['id']} finished but cannot be read back")
        log.info("preview %s for %s %s at %s: %s", job["id"][:8], summary["machine_id"], summary["mode"],
                 summary["target_m"], summary["status"])
        return summary


def _summary(job: dict | None) -> dict | None:
    """The summary of a stored preview job (PreviewService.get), None if ``job`` is None or not a
    finished preview. Its ``created_at`` is when the machine state it starts from was read (an
    ellipse extending a nominal: the nominal's)."""
    if job is None or job["kind"] != "preview" or job["status"] != "done":
        return None
    meta = job["params"]["meta"]
    return {**job["result"], **meta, "id": job["id"], "created_at": meta.get("state_at") or job["created_at"]}
