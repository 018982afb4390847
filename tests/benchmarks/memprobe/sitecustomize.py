"""Memory probe of bench_soak's server and worker (``bench_soak.py --probe-dir DIR`` puts this
folder on the stack's PYTHONPATH; Python imports ``sitecustomize`` at start-up, site(3)).

In a process started as ``slinger server``, ``slinger worker`` or ``slinger runtime``, a daemon thread appends a row
every ``MEMPROBE_EVERY_S`` seconds (default 30) to ``$MEMPROBE_DIR/<role>-<pid>.tsv``: seconds
since start, resident memory (bytes, /proc/self/statm), glibc's heap figures (mallinfo2(3):
``arena`` bytes taken from the system by malloc outside mmap, ``hblkhd`` bytes in mmapped
blocks, ``uordblks`` bytes in use, ``fordblks`` bytes free inside the heap), the bytes SQLite
holds (``sqlite3_memory_used``: page caches, prepared statements), Python's allocated blocks
(``sys.getallocatedblocks``), objects tracked by the garbage collector and threads, the
resident memory split into anonymous and file-backed pages (``RssAnon``, ``RssFile`` of
/proc/self/status: heap and stacks, against the code and data of mapped libraries touched so
far) and the bytes of Python's own small-object arenas (pymalloc, 1 MiB each, mapped outside
glibc's heap; ``sys._debugmallocstats``, read through a brief redirection of file descriptor 2,
so a line another thread writes to stderr in that moment is lost). Growth of
``uordblks`` is memory in use; growth of ``fordblks`` with flat use is the allocator keeping
freed memory (fragmentation). Every other process is untouched.

With ``MEMPROBE_TRACE_AFTER_S`` set, in the roles of ``MEMPROBE_TRACE_ROLES`` (comma-separated,
default ``runtime``) Python's tracemalloc starts that many seconds after the
process (after its warm-up, so only what is allocated later is traced, and the tracing slows
only that part) with ``MEMPROBE_TRACE_FRAMES`` frames (default 12); every
``MEMPROBE_TRACE_EVERY_S`` seconds (default 300) the blocks allocated since then and still alive,
grouped by traceback, largest first (the top 30), are written to
``$MEMPROBE_DIR/<role>-<pid>.trace.txt``: what a growing process keeps.
"""

import os
import sys

ROLES = ("server", "worker", "runtime")
_ROLE = next((r for r in ROLES if r in sys.argv[1:3]), None)

if os.environ.get("MEMPROBE_DIR") and _ROLE is not None:
    import ctypes
    import ctypes.util
    import gc
    import threading
    import time

    class _MallInfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                   "fsmblks", "uordblks", "fordblks", "keepcost")]

    COLUMNS = ("t_s", "rss", "arena", "hblkhd", "uordblks", "fordblks", "sqlite", "pyblocks", "gc_objects", "threads",
               "rss_anon", "rss_file", "pyarenas")

    def _status_kib(key: str) -> int:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
        return 0

    def _pyarena_bytes() -> int:
        import tempfile

        saved = os.dup(2)
        with tempfile.TemporaryFile() as f:
            os.dup2(f.fileno(), 2)
            try:
                sys._debugmallocstats()
            finally:
                os.dup2(saved, 2)
                os.close(saved)
            f.seek(0)
            for line in f.read().decode(errors="replace").splitlines():
                if "bytes/arena" in line:  # "N arenas * 1048576 bytes/arena = ..."
                    return int(line.split("=")[1].replace(",", ""))
        return 0

    def _dump_trace(path: str, now: float, traced_at: float) -> None:
        import tracemalloc

        snap = tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(False, tracemalloc.__file__)])
        stats = snap.statistics("traceback")
        total = sum(st.size for st in stats)
        lines = [f"=== {now:.0f} s since start, traced since {traced_at:.0f} s: {total / 2**20:.3f} MiB in "
                 f"{sum(st.count for st in stats)} live blocks"]
        for st in stats[:30]:
            lines.append(f"--- {st.size / 2**10:.1f} KiB in {st.count} blocks")
            lines.extend(f"    {fr.filename}:{fr.lineno}" for fr in st.traceback)
        with open(path, "a") as f:
            f.write("\n".join(lines) + "\n")

    def _probe(path: str, every_s: float) -> None:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = _MallInfo2
        sqlite = ctypes.CDLL(ctypes.util.find_library("sqlite3") or "libsqlite3.so.0")
        sqlite.sqlite3_memory_used.restype = ctypes.c_int64
        t0 = time.monotonic()
        with open(path, "w") as f:
            f.write("\t".join(COLUMNS) + "\n")
        traced_role = _ROLE in os.environ.get("MEMPROBE_TRACE_ROLES", "runtime").split(",")
        trace_after = float(os.environ.get("MEMPROBE_TRACE_AFTER_S", "-1")) if traced_role else -1.0
        trace_every = float(os.environ.get("MEMPROBE_TRACE_EVERY_S", "300"))
        traced_at, dumped_at = None, None
        while True:
            now = time.monotonic() - t0
            if trace_after >= 0 and traced_at is None and now >= trace_after:
                import tracemalloc

                tracemalloc.start(int(os.environ.get("MEMPROBE_TRACE_FRAMES", "12")))
                traced_at = dumped_at = now
            elif traced_at is not None and now - dumped_at >= trace_every:
                _dump_trace(path.replace(".tsv", ".trace.txt"), now, traced_at)
                dumped_at = now
            m = libc.mallinfo2()
            with open("/proc/self/statm") as f:
                rss = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
            row = (round(time.monotonic() - t0), rss, m.arena, m.hblkhd, m.uordblks, m.fordblks,
                   sqlite.sqlite3_memory_used(), sys.getallocatedblocks(), len(gc.get_objects()),
                   threading.active_count(), _status_kib("RssAnon"), _status_kib("RssFile"), _pyarena_bytes())
            with open(path, "a") as f:
                f.write("\t".join(map(str, row)) + "\n")
            time.sleep(every_s)

    threading.Thread(target=_probe, name="memprobe", daemon=True,
                     args=(f"{os.environ['MEMPROBE_DIR']}/{_ROLE}-{os.getpid()}.tsv",
                           float(os.environ.get("MEMPROBE_EVERY_S", "30")))).start()
