"""Live push to the console: one machine state per machine, throw progress, results and live
throw samples, delivered to every open console page over Server-Sent Events (``GET /api/live``).

:class:`LiveHub` listens on Zenoh next to :class:`server.fleet.Fleet` (same session):

* ``keys.ALL_RUNTIME_STATES``: the runtime's RuntimeInfo (2 Hz and on every change) ->
  ``machine`` events (see :func:`machine_status`);
* ``keys.ALL_RUNTIME_ALIVE`` (liveliness): runtime online/offline -> ``machine`` events at once;
* ``keys.ALL_STATUS``: ThrowStatus -> ``throw`` events (phase, seconds since the request);
* ``keys.ALL_STATES`` and the valve commands: during a throw, ``sample`` events at
  ``SAMPLE_RATE_HZ`` (joint velocities, passive angles, valve commands, payload position);
* stored results (``Fleet.result_listeners``) -> ``result`` events;
* per-console events (the target a click picked, ...) from :mod:`server.scene` via :meth:`LiveHub.publish`.

Every subscriber also gets a ``heartbeat`` each ``HEARTBEAT_S`` so a page notices a silent server.
Zenoh callbacks run on Zenoh threads; events are handed to each subscriber's asyncio queue with
``loop.call_soon_threadsafe`` (a full queue drops the subscriber's oldest events: slow pages lose
samples, never block the server).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import zenoh
from pydantic import ValidationError

from runtime.machine import forward_kinematics
from runtime.protocol import keys
from runtime.protocol.messages import MachineState, RuntimeInfo, ThrowStatus, ValveCommand, decode
from server.fleet import RUNTIME_SILENT_S

log = logging.getLogger(__name__)

HEARTBEAT_S = 1.0
"""A heartbeat event this often; the page shows "server unreachable" after 4 s without any event."""
SAMPLE_RATE_HZ = 25.0
"""Live throw samples per second and machine (MachineState comes at 100 Hz)."""
QUEUE_SIZE = 2000
ACTIVE_PHASES = ("preparing", "swinging", "released")
ALL_VALVE_CMDS = f"{keys.ROOT}/machine/*/valve_cmd"
SILENT_AFTER_S = RUNTIME_SILENT_S
"""A runtime that published RuntimeInfo before and is silent this long is shown offline
("runtime not answering": frozen or cut off), whatever it said last (busy, swinging, ...)."""


def machine_status(machine_id: str, online: bool, info: RuntimeInfo | None, info_age_s: float | None,
                   throw: dict | None = None) -> dict:
    """The one machine state the console shows, from the runtime's own RuntimeInfo.

    Args:
        machine_id: the machine.
        online: the runtime holds its liveliness token.
        info: its latest RuntimeInfo (None if none heard since it came online).
        info_age_s: seconds since ``info`` was received (None: never).
        throw: the running throw as tracked from ThrowStatus ({"throw_id", "phase", ...}).

    Returns:
        {"machine_id", "state": "offline" | "estopped" | "throwing" | "not_ready" | "ready",
        "reason" (str | None, plain words), "estop_reason", "phase", "throw_id", "policies"
        {mode: version}, "simulated", "recovery" (the runtime's offered recovery action, e.g.
        "return_to_ready", else None), "returning" (a return to the ready pose runs),
        "return_progress" (0..1 or None), "return_result" (how the last one ended or None)}. A runtime without the machine-state fields of RuntimeInfo
        (older protocol; on the wire as ready False without a reason) is judged by ``busy``,
        ``machine_online`` and its policies.
    """
    out = {"machine_id": machine_id, "state": "offline", "reason": "runtime offline", "estop_reason": None,
           "phase": None, "throw_id": None, "policies": {}, "simulated": bool(info and info.simulated),
           "recovery": None, "returning": False, "return_progress": None, "return_result": None}
    if not online:
        return out
    if info is None:
        return {**out, "state": "not_ready", "reason": "waiting for the runtime's state"}
    out["policies"] = {p.mode: p.version for p in info.policies}
    out.update(recovery=info.recovery, returning=info.returning, return_progress=info.return_progress,
               return_result=info.return_result)
    phase = info.phase or (throw or {}).get("phase")
    out.update(phase=phase, throw_id=info.throw_id or (throw or {}).get("throw_id"), reason=None)
    if info_age_s is not None and info_age_s > SILENT_AFTER_S:  # frozen or cut off: what it said last no longer holds
        return {**out, "state": "offline", "reason": f"runtime not answering for {info_age_s:.0f} s",
                "phase": None, "throw_id": None}
    if info.estop_latched:
        return {**out, "state": "estopped", "reason": info.estop_reason or "E-STOP latched",
                "estop_reason": info.estop_reason}
    if phase in ACTIVE_PHASES:
        return {**out, "state": "throwing"}
    if not info.machine_online:
        return {**out, "state": "not_ready", "reason": "machine offline (no joint states)"}
    if info.ready:
        return {**out, "state": "ready"}
    if info.not_ready_reason:
        return {**out, "state": "not_ready", "reason": info.not_ready_reason}
    # not ready without a reason: a runtime that does not judge readiness itself (older protocol)
    if not info.policies:
        return {**out, "state": "not_ready", "reason": "no policy installed"}
    if info.busy:
        return {**out, "state": "throwing"}
    return {**out, "state": "ready"}


@dataclass
class Subscriber:
    """One open event stream (a console page). ``console_id`` receives that console's events."""

    loop: asyncio.AbstractEventLoop
    console_id: str | None
    queue: asyncio.Queue = field(default_factory=lambda: asyncio.Queue(QUEUE_SIZE))

    def put(self, event: tuple[str, dict]) -> None:
        """Thread-safe: queue ``event`` (dropping the oldest one when full)."""
        def _put() -> None:
            if self.queue.full():
                self.queue.get_nowait()
            self.queue.put_nowait(event)

        try:
            self.loop.call_soon_threadsafe(_put)
        except RuntimeError:  # loop closed: the page is gone
            pass


