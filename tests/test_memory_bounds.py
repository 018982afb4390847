"""The server's memory bounds (docs/safety.md, memory): each SQLite connection's page cache is
bounded, and the heap glibc keeps free is given back to the system periodically."""

from __future__ import annotations

import os

import pytest
from sqlalchemy import text

from server.db.session import SQLITE_CACHE_KIB, make_engine
from runtime.heap import HeapTrimmer


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def test_every_sqlite_connection_has_a_bounded_page_cache(tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path / 'db.sqlite'}")
    conns = [engine.connect() for _ in range(3)]  # three pooled connections, each set up on connect
    try:
        for c in conns:
            assert c.execute(text("PRAGMA cache_size")).scalar() == -SQLITE_CACHE_KIB
    finally:
        for c in conns:
            c.close()
        engine.dispose()


def test_the_heap_trimmer_runs_when_due_and_gives_free_pages_back():
    trimmer = HeapTrimmer(every_s=3600.0)
    if not trimmer.available:
        pytest.skip("not glibc: no malloc_trim")
    assert trimmer.tick() is False  # not due yet
    blocks = [bytearray(2000) for _ in range(60_000)]  # ~120 MiB of small blocks in the heap
    kept = blocks[::1000]  # one block in a thousand stays in use: the free memory between them stays resident
    del blocks
    before = _rss_bytes()
    trimmer.every_s = 0.0
    trimmer._due = 0.0  # noqa: SLF001  due now
    assert trimmer.tick() is True
    assert trimmer.trims == 1 and trimmer.max_s >= trimmer.last_s > 0.0
    assert _rss_bytes() < before - 50 * 2**20  # most of the free heap went back to the system
    assert len(kept) == 60



HEAP_PROBE = """
import ctypes, re, sys, tempfile, threading
from runtime.heap import bound_heap
if sys.argv[1] == "bounded":
    assert bound_heap(2, 256 * 1024)
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
libc.fopen.restype = ctypes.c_void_p
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
libc.fclose.argtypes = [ctypes.c_void_p]
class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                 "fsmblks", "uordblks", "fordblks", "keepcost")]
libc.mallinfo2.restype = MallInfo2
# a freed 4 MiB mapped block raises glibc's dynamic mmap threshold to 4 MiB; is a 1 MiB block then mapped?
libc.free(libc.malloc(4 << 20))
before = libc.mallinfo2().hblks
block = libc.malloc(1 << 20)
mapped = libc.mallinfo2().hblks - before
alive = threading.Barrier(8)
def first_malloc():  # each thread's first malloc picks an arena; all eight alive at once
    libc.malloc(4096)
    alive.wait()
threads = [threading.Thread(target=first_malloc) for _ in range(8)]
for t in threads: t.start()
for t in threads: t.join()
path = tempfile.mktemp()
fp = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, fp)
libc.fclose(fp)
print(len(re.findall('<heap nr=', open(path).read())), mapped)
"""


@pytest.mark.skipif(not HeapTrimmer().available, reason="glibc only")
def test_the_heap_bounds_cap_the_arenas_and_keep_large_blocks_mapped():
    import subprocess
    import sys

    from runtime.heap import bound_heap

    def probe(mode: str) -> tuple[int, int]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
        out = subprocess.run([sys.executable, "-c", HEAP_PROBE, mode], capture_output=True, text=True, check=True, env=env)
        arenas, mapped = out.stdout.split()
        return int(arenas), int(mapped)

    arenas, mapped = probe("default")
    assert arenas > 2  # glibc's default: an arena for each new thread (up to 8 per core)
    assert mapped == 0  # the dynamic threshold, raised by the freed 4 MiB block, put the 1 MiB block in the heap
    assert probe("bounded") == (2, 1)  # two arenas at most; the block mapped (given back whole on free)
    with pytest.raises(ValueError):
        bound_heap(0)
    with pytest.raises(ValueError):
        bound_heap(2, 64 * 1024 * 1024)
