"""Bound glibc's heap and give the memory it keeps free back to the system, periodically: used by
the two long-running processes that allocate and free per throw, the server (server.services) and
the machine's runtime (runtime.node, where a trim runs only while no throw or return runs).

glibc's malloc keeps memory that the program freed inside its arenas for later allocations; it
returns it to the system only from the top of the main heap, above ``M_TRIM_THRESHOLD``. A
long-running server with many threads (FastAPI's thread pool, Zenoh callbacks, the session
mirror, the reconciler) frees small blocks in many places of several arenas, so its resident
memory grows with that free memory although its memory in use stays flat: in a 43-minute soak the
server's heap free grew 15.7 -> 25.5 MiB while Python's objects stayed flat (reports/soak_43min,
archived: reports/ARCHIVE.md).
``malloc_trim(0)`` (malloc_trim(3), glibc >= 2.8) hands every whole free page of every arena back
with ``madvise(MADV_DONTNEED)``; the memory stays in the allocator's free lists and is taken
again, page by page, when it is needed.

:class:`HeapTrimmer` calls it at most every ``every_s`` seconds from a thread that already runs
periodically (the server's session-mirror tick, server.services; the runtime's watchdog loop,
runtime.node, between throws only, so that no 10 ms control step waits for a trim). A trim walks the arenas while
holding each one's lock, so another thread's allocation in that arena waits for it: on the
server's heap of about 60 MiB the longest trim of a 66-minute soak took 25.6 ms with the 2-core
host's 1-minute load at 9-12 (2.7 ms in an 8-minute soak; reports/soak_60min), against the
E-STOP's 100 ms goal; the server logs each new longest (:attr:`HeapTrimmer.max_s`). It gives back
whole free pages only: free chunks inside pages still partly in use stay resident (the server's
remaining growth in that soak). Where the C library is not glibc it does nothing.

:func:`bound_heap` sets two of glibc's malloc parameters (mallopt(3)) once, at the process's start,
before its threads run (server.services, runtime.node); the same as the environment variables
``MALLOC_ARENA_MAX`` and ``MALLOC_MMAP_THRESHOLD_``, set from inside the process because
``slinger up`` runs the server and each runtime in processes of their own:

* ``M_ARENA_MAX`` 2: by default a 64-bit process may make 8 arenas per core, one for each thread
  that finds the others locked, and each keeps its own free chunks, so the same frees leave more
  partly used pages resident;
* ``M_MMAP_THRESHOLD`` 256 KiB, fixed: by default the threshold is dynamic, and each freed mapped
  block raises it to that block's size (up to 32 MiB), after which blocks of that size (request
  bodies, telemetry, JSON of a throw) are carved from the heap and leave holes there when freed.
  A fixed threshold keeps them mapped and gives them back whole on free.
"""

from __future__ import annotations

import ctypes
import logging
import time

log = logging.getLogger(__name__)

TRIM_EVERY_S = 60.0
"""How often the server and the runtime give their free heap back, s (the runtime: at the first idle
watchdog tick after that)."""
ARENA_MAX = 2
"""glibc arenas a process may make (:func:`bound_heap`)."""
MMAP_THRESHOLD_B = 256 * 1024
"""Blocks at least this large are mapped, not carved from the heap (:func:`bound_heap`), bytes."""
M_MMAP_THRESHOLD, M_ARENA_MAX = -3, -8
"""mallopt's parameter numbers (glibc's malloc.h)."""


def bound_heap(arenas: int = ARENA_MAX, mmap_threshold_b: int = MMAP_THRESHOLD_B) -> bool:
    """Cap glibc's malloc arenas at ``arenas`` (for threads that start from now on) and fix the
    mmap threshold at ``mmap_threshold_b`` bytes (module doc; mallopt(3)). True if the C library
    took both, False where it is not glibc or refused one.

    Raises:
        ValueError: ``arenas`` < 1 or a threshold outside 0..32 MiB (glibc's HEAP_MAX bound).
    """
    if arenas < 1:
        raise ValueError(f"arena cap {arenas}: at least 1")
    if not 0 <= mmap_threshold_b <= 32 * 1024 * 1024:
        raise ValueError(f"mmap threshold {mmap_threshold_b} B: 0..32 MiB")
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_ARENA_MAX, arenas)) & bool(mallopt(M_MMAP_THRESHOLD, mmap_threshold_b))


def _malloc_trim():
    """glibc's ``malloc_trim`` (int malloc_trim(size_t pad)), or None where there is none."""
    try:
        fn = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


class HeapTrimmer:
    """Calls ``malloc_trim(0)`` when :meth:`tick` finds ``every_s`` seconds passed since the last
    call (monotonic clock); never raises.

    Attributes:
        trims: how many trims ran.
        last_s, max_s: duration of the last and the longest trim, s.
    """

    def __init__(self, every_s: float = TRIM_EVERY_S):
        self.every_s = every_s
        self._trim = _malloc_trim()
        self._due = time.monotonic() + every_s
        self.trims = 0
        self.last_s = 0.0
        self.max_s = 0.0

    @property
    def available(self) -> bool:
        """True where the C library has ``malloc_trim`` (glibc)."""
        return self._trim is not None

    def tick(self) -> bool:
        """Trim if due; True if a trim ran."""
        now = time.monotonic()
        if self._trim is None or now < self._due:
            return False
        self._due = now + self.every_s
        try:
            self._trim(0)
        except Exception:  # a foreign call must never end the caller's periodic thread
            log.exception("malloc_trim failed")
            return False
        self.last_s = time.monotonic() - now
        self.trims += 1
        if self.last_s > self.max_s:  # a new longest trim is logged, the others are not
            log.info("heap trimmed in %.1f ms (the longest so far, trim %d)", self.last_s * 1e3, self.trims)
        self.max_s = max(self.max_s, self.last_s)
        return True
