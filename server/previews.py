"""Previews: run the machine's active policy in the CPU twin (sim_twin.preview) from its current
joint state, keep the result for a while so that a throw can be sent "as previewed".

The policy file comes from the server's copy of the policy version the runtime reports
(RuntimeInfo sha256 -> policy_versions.onnx_path); loaded runners are cached by SHA-256.
"""

from __future__ import annotations

import logging
import threading
import uuid
from collections import OrderedDict
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from runtime.policy import PolicyError, PolicyRunner
from server.db.models import PolicyVersion
from server.db.types import utcnow
from server.fleet import Fleet
from server.throws import ThrowRefused, ThrowService

log = logging.getLogger(__name__)

KEEP_PREVIEWS = 200


class PreviewService:
    """Makes and remembers previews.

    Args:
        fleet: machine states and runtime infos.
        sessions: database sessions (policy versions).
        throws: the throw service (its target checks are the previews' too).
        data_dir: where policy files live (policy_versions.onnx_path is relative to it).
        clearance_radius_m: see server.config.Settings.
    """

    def __init__(self, fleet: Fleet, sessions: sessionmaker[Session], throws: ThrowService, data_dir: Path,
                 clearance_radius_m: float = 12.0):
        self.fleet, self.sessions, self.throws = fleet, sessions, throws
        self.data_dir = Path(data_dir)
        self.clearance_radius_m = clearance_radius_m
        self._runners: dict[str, PolicyRunner] = {}
        self._store: OrderedDict[str, dict] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, preview_id: str) -> dict | None:
        with self._lock:
            return self._store.get(preview_id)

    def active_policy(self, machine_id: str, mode: str) -> tuple[PolicyRunner, str]:
        """(runner, version name) of the policy ``machine_id`` runs for ``mode``.

        Raises:
            ThrowRefused: 422 no policy for the mode; 409 the server has no file of it.
        """
        info = self.fleet.fresh_info(machine_id, max_age_s=2.0, timeout_s=1.0)
        pol = next((p for p in (info.policies if info else []) if p.mode == mode), None)
        if pol is None:
            raise ThrowRefused(422, f"machine {machine_id} runs no {mode} policy")
        with self._lock:
            runner = self._runners.get(pol.sha256)
        if runner is not None:
            return runner, pol.version
        with self.sessions() as db:
            row = db.scalar(select(PolicyVersion).where(PolicyVersion.sha256 == pol.sha256))
        if row is None or not row.onnx_path or not (self.data_dir / row.onnx_path).is_file():
            raise ThrowRefused(409, f"the server has no file of policy {pol.version} ({pol.sha256[:12]}…): "
                                    "upload that version to preview it")
        try:
            runner = PolicyRunner.load(self.data_dir / row.onnx_path)
        except PolicyError as e:
            raise ThrowRefused(409, f"policy {pol.version} does not load on the server: {e}") from e
        with self._lock:
            self._runners[pol.sha256] = runner
        return runner, pol.version

    def preview(self, machine_id: str, mode: str, target: list[float], rollouts: int) -> dict:
        """Check the target (as a throw would be checked), run the twin, store and return the
        summary (sim_twin.preview.preview_throw keys plus id, machine_id, policy_version,
        created_at, start_q).

        Raises:
            ThrowRefused: as ThrowService.checked_state and :meth:`active_policy`.
        """
        from sim_twin.preview import PreviewRequest, preview_throw

        state = self.throws.checked_state(machine_id, mode, target)
        runner, version = self.active_policy(machine_id, mode)
        summary = preview_throw(runner, PreviewRequest(
            mode=mode, target_m=list(target), q=list(state.q), qd=list(state.qd), rollouts=rollouts,
            clearance_radius_m=self.clearance_radius_m))
        summary.update(id=str(uuid.uuid4()), machine_id=machine_id, mode=mode, target_m=list(target),
                       policy_version=version, created_at=utcnow().isoformat(), start_q=list(state.q))
        with self._lock:
            self._store[summary["id"]] = summary
            while len(self._store) > KEEP_PREVIEWS:
                self._store.popitem(last=False)
        log.info("preview %s for %s %s at %s: %s", summary["id"][:8], machine_id, mode, target, summary["status"])
        return summary
