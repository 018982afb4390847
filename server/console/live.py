"""Live push to the console: one machine state per machine, throw progress, results and live
throw samples, delivered to every open console page over Server-Sent Events (``GET /api/live``).

:class:`LiveHub` is a consumer of the fleet's events (:mod:`server.fleet.events`, through
:meth:`server.fleet.link.Fleet.add_consumer`); it declares nothing on Zenoh itself:

* RuntimeInfoEvent (the runtime's RuntimeInfo, 2 Hz and on every change) -> ``machine`` events
  (see :func:`machine_status`; the RuntimeInfo is read from the fleet's one cache);
* RuntimeOnline / RuntimeOffline (liveliness) -> ``machine`` events at once;
* ThrowStatusEvent -> ``throw`` events (phase, seconds since the request);
* MachineStateEvent and ValveCommandEvent: during a throw, ``sample`` events at ``SAMPLE_RATE_HZ``
  (joint velocities, passive angles, valve commands, payload position);
* ResultStored -> ``result`` events; so does a throw the reconciliation closed as lost
  (:meth:`LiveHub.throw_closed`: no result will come, and a page showing it running reads its row again);
* a deployment a runtime confirmed or refused -> ``deployment`` events (:meth:`LiveHub.deployment_changed`);
* per-console events (the target a click picked, ...) from :mod:`server.console.scene` via :meth:`LiveHub.publish`.

Every subscriber also gets a ``heartbeat`` each ``HEARTBEAT_S`` so a page notices a silent server.
Fleet events come on Zenoh threads; events are handed to each subscriber's asyncio queue with
``loop.call_soon_threadsafe`` (a full queue drops the subscriber's oldest events: slow pages lose
samples, never block the server).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from runtime.machine import forward_kinematics
from runtime.protocol.messages import MachineState, RuntimeInfo
from server.fleet.events import (
    FleetEvent,
    MachineStateEvent,
    ResultStored,
    RuntimeInfoEvent,
    RuntimeOffline,
    RuntimeOnline,
    ThrowStatusEvent,
    ValveCommandEvent,
)
from server.fleet.link import RUNTIME_SILENT_S, clock_warning

log = logging.getLogger(__name__)

HEARTBEAT_S = 1.0
"""A heartbeat event this often; the page shows "server unreachable" after 4 s without any event."""
SAMPLE_RATE_HZ = 25.0
"""Live throw samples per second and machine (MachineState comes at 100 Hz)."""
QUEUE_SIZE = 2000
ACTIVE_PHASES = ("preparing", "swinging", "released")
NO_REASON = "the runtime says it is not ready (no reason given)"
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
        info_age_s: seconds since the runtime last published its RuntimeInfo (None or 0: not
            judged, e.g. none published since it came online).
        throw: the running throw as tracked from ThrowStatus ({"throw_id", "phase", ...}).

    Returns:
        {"machine_id", "state": "offline" | "estopped" | "throwing" | "not_ready" | "ready",
        "reason" (str | None, plain words), "estop_reason", "phase", "throw_id", "policies"
        {mode: version}, "simulated", "recovery" (the runtime's offered recovery action, e.g.
        "return_to_ready", else None), "returning" (a return to the ready pose runs),
        "return_progress" (0..1 or None), "return_result" (how the last one ended or None),
        "epoch" (the runtime's RuntimeInfo epoch, ms at its start: changes when it restarts;
        None before its first RuntimeInfo), "lease_holder" (the server id whose commands the
        runtime obeys, None: nobody or unknown), "undeliverable_results" (results its outbox set
        aside, None: unknown)}.
    """
    out: dict[str, Any] = {"machine_id": machine_id, "state": "offline", "reason": "runtime offline", "estop_reason": None,
           "phase": None, "throw_id": None, "policies": {}, "simulated": bool(info and info.simulated),
           "recovery": None, "returning": False, "return_progress": None, "return_result": None, "epoch": None,
           "lease_holder": None, "undeliverable_results": None}
    if not online:
        return out
    if info is None:
        return {**out, "state": "not_ready", "reason": "waiting for the runtime's state"}
    out["policies"] = {p.mode: p.version for p in info.policies}
    out["epoch"] = info.epoch  # the runtime's start (ms): a new value is a restarted runtime
    out.update(lease_holder=info.lease_holder, undeliverable_results=info.undeliverable_results)
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
    return {**out, "state": "not_ready", "reason": info.not_ready_reason or NO_REASON}


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
    """Turns fleet events into console events and fans them out to subscribers.

    Args:
        fleet: :class:`server.fleet.link.Fleet`: its events (:meth:`~server.fleet.link.Fleet.add_consumer`),
            presence, latest machine states and its RuntimeInfo cache.
    """

    def __init__(self, fleet):
        self.drift = None  # server.analysis.drift.DriftWatch: its alert joins each machine's state as "drift_alert"
        self.fleet = fleet
        self._lock = threading.Lock()
        self._subs: list[Subscriber] = []
        self._throws: dict[str, dict] = {}
        self._valves: dict[str, list[float]] = {}
        self._last_sample: dict[str, float] = {}
        self._last_status: dict[str, dict] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        """Consume the fleet's events and start the heartbeat thread."""
        self.fleet.add_consumer(self.on_event)
        self._thread = threading.Thread(target=self._tick, name="live-hub", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self.fleet.remove_consumer(self.on_event)
        if self._thread is not None:
            self._thread.join(timeout=3.0)

    # --- subscribers ---------------------------------------------------------------------------
    def subscribe(self, console_id: str | None = None) -> Subscriber:
        """A new event stream on the running asyncio loop; it starts with every machine's state
        and every machine's drift alert (``drift`` events, server.analysis.drift)."""
        sub = Subscriber(asyncio.get_running_loop(), console_id)
        with self._lock:
            self._subs.append(sub)
        for status in self.statuses():
            sub.put(("machine", status))
        for alert in self.drift.alerts() if self.drift is not None else []:
            sub.put(("drift", alert))
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
    def status(self, machine_id: str) -> dict:
        """:func:`machine_status` of ``machine_id`` now, from the fleet's presence and RuntimeInfo
        cache, with ``simulated``, ``cabin_turn_rad`` (from its latest MachineState, rad, None if
        none), ``drift_alert`` (:meth:`server.analysis.drift.DriftWatch.alert`) and ``clock_warning``
        (:func:`server.fleet.link.clock_warning`, None while the clocks agree) and ``lease_held_here``
        (the lease holder is this server; None while nobody or an unknown server holds it) added. An E-STOP the
        server holds latched (:meth:`server.fleet.link.Fleet.estop_latch`) makes the state
        ``estopped`` whatever the runtime says or whether it answers."""
        online = self.fleet.is_online(machine_id)
        with self._lock:
            throw = self._throws.get(machine_id)
        info = self.fleet.last_info(machine_id)
        st = machine_status(machine_id, online, info, self.fleet.silent_for_s(machine_id) if info else None, throw)
        latch = self.fleet.estop_latch(machine_id)
        if latch is not None:
            st.update(state="estopped", reason=latch.describe(), estop_reason=latch.reason)
        state = self.fleet.latest_state(machine_id)
        st["simulated"] = st["simulated"] or bool(state is not None and state.simulated)
        st["cabin_turn_rad"] = float(state.q[0]) if state is not None else None
        st["drift_alert"] = self.drift.alert(machine_id) if self.drift is not None else None
        st["clock_warning"] = clock_warning(self.fleet.clock_offset_s(machine_id)) if online else None
        holder = st["lease_holder"]
        st["lease_held_here"] = (holder == self.fleet.signer.server_id) if holder is not None else None
        return st

    def statuses(self) -> list[dict]:
        ids = set(self.fleet.online_ids()) | set(self.fleet.latest_states()) | self.fleet.estop_latched_ids()
        with self._lock:
            ids |= set(self._last_status)
        return [self.status(mid) for mid in sorted(ids)]

    def _push_status(self, machine_id: str, force: bool = False) -> None:
        st = self.status(machine_id)
        key = {k: v for k, v in st.items() if k != "cabin_turn_rad"}
        with self._lock:
            same = self._last_status.get(machine_id) == key
            self._last_status[machine_id] = key
        if force or not same:
            self.publish("machine", st)

    # --- fleet events (Zenoh threads; ResultStored on the fleet's database thread) ---------------
    def on_event(self, event: FleetEvent) -> None:
        """Consume one fleet event (the fleet's own state is already updated)."""
        if isinstance(event, MachineStateEvent):
            self._on_state(event.state)
        elif isinstance(event, ValveCommandEvent):
            with self._lock:
                self._valves[event.machine_id] = [round(float(u), 4) for u in event.command.u]
        elif isinstance(event, RuntimeInfoEvent):
            self._push_status(event.machine_id)
        elif isinstance(event, ThrowStatusEvent):
            self._on_status(event)
        elif isinstance(event, (RuntimeOnline, RuntimeOffline)):
            if isinstance(event, RuntimeOffline):
                with self._lock:
                    self._throws.pop(event.machine_id, None)
            self._push_status(event.machine_id, force=True)
        elif isinstance(event, ResultStored):
            self.publish("result", {"throw_id": event.throw_id})

    def deployment_changed(self, machine_id: str, mode: str, status: str) -> None:
        """A runtime's PolicyUpdate settled a deployment of ``machine_id`` for ``mode`` (``status``
        "active" or "failed", server.policies.versions.PolicyService): a ``deployment`` event
        ``{"machine_id", "mode", "status"}``. Its RuntimeInfo may have shown the new policy before:
        a page that fetched the machine's rollback target then reads it again."""
        self.publish("deployment", {"machine_id": machine_id, "mode": mode, "status": status})

    def throw_closed(self, throw_id: str) -> None:
        """Throw ``throw_id`` was closed without a result (server.fleet.reconcile marked it
        ``lost``): a ``result`` event ``{"throw_id"}``, the same as for a stored result, so every page
        that shows the throw (running, requested) or its machine's last throw reads its row again."""
        self.publish("result", {"throw_id": throw_id})

    def _on_status(self, event: ThrowStatusEvent) -> None:
        status, machine_id = event.status, event.machine_id
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

    def _on_state(self, state: MachineState) -> None:
        mid = state.machine_id
        now = time.monotonic()
        with self._lock:
            throw = self._throws.get(mid)
            if throw is None or now - self._last_sample.get(mid, 0.0) < 1.0 / SAMPLE_RATE_HZ:
                return
            self._last_sample[mid] = now
            valves = self._valves.get(mid)
        self.publish("sample", sample_of(state, throw, valves, now))

    def _tick(self) -> None:
        """Heartbeats, and re-judged states (a runtime gone silent shows offline after SILENT_AFTER_S)."""
        while not self._stop.wait(HEARTBEAT_S):
            self.publish("heartbeat", {"server_time_s": time.time()})
            ids = set(self.fleet.online_ids()) | self.fleet.estop_latched_ids()
            with self._lock:
                ids |= set(self._last_status)
            for mid in ids:
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
