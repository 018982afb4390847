"""Starting a throw: checks, the runtime handshake, and the no-half-written-rows rule.

:meth:`ThrowService.create` refuses early what it can (unknown machine 404, runtime offline 503,
target the mode cannot serve 422 via :func:`runtime.throw_geometry.target_refusal`, no fresh OK
preview of the same request 409/422 via :mod:`server.throws.gate`), then commits a ``requested``
row (so that the runtime's first ThrowStatus finds it), signs the request for the user and the
runtime's epoch and asks the runtime. When the runtime refuses (or nothing could be sent) the row
is deleted again; when the runtime does not answer, it may still have taken the throw, so the row
stays and the reconciliation (server.fleet.reconcile) closes it with its result or as ``lost``.
"""

from __future__ import annotations

import logging
import math
import uuid
from collections.abc import Callable
from dataclasses import dataclass

from sqlalchemy import delete, select
from sqlalchemy.orm import Session, sessionmaker

from runtime.protocol.messages import MachineState, ThrowAck, ThrowRequest
from server.accounts.auth import audit
from server.db.models import Machine, PolicyVersion, Throw
from server.db.types import utcnow
from server.errors import Conflict, NotFound, Refused, Unavailable
from server.fleet.link import Fleet, RuntimeUnavailable
from server.fleet.results import ensure_machine
from server.throws.gate import GateLimits, preview_refusal
from server.throws.targets import serve_refusal

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ThrowOrder:
    """An operator's throw, as the service takes it (the API's ThrowCreate, validated there).

    Attributes:
        machine_id: the machine.
        mode: "2d" or "3d".
        target: (3,) target in the machine frame, m.
        preview_id: the preview the throw was shown (its prediction is stored with the throw).
        confirm_clearance: 3D throws only: the operator confirmed the swept clearance zone is clear.
    """

    machine_id: str
    mode: str
    target: list[float]
    preview_id: str | None = None
    confirm_clearance: bool = False


