"""Real-time health of the simulated machine's loop (sim_twin.twin.plant): when the plant cannot keep
real time it says so (MachineState.machine_fault) instead of letting the arm drift."""

from __future__ import annotations

import logging

log = logging.getLogger(__name__)

BEHIND_FAULT_S = 0.1
"""A period starting this much later than scheduled is a fault: 10 physics periods, the plant's
valve watchdog limit (sim_twin.twin.plant.VALVE_WATCHDOG_S; beyond it the runtime's commands could no
longer have reached the valves in time). 50 ms tripped on a loaded 2-core machine at every
process start."""
RECOVER_S = 1.0
"""The fault clears after this long of periods starting on time."""


class RealTimeGuard:
    """Says when the plant cannot keep real time (see BEHIND_FAULT_S, RECOVER_S).

    :meth:`update` gets how late each period starts (s) and the monotonic time; it returns the
    fault text "behind real time by N ms" (N: the worst lateness since the fault began) while
    faulted, else None.
    """

    def __init__(self, threshold_s: float = BEHIND_FAULT_S, recover_s: float = RECOVER_S):
        self.threshold_s, self.recover_s = threshold_s, recover_s
        self.fault: str | None = None
        self._worst_s = 0.0
        self._ok_since_s: float | None = None

    def update(self, late_s: float, now_s: float) -> str | None:
        if late_s > self.threshold_s:
            self._worst_s = max(self._worst_s, late_s) if self.fault else late_s
            if self.fault is None:
                log.error("plant behind real time by %.0f ms: machine fault, valves neutral", late_s * 1e3)
            self.fault = f"behind real time by {self._worst_s * 1e3:.0f} ms"
            self._ok_since_s = None
        elif self.fault is not None:
            self._ok_since_s = now_s if self._ok_since_s is None else self._ok_since_s
            if now_s - self._ok_since_s >= self.recover_s:
                log.warning("plant keeps real time again for %.1f s: fault cleared", self.recover_s)
                self.fault, self._ok_since_s = None, None
        return self.fault
