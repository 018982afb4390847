"""Book-keeping of the fleet load benchmark (tests/benchmarks/bench_fleet_load.py): the throws it
requested and how each ended, refusals, returns to the ready pose, read latencies, and the CPU
time of process trees and of the whole host (from /proc, Linux only).

No timing assertions anywhere: tests/test_fleet_load_stats.py checks the accounting itself.
"""

from __future__ import annotations

import os
import re
import threading
from collections import Counter
from dataclasses import dataclass, field

FINAL = ("landed", "failed", "aborted", "lost")
"""Final throw statuses (server.db.models.FINAL_STATUSES)."""
POSE_REASONS = ("joint at end", "pose outside the envelope")
"""Not-ready reasons a return to the ready pose recovers from (runtime.recovery.POSE_REASONS)."""
CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def percentile(xs: list[float], q: float) -> float:
    """The ``q`` quantile (0..1, nearest rank below) of ``xs``; NaN when empty."""
    if not 0.0 <= q <= 1.0:
        raise ValueError(f"quantile {q} outside 0..1")
    xs = sorted(xs)
    return xs[int(q * (len(xs) - 1))] if xs else float("nan")


def short_reason(text: str | None, n: int = 70) -> str:
    """A failure or refusal text shortened for counting: numbers become '#', so that "behind
    real time by 104 ms" and "... by 131 ms" count as one reason."""
    return re.sub(r"\d+(\.\d+)?", "#", (text or "").strip())[:n] or "(no reason given)"


def is_pose_refusal(text: str) -> bool:
    """True when a refusal says the machine is not ready because of its pose."""
    return any(r in text for r in POSE_REASONS)


@dataclass
class Tally:
    """Thread-safe record of a load run. ``requested``: throw id -> machine id for every throw the
    server accepted (202); ``final``: throw id -> (status, failure_reason) once final."""

    requested: dict[str, str] = field(default_factory=dict)
    final: dict[str, tuple[str, str | None]] = field(default_factory=dict)
    refusals: Counter = field(default_factory=Counter)
    returns: Counter = field(default_factory=Counter)
    return_s: list[float] = field(default_factory=list)
    round_trip_s: list[float] = field(default_factory=list)
    read_ms: dict[str, list[float]] = field(default_factory=lambda: {"history": [], "accuracy": []})
    read_errors: Counter = field(default_factory=Counter)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def accepted(self, throw_id: str, machine_id: str) -> None:
        with self.lock:
            self.requested[throw_id] = machine_id

    def ended(self, throw_id: str, status: str, reason: str | None) -> None:
        """Record the final status of a throw; raises ValueError for a non-final status or an
        id that was never requested (the accounting would be wrong)."""
        if status not in FINAL:
            raise ValueError(f"{status!r} is not a final status")
        with self.lock:
            if throw_id not in self.requested:
                raise ValueError(f"throw {throw_id} was never requested")
            self.final[throw_id] = (status, reason)

    def refused(self, what: str, text: str) -> None:
        with self.lock:
            self.refusals[f"{what}: {short_reason(text)}"] += 1

    def outcome(self) -> dict:
        """{"requested", "by_status" {status: n}, "lost", "stuck" (requested, never final),
        "reasons" {short reason: n} of the throws that did not land}."""
        with self.lock:
            by_status = Counter(s for s, _ in self.final.values())
            reasons = Counter(f"{s}: {short_reason(r)}" for s, r in self.final.values() if s != "landed")
            stuck = [t for t in self.requested if t not in self.final]
            return {"requested": len(self.requested), "by_status": dict(by_status), "lost": by_status.get("lost", 0),
                    "stuck": len(stuck), "reasons": dict(reasons.most_common())}


def _children() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, []).append(int(d))
    return kids


def proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (its own threads; 0.0 if it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime (fields 14, 15 of proc(5))


def tree_cpu_s(pid: int, kids: dict[int, list[int]] | None = None) -> float:
    """CPU seconds of ``pid`` and its living descendants."""
    kids = _children() if kids is None else kids
    return proc_cpu_s(pid) + sum(tree_cpu_s(k, kids) for k in kids.get(pid, []))


def host_cpu_s() -> tuple[float, float]:
    """(busy, total) CPU seconds of the host since boot, all cores (/proc/stat)."""
    with open("/proc/stat") as f:
        vals = [int(v) for v in f.readline().split()[1:]]
    idle = vals[3] + (vals[4] if len(vals) > 4 else 0)
    return (sum(vals[:8]) - idle) / CLK_TCK, sum(vals[:8]) / CLK_TCK