class ThrowService:
    """Creates throws.

    Args:
        fleet: the Zenoh side.
        sessions: database session factory.
        keep_out_zones: ground circles no target may lie in (server.config.KeepOutZone).
        previews: looks up a preview summary by id (None: unknown or expired).
        gate: bounds of the preview gate; None switches the gate off (tests of other parts
            only: Settings.require_preview).
        machine_status: the console's machine state of a machine id (server.console.live.LiveHub.status:
            a dict with "state" and "estop_reason", from the RuntimeInfo the runtime publishes);
            a second source of the E-STOP latch beside the query at the throw request.
    """

    def __init__(self, fleet: Fleet, sessions: sessionmaker[Session], keep_out_zones=(),
                 previews: Callable[[str], dict | None] | None = None, gate: GateLimits | None = GateLimits(),
                 machine_status: Callable[[str], dict] | None = None):
        self.fleet = fleet
        self.machine_status = machine_status
        self.sessions = sessions
        self.keep_out_zones = list(keep_out_zones)
        self.previews = previews or (lambda _id: None)
        self.gate = gate

    def checked_state(self, mid: str, mode: str, target) -> MachineState:
        """The machine's latest state if it can serve ``target`` in ``mode`` now.

        Raises:
            NotFound: unknown machine. Unavailable: runtime offline or no state. Refused: a target
                the mode cannot serve (with the reason).
        """
        with self.sessions() as db:
            known = db.get(Machine, mid) is not None
        state = self.fleet.latest_state(mid)
        online = self.fleet.is_online(mid)
        if not (known or online or state is not None):
            raise NotFound(f"unknown machine {mid!r}")
        if not online:
            raise Unavailable(f"the runtime of machine {mid} is offline")
        if state is None:
            raise Unavailable(f"no state from machine {mid} yet: is the machine connected?")
        reason = serve_refusal(mode, target, state.q[0], self.target_range(mid, mode), self.keep_out_zones)
        if reason is not None:
            raise Refused(reason)
        return state

    def create(self, body: ThrowOrder, username: str = "system") -> tuple[Throw, ThrowAck]:
        """Check, record and hand a throw to its runtime.

        Returns:
            (row, ack) of an accepted throw; the row is committed with status ``requested``
            (or a later phase if the runtime already reported one).

        Raises:
            NotFound: unknown machine. Unavailable: runtime offline, no machine state, no
                answer (the row then stays until reconciled), or no command key. Conflict: E-STOP
                latched (as the runtime last reported it), preview stale, policy changed or machine
                moved. Refused: a target the mode cannot serve, preview missing/failed/for another
                request, or the runtime refused (its reason).
        """
        mid = body.machine_id
        state = self.checked_state(mid, body.mode, body.target)
        latched = self.estop_reason(mid)
        if latched is not None:
            # named before the preview gate: the operator must reset first (the runtime refuses anyway)
            raise Conflict(f"E-STOP latched on {mid} ({latched}): reset it before throwing",
                               "estop_latched")
        preview = self._preview_of(body, state)
        if body.mode == "3d" and not body.confirm_clearance:
            raise Refused("a 3D throw turns the cabin: confirm that the swept clearance zone is "
                                    "clear (confirm_clearance: true)")

        throw_id = str(uuid.uuid4())
        with self.sessions.begin() as db:
            ensure_machine(db, mid, simulated=state.simulated)
            db.add(Throw(id=throw_id, machine_id=mid, mode=body.mode, status="requested",
                         target_x_m=body.target[0], target_y_m=body.target[1],
                         target_z_m=body.target[2], requested_by=username, preview=preview))
        request = ThrowRequest(throw_id=throw_id, machine_id=mid, mode=body.mode, target_m=body.target)
        try:
            ack, epoch = self.fleet.request_throw(request, username)
            if ack.throw_id != throw_id:
                raise RuntimeUnavailable(f"ack for throw {ack.throw_id}, expected {throw_id}")
        except RuntimeUnavailable as e:
            # the request may have reached the runtime: keep the row for the reconciliation
            log.warning("throw %s: no confirmation from %s (%s); left to reconciliation", throw_id, mid, e)
            raise Unavailable(f"runtime of {mid} did not confirm the throw: {e}") from e
        except BaseException as e:
            self._delete(throw_id)
            if isinstance(e, ValueError):
                raise Unavailable(f"cannot sign the throw for {mid}: {e}") from e
            raise
        if not ack.accepted:
            self._delete(throw_id)
            raise Refused(ack.reason or "the runtime refused the throw")
        self.fleet.forget_info(mid)  # busy now: the next read asks the runtime
        with self.sessions.begin() as db:
            row = db.get(Throw, throw_id)
            if row is None:
                raise RuntimeError(f"throw {throw_id} vanished while its runtime accepted it")
            row.policy_version, row.runtime_epoch = ack.policy_version, epoch
            row.policy_sha256 = ack.policy_sha256 or self._policy_sha256(mid, body.mode, ack.policy_version)
            audit(db, username, "throw", throw_id, machine_id=mid, mode=body.mode, target_m=body.target,
                  policy_version=ack.policy_version, epoch=epoch, preview_id=body.preview_id)
        log.info("throw %s accepted by %s (%s, target %s)", throw_id, mid, body.mode, body.target)
        return row, ack

    def estop_reason(self, mid: str) -> str | None:
        """Why the E-STOP of ``mid`` is latched, or None if neither the runtime's answer to a query
        now nor its latest published RuntimeInfo says it is (either suffices: a slow query under load
        falls back to a cached, older answer)."""
        info = self.fleet.fresh_info(mid, max_age_s=0.0, timeout_s=1.0)  # ask the runtime now (a latch is instant)
        if info is not None and info.estop_latched:
            return info.estop_reason or "no reason given"
        st = self.machine_status(mid) if self.machine_status is not None else None
        if st is not None and st.get("state") == "estopped":
            return st.get("estop_reason") or "no reason given"
        return None

    def _preview_of(self, body: ThrowOrder, state: MachineState) -> dict | None:
        """The stored form of the preview the throw is sent with, after the gate
        (server.throws.gate) passed; None without a preview when the gate is off.

        Raises:
            Refused / Conflict: the failed gate condition (with ``condition``).
        """
        p = self.previews(body.preview_id) if body.preview_id is not None else None
        if self.gate is not None:
            info = self.fleet.fresh_info(body.machine_id, max_age_s=2.0, timeout_s=1.0)
            sha = next((q.sha256 for q in (info.policies if info else []) if q.mode == body.mode), None)
            refusal = preview_refusal(p, body.preview_id, body.machine_id, body.mode, body.target, state.q, sha,
                                      utcnow(), self.gate, self.keep_out_zones)
            if refusal is not None:
                raise refusal.error(refusal.message, refusal.condition)
        elif body.preview_id is not None:
            if p is None:
                raise Refused(f"unknown or expired preview {body.preview_id!r}: preview again", "preview_unknown")
            if p["machine_id"] != body.machine_id or p["mode"] != body.mode or math.dist(p["target_m"], body.target) > 1e-6:
                raise Refused("the preview was made for another machine, mode or target: preview again",
                                   "preview_other")
        if p is None:
            return None
        keep = {k: v for k, v in p.items() if k != "mc"}
        if p.get("mc"):
            keep["mc"] = {k: v for k, v in p["mc"].items() if k != "impacts_m"}
        return keep

    def _delete(self, throw_id: str) -> None:
        with self.sessions.begin() as db:
            db.execute(delete(Throw).where(Throw.id == throw_id))

    def _policy_sha256(self, machine_id: str, mode: str, version: str | None) -> str | None:
        """The SHA-256 of the policy ``machine_id`` reports for ``mode`` (runtimes whose acks
        carry no SHA), if its name is the acknowledged one."""
        info = self.fleet.fresh_info(machine_id, max_age_s=60.0, timeout_s=1.0)
        return next((p.sha256 for p in (info.policies if info else []) if p.mode == mode and p.version == version), None)

    def target_range(self, machine_id: str, mode: str) -> tuple[float, float] | None:
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
