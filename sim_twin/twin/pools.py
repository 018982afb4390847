"""Process pools of the twin's batch work (evaluation, site matrix, dataset generation, benchmark).

The pools start their workers from a fresh interpreter (multiprocessing's ``forkserver``), never
by forking the caller: a caller with threads (a Zenoh session, a job worker's heartbeat, a test
process that ran a server) may hold a lock at the moment of a fork, and a forked worker that needs
that lock waits forever (Python's documentation of ``os.fork``: "forking a multi-threaded process
is problematic"; Python 3.14 makes forkserver the default on Linux for that reason). Workers import
MuJoCo and the policy on their first task, so the cost is about a second per worker per pool.
Everything submitted must be picklable (module-level functions and plain arguments).

No worker outlives its pool's owner (the process that made the pool): a worker's parent is the
forkserver, which stays up while any worker holds its "alive" pipe, so a parent-death signal alone
would never fire. Each worker therefore watches the owner itself: a thread blocks on a pidfd of the
owner (pidfd_open(2)) and ends the worker when the owner exits, however it died; the worker also
asks for SIGKILL when the forkserver dies (prctl(2) ``PR_SET_PDEATHSIG``). With the workers gone
the forkserver sees its alive pipe close and exits. So a kill -9 of a job worker or of a whole
``slinger up`` stack leaves no pool process behind.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import select
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor

PR_SET_PDEATHSIG = 1
"""prctl(2) option: the signal this process gets when its parent thread exits (linux/prctl.h)."""


def die_with_parent(sig: int = signal.SIGKILL) -> bool:
    """Ask the kernel to send ``sig`` to this process when its parent exits (Linux only).

    Returns:
        True if set (False elsewhere, or if prctl refused). Exits at once if the parent is
        already gone (the request would never fire then: prctl(2) "parent death signal").
    """
    if not sys.platform.startswith("linux"):
        return False
    parent = os.getppid()
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, sig, 0, 0, 0) != 0:
        return False
    if os.getppid() != parent or parent == 1:  # orphaned before the request took effect
        os._exit(1)
    return True


def exit_with(owner_pid: int) -> None:
    """End this process (exit status 1) when process ``owner_pid`` exits: a daemon thread waits on
    a pidfd of it (Linux >= 5.3; elsewhere it polls every second). Also :func:`die_with_parent`.
    A pool worker's initializer."""
    die_with_parent()
    try:
        fd = os.pidfd_open(owner_pid)
    except ProcessLookupError:  # gone already
        os._exit(1)
    except (AttributeError, OSError):  # no pidfd here: poll
        fd = None

    def watch() -> None:
        if fd is not None:
            select.select([fd], [], [])
        else:
            while _alive(owner_pid):
                time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="owner-watch", daemon=True).start()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def process_pool(workers: int | None = None) -> ProcessPoolExecutor:
    """A ProcessPoolExecutor of ``workers`` processes (default: every core) started by forkserver,
    each ending when this process exits (:func:`exit_with`)."""
    return ProcessPoolExecutor(max_workers=workers or os.cpu_count() or 1,
                               mp_context=multiprocessing.get_context("forkserver"), initializer=exit_with,
                               initargs=(os.getpid(),))