class LiveHub:
    """Collects machine state, throw progress and results; fans them out to subscribers.

    Args:
        session: the server's open Zenoh session (the caller closes it).
        fleet: :class:`server.fleet.Fleet` (presence, result listeners, RuntimeInfo fallback).
    """

    def __init__(self, session: zenoh.Session, fleet):
        self.drift = None  # server.drift.DriftWatch: its alert joins each machine's state as "drift_alert"
        self.session, self.fleet = session, fleet
        self._lock = threading.Lock()
        self._subs: list[Subscriber] = []
        self._infos: dict[str, tuple[float, RuntimeInfo]] = {}
        self._throws: dict[str, dict] = {}
        self._valves: dict[str, list[float]] = {}
        self._last_sample: dict[str, float] = {}
        self._last_status: dict[str, dict] = {}
        self._decls: list = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        s = self.session
        self._decls = [
            s.declare_subscriber(keys.ALL_RUNTIME_STATES, self._on_runtime_state),
            s.liveliness().declare_subscriber(keys.ALL_RUNTIME_ALIVE, self._on_alive, history=True),
            s.declare_subscriber(keys.ALL_STATUS, self._on_status),
            s.declare_subscriber(keys.ALL_STATES, self._on_state),
            s.declare_subscriber(ALL_VALVE_CMDS, self._on_valve),
        ]
        self.fleet.result_listeners.append(self._on_result)
        self._thread = threading.Thread(target=self._tick, name="live-hub", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        for d in self._decls:
            try:
                d.undeclare()
            except Exception:  # session already closed
                log.debug("undeclare failed", exc_info=True)
        self._decls = []
        if self._thread is not None:
            self._thread.join(timeout=3.0)

    # --- subscribers ---------------------------------------------------------------------------
    def subscribe(self, console_id: str | None = None) -> Subscriber:
        """A new event stream on the running asyncio loop; it starts with every machine's state."""
        sub = Subscriber(asyncio.get_running_loop(), console_id)
        with self._lock:
            self._subs.append(sub)
        for status in self.statuses():
            sub.put(("machine", status))
        return sub

    def unsubscribe(self, sub: Subscriber) -> None:
        with self._lock:
            if sub in self._subs:
                self._subs.remove(sub)

    def publish(self, event: str, data: dict, console_id: str | None = None) -> None:
        """Send ``event`` to every subscriber, or only to those of ``console_id``."""
        with self._lock:
            subs = [s for s in self._subs if console_id is None or s.console_id == console_id]
        for s in subs:
            s.put((event, data))

    # --- state ---------------------------------------------------------------------------------
    def status(self, machine_id: str, online: bool | None = None) -> dict:
        """:func:`machine_status` of ``machine_id`` now (``online``: presence if known better
        than the fleet's, e.g. from the liveliness sample being handled)."""
        online = self.fleet.is_online(machine_id) if online is None else online
        with self._lock:
            entry = self._infos.get(machine_id)
            throw = self._throws.get(machine_id)
        if entry is not None:
            info, age = entry[1], time.monotonic() - entry[0]
        else:
            info, age = self.fleet.cached_info(machine_id), None
        st = machine_status(machine_id, online, info, age, throw)
        state = self.fleet.latest_state(machine_id)
        st["simulated"] = st["simulated"] or bool(state is not None and state.simulated)
        st["cabin_turn_rad"] = float(state.q[0]) if state is not None else None
        st["drift_alert"] = self.drift.alert(machine_id) if self.drift is not None else None
        return st

    def statuses(self) -> list[dict]:
        ids = set(self.fleet.online_ids()) | set(self.fleet.latest_states())
        with self._lock:
            ids |= set(self._infos) | set(self._last_status)
        return [self.status(mid) for mid in sorted(ids)]

    def _push_status(self, machine_id: str, force: bool = False) -> None:
        st = self.status(machine_id)
        key = {k: v for k, v in st.items() if k != "cabin_turn_rad"}
        with self._lock:
            same = self._last_status.get(machine_id) == key
            self._last_status[machine_id] = key
        if force or not same:
            self.publish("machine", st)

    # --- Zenoh callbacks -----------------------------------------------------------------------
    def _on_runtime_state(self, sample: zenoh.Sample) -> None:
        try:
            info = decode(RuntimeInfo, sample.payload.to_bytes())
        except ValidationError:
            log.debug("dropped malformed RuntimeInfo on %s", sample.key_expr)
            return
        with self._lock:
            self._infos[info.machine_id] = (time.monotonic(), info)
        self._push_status(info.machine_id)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            machine_id = keys.machine_id_of(str(sample.key_expr))
        except ValueError:
            return
        if sample.kind != zenoh.SampleKind.PUT:
            with self._lock:
                self._infos.pop(machine_id, None)
                self._throws.pop(machine_id, None)
        # the fleet's own liveliness callback may run after ours: judge presence from the sample
        st = self.status(machine_id, online=sample.kind == zenoh.SampleKind.PUT)
        with self._lock:
            self._last_status[machine_id] = {k: v for k, v in st.items() if k != "cabin_turn_rad"}
        self.publish("machine", st)

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            status = decode(ThrowStatus, sample.payload.to_bytes())
            machine_id = keys.machine_id_of(str(sample.key_expr))
        except (ValidationError, ValueError):
            return
        now = time.monotonic()
        with self._lock:
            cur = self._throws.get(machine_id)
            if cur is None or cur["throw_id"] != status.throw_id:
                cur = {"throw_id": status.throw_id, "started": now}
            cur.update(phase=status.phase, detail=status.detail)
            if status.phase in ACTIVE_PHASES:
                self._throws[machine_id] = cur
            else:
                self._throws.pop(machine_id, None)
        self.publish("throw", {"machine_id": machine_id, "throw_id": status.throw_id, "phase": status.phase,
                               "detail": status.detail, "elapsed_s": round(now - cur["started"], 3)})
        self._push_status(machine_id)

    def _on_valve(self, sample: zenoh.Sample) -> None:
        try:
            cmd = decode(ValveCommand, sample.payload.to_bytes())
            machine_id = keys.machine_id_of(str(sample.key_expr))
        except (ValidationError, ValueError):
            return
        with self._lock:
            self._valves[machine_id] = [round(float(u), 4) for u in cmd.u]

    def _on_state(self, sample: zenoh.Sample) -> None:
        try:
            state = decode(MachineState, sample.payload.to_bytes())
        except ValidationError:
            return
        mid = state.machine_id
        now = time.monotonic()
        with self._lock:
            throw = self._throws.get(mid)
            if throw is None or now - self._last_sample.get(mid, 0.0) < 1.0 / SAMPLE_RATE_HZ:
                return
            self._last_sample[mid] = now
            valves = self._valves.get(mid)
        self.publish("sample", sample_of(state, throw, valves, now))

    def _on_result(self, throw_id: str) -> None:
        self.publish("result", {"throw_id": throw_id})

    def _tick(self) -> None:
        """Heartbeats, and re-judged states (a silent runtime, presence changes seen late)."""
        while not self._stop.wait(HEARTBEAT_S):
            self.publish("heartbeat", {"server_time_s": time.time()})
            ids = set(self.fleet.online_ids())
            with self._lock:
                ids |= set(self._last_status)
            for mid in ids:
                with self._lock:
                    heard = mid in self._infos
                if not heard and self.fleet.is_online(mid):
                    # runtime without keys.runtime_state (older protocol): ask it (cached 2 s)
                    self.fleet.fresh_info(mid, max_age_s=2.0, timeout_s=0.5)
                self._push_status(mid)


def sample_of(state: MachineState, throw: dict, valves: list[float] | None, now: float) -> dict:
    """One live throw sample: {"machine_id", "throw_id", "t_s" (since the throw started),
    "qd" (4,) active joint velocities rad/s | m/s, "passive_rad" (2,), "u" (4,) valve commands
    or None, "p_m" (3,) payload (or gripper centre while held), "held"}."""
    q, qd = np.asarray(state.q, dtype=float), np.asarray(state.qd, dtype=float)
    held = state.payload_attached is not False or state.payload_pos_m is None
    p = forward_kinematics(np, q, qd).gripper_centre if held else np.asarray(state.payload_pos_m)
    return {"machine_id": state.machine_id, "throw_id": throw["throw_id"], "t_s": round(now - throw["started"], 3),
            "qd": [round(float(v), 4) for v in qd[:4]], "passive_rad": [round(float(v), 4) for v in q[4:6]],
            "u": valves, "p_m": [round(float(v), 3) for v in p], "held": bool(held)}
