"""Memory probe of bench_soak's server and worker (``bench_soak.py --probe-dir DIR`` puts this
folder on the stack's PYTHONPATH; Python imports ``sitecustomize`` at start-up, site(3)).

In a process started as ``slinger server`` or ``slinger worker``, a daemon thread appends a row
every ``MEMPROBE_EVERY_S`` seconds (default 30) to ``$MEMPROBE_DIR/<role>-<pid>.tsv``: seconds
since start, resident memory (bytes, /proc/self/statm), glibc's heap figures (mallinfo2(3):
``arena`` bytes taken from the system by malloc outside mmap, ``hblkhd`` bytes in mmapped
blocks, ``uordblks`` bytes in use, ``fordblks`` bytes free inside the heap), the bytes SQLite
holds (``sqlite3_memory_used``: page caches, prepared statements), Python's allocated blocks
(``sys.getallocatedblocks``), objects tracked by the garbage collector and threads. Growth of
``uordblks`` is memory in use; growth of ``fordblks`` with flat use is the allocator keeping
freed memory (fragmentation). Every other process is untouched.
"""

import os
import sys

if os.environ.get("MEMPROBE_DIR") and ("server" in sys.argv[1:3] or "worker" in sys.argv[1:3]):
    import ctypes
    import ctypes.util
    import gc
    import threading
    import time

    class _MallInfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                   "fsmblks", "uordblks", "fordblks", "keepcost")]

    COLUMNS = ("t_s", "rss", "arena", "hblkhd", "uordblks", "fordblks", "sqlite", "pyblocks", "gc_objects", "threads")

    def _probe(path: str, every_s: float) -> None:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallinfo2.restype = _MallInfo2
        sqlite = ctypes.CDLL(ctypes.util.find_library("sqlite3") or "libsqlite3.so.0")
        sqlite.sqlite3_memory_used.restype = ctypes.c_int64
        t0 = time.monotonic()
        with open(path, "w") as f:
            f.write("\t".join(COLUMNS) + "\n")
        while True:
            m = libc.mallinfo2()
            with open("/proc/self/statm") as f:
                rss = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
            row = (round(time.monotonic() - t0), rss, m.arena, m.hblkhd, m.uordblks, m.fordblks,
                   sqlite.sqlite3_memory_used(), sys.getallocatedblocks(), len(gc.get_objects()),
                   threading.active_count())
            with open(path, "a") as f:
                f.write("\t".join(map(str, row)) + "\n")
            time.sleep(every_s)

    _role = "server" if "server" in sys.argv[1:3] else "worker"
    threading.Thread(target=_probe, name="memprobe", daemon=True,
                     args=(f"{os.environ['MEMPROBE_DIR']}/{_role}-{os.getpid()}.tsv",
                           float(os.environ.get("MEMPROBE_EVERY_S", "30")))).start()
