"""Starting a throw: checks, the runtime handshake, and the no-half-written-rows rule.

:meth:`ThrowService.create` refuses early what it can (unknown machine 404, runtime offline 503,
target the mode cannot serve 422 via :func:`runtime.throw_geometry.target_refusal`), then commits
a ``requested`` row (so that the runtime's first ThrowStatus finds it), asks the runtime and, on
ANY failure of the handshake, deletes that row again before raising.
"""

from __future__ import annotations

import logging
import uuid
from typing import Callable

from sqlalchemy import delete, select
from sqlalchemy.orm import Session, sessionmaker

from runtime.protocol.messages import MachineState, ThrowAck, ThrowRequest
from server.targets import serve_refusal
from server.api.schemas import ThrowCreate
from server.auth import audit
from server.db.models import Machine, PolicyVersion, Throw
from server.fleet import Fleet, RuntimeUnavailable
from server.results import ensure_machine

log = logging.getLogger(__name__)


class ThrowRefused(Exception):
    """A throw request the server or the runtime refused; ``status_code`` is the HTTP status."""

    def __init__(self, status_code: int, detail: str):
        super().__init__(detail)
        self.status_code = status_code
        self.detail = detail


class ThrowService:
    """Creates throws.

    Args:
        fleet: the Zenoh side.
        sessions: database session factory.
        keep_out_zones: ground circles no target may lie in (server.config.KeepOutZone).
        previews: looks up a preview summary by id (None: unknown or expired).
    """

    def __init__(self, fleet: Fleet, sessions: sessionmaker[Session], keep_out_zones=(),
                 previews: Callable[[str], dict | None] | None = None):
        self.fleet = fleet
        self.sessions = sessions
        self.keep_out_zones = list(keep_out_zones)
        self.previews = previews or (lambda _id: None)

    def checked_state(self, mid: str, mode: str, target) -> MachineState:
        """The machine's latest state if it can serve ``target`` in ``mode`` now.

        Raises:
            ThrowRefused: 404 unknown machine; 503 runtime offline or no state; 422 a target
                the mode cannot serve (with the reason).
        """
        with self.sessions() as db:
            known = db.get(Machine, mid) is not None
        state = self.fleet.latest_state(mid)
        online = self.fleet.is_online(mid)
        if not (known or online or state is not None):
            raise ThrowRefused(404, f"unknown machine {mid!r}")
        if not online:
            raise ThrowRefused(503, f"the runtime of machine {mid} is offline")
        if state is None:
            raise ThrowRefused(503, f"no state from machine {mid} yet: is the machine connected?")
        reason = serve_refusal(mode, target, state.q[0], self._target_range(mid, mode), self.keep_out_zones)
        if reason is not None:
            raise ThrowRefused(422, reason)
        return state

    def create(self, body: ThrowCreate, username: str = "system") -> tuple[Throw, ThrowAck]:
        """Check, record and hand a throw to its runtime.

        Returns:
            (row, ack) of an accepted throw; the row is committed with status ``requested``
            (or a later phase if the runtime already reported one).

        Raises:
            ThrowRefused: 404 unknown machine; 503 runtime offline, no machine state, or no
                answer; 422 target the mode cannot serve, or the runtime refused (its reason).
                No throw row remains in any of these cases.
        """
        mid = body.machine_id
        state = self.checked_state(mid, body.mode, body.target)
        preview = self._preview_of(body)
        if body.mode == "3d" and not body.confirm_clearance:
            raise ThrowRefused(422, "a 3D throw turns the cabin: confirm that the swept clearance zone is "
                                    "clear (confirm_clearance: true)")

        throw_id = str(uuid.uuid4())
        with self.sessions.begin() as db:
            ensure_machine(db, mid, simulated=state.simulated)
            db.add(Throw(id=throw_id, machine_id=mid, mode=body.mode, status="requested",
                         target_x_m=body.target[0], target_y_m=body.target[1],
                         target_z_m=body.target[2], requested_by=username, preview=preview))
        try:
            ack = self.fleet.request_throw(
                ThrowRequest(throw_id=throw_id, machine_id=mid, mode=body.mode, target_m=body.target)
            )
            if ack.throw_id != throw_id:
                raise RuntimeUnavailable(f"ack for throw {ack.throw_id}, expected {throw_id}")
            if not ack.accepted:
                raise ThrowRefused(422, ack.reason or "the runtime refused the throw")
        except BaseException as e:
            self._delete(throw_id)
            if isinstance(e, RuntimeUnavailable):
                raise ThrowRefused(503, f"runtime of {mid} did not accept the throw: {e}") from e
            raise
        with self.sessions.begin() as db:
            row = db.get(Throw, throw_id)
            row.policy_version = ack.policy_version
            audit(db, username, "throw", throw_id, machine_id=mid, mode=body.mode, target_m=body.target,
                  policy_version=ack.policy_version)
        log.info("throw %s accepted by %s (%s, target %s)", throw_id, mid, body.mode, body.target)
        return row, ack

    def _preview_of(self, body: ThrowCreate) -> dict | None:
        """The stored form of the preview the throw is sent with (422 if unknown or another
        request's); None without a preview id."""
        if body.preview_id is None:
            return None
        p = self.previews(body.preview_id)
        if p is None:
            raise ThrowRefused(422, f"unknown or expired preview {body.preview_id!r}: preview again")
        same_target = all(abs(a - b) < 1e-6 for a, b in zip(p["target_m"], body.target))
        if p["machine_id"] != body.machine_id or p["mode"] != body.mode or not same_target:
            raise ThrowRefused(422, "the preview was made for another machine, mode or target: preview again")
        keep = {k: v for k, v in p.items() if k != "mc"}
        if p.get("mc"):
            keep["mc"] = {k: v for k, v in p["mc"].items() if k != "impacts_m"}
        return keep

    def _delete(self, throw_id: str) -> None:
        with self.sessions.begin() as db:
            db.execute(delete(Throw).where(Throw.id == throw_id))

    def _target_range(self, machine_id: str, mode: str) -> tuple[float, float] | None:
        """The trained target range of the policy ``machine_id`` runs for ``mode``, from its
        registered manifest; None when unknown (target_refusal then uses its default)."""
        default = None
        info = self.fleet.cached_info(machine_id)
        if info is None:
            return default
        sha = next((p.sha256 for p in info.policies if p.mode == mode), None)
        if sha is None:
            return default
        with self.sessions() as db:
            manifest = db.scalar(select(PolicyVersion.manifest).where(PolicyVersion.sha256 == sha))
        rng = (manifest or {}).get("target_range_m")
        return (float(rng[0]), float(rng[1])) if rng else default
