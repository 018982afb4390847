"""Supervision of the processes ``slinger up`` spawns (simulated machines, runtimes).

Guarantees, and how:

- **A child dies with the stack, also on ``kill -9`` of ``slinger up``.** Each child is started
  in its own session (own process group, so Ctrl-C in the terminal does not reach it directly)
  with ``prctl(PR_SET_PDEATHSIG, SIGTERM)`` set in the child before ``exec`` (Linux): the kernel
  sends it SIGTERM when the thread that spawned it ends. Children are therefore only spawned
  from long-lived threads (the main thread and the supervisor thread).
- **So do the children's own children.** A warden process (:mod:`server.site.warden`) holds the read
  end of a pipe whose write end only ``slinger up`` has; it learns every child's process group.
  When ``slinger up`` ends in any way the pipe closes and the warden sends SIGTERM to every group
  that still exists, then SIGKILL after :data:`server.site.warden.GRACE_S`. Every child (and what it
  spawns) also carries ``SLINGER_STACK_DIR=<data dir>`` in its environment, which is how a test
  or an operator finds the processes of one stack (``/proc/<pid>/environ``).
- **SIGTERM / Ctrl-C of ``slinger up`` stop everything cleanly:** :meth:`Children.stop` sends
  SIGTERM to each child's process group (runtimes before plants), waits, then SIGKILLs the rest.
- **A child that dies while the stack lives is restarted** with exponential back-off
  (:data:`BACKOFF_BASE_S` doubling up to :data:`BACKOFF_CAP_S`; back to the base once a child
  ran :data:`STABLE_S`). Exit code 2 (bad configuration) is not retried: it cannot get better by
  itself. Exit code 3 ("machine already has a runtime") is retried at the cap only, since the
  other runtime may go away.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

STOP_GRACE_S = 10.0
BACKOFF_BASE_S = 1.0
BACKOFF_CAP_S = 30.0
STABLE_S = 60.0
EXIT_BAD_CONFIG = 2
EXIT_ALREADY_RUNNING = 3
STACK_ENV = "SLINGER_STACK_DIR"
PR_SET_PDEATHSIG = 1  # <linux/prctl.h>

_prctl = None


def _libc_prctl():
    """libc's prctl, resolved once in the parent (the child must not load libraries after fork)."""
    global _prctl
    if _prctl is None and sys.platform.startswith("linux"):
        _prctl = ctypes.CDLL(None, use_errno=True).prctl
    return _prctl


def die_with_parent(sig: int = signal.SIGTERM):
    """A ``preexec_fn``: the child gets ``sig`` when the spawning thread of its parent ends.

    If the parent already died between fork and prctl (the child was re-parented), the child
    sends itself ``sig`` at once. No-op off Linux."""
    prctl, parent = _libc_prctl(), os.getpid()

    def preexec() -> None:
        if prctl is not None:
            prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0)
            if os.getppid() != parent:
                os.kill(os.getpid(), sig)

    return preexec


def _killpg(pgid: int, sig: int) -> bool:
    """Signal a process group; False if it no longer exists."""
    try:
        os.killpg(pgid, sig)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        log.warning("no permission to signal process group %d", pgid)
        return False


@dataclass
class Child:
    """One supervised process. ``restarts`` counts respawns; ``given_up`` is set when it
    exited with :data:`EXIT_BAD_CONFIG` and is left down."""

    name: str
    argv: list[str]
    log_dir: Path | None = None
    proc: subprocess.Popen | None = None
    started_s: float = 0.0
    restarts: int = 0
    backoff_s: float = 0.0
    restart_at_s: float | None = None
    given_up: bool = False


@dataclass
class Children:
    """Spawned subprocesses; :meth:`supervise` restarts dead ones, :meth:`stop` ends them all.

    Args:
        stack_dir: value of ``SLINGER_STACK_DIR`` in the children's environment (the data dir).
        warden: start the warden (children die even on ``kill -9`` of this process).
        backoff_base_s / backoff_cap_s / stable_s: restart back-off, s (module defaults).
    """

    stack_dir: Path | None = None
    warden: bool = True
    backoff_base_s: float = BACKOFF_BASE_S
    backoff_cap_s: float = BACKOFF_CAP_S
    stable_s: float = STABLE_S
    items: list[Child] = field(default_factory=list)
    _stopping: threading.Event = field(default_factory=threading.Event)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _warden: subprocess.Popen | None = None

    def _env(self) -> dict[str, str]:
        env = dict(os.environ)
        if self.stack_dir is not None:
            env[STACK_ENV] = str(self.stack_dir)
        return env

    def _tell_warden(self, line: str) -> None:
        if self.warden and self._warden is None:
            self._warden = subprocess.Popen([sys.executable, "-m", "server.site.warden"], stdin=subprocess.PIPE,
                                            start_new_session=True, env=self._env())
        if self._warden is not None and self._warden.stdin is not None:
            try:
                self._warden.stdin.write(f"{line}\n".encode())
                self._warden.stdin.flush()
            except (BrokenPipeError, ValueError):
                log.warning("the stack's warden is gone: children may outlive a kill -9 of this process")

    def spawn(self, name: str, argv: list[str], log_dir: Path | None = None) -> Child:
        """Start ``argv`` supervised (own session, dies with this process); output goes to
        ``<log_dir>/<name>.log`` (appended across restarts) when given, else is inherited."""
        child = Child(name, argv, log_dir)
        self._start(child)
        with self._lock:
            self.items.append(child)
        return child

    def _start(self, child: Child) -> None:
        out = None
        if child.log_dir is not None:
            child.log_dir.mkdir(parents=True, exist_ok=True)
            out = open(child.log_dir / f"{child.name}.log", "ab")
        try:
            proc = child.proc = subprocess.Popen(child.argv, stdout=out, stderr=subprocess.STDOUT if out else None,
                                          start_new_session=True, cwd=os.getcwd(), env=self._env(),
                                          preexec_fn=die_with_parent())
        finally:
            if out is not None:
                out.close()
        child.started_s, child.restart_at_s = time.monotonic(), None
        self._tell_warden(f"+{proc.pid}")  # the child leads its own process group
        log.info("started %s (pid %d): %s", child.name, proc.pid, " ".join(child.argv[1:]))

    def _on_exit(self, child: Child, rc: int, now_s: float) -> None:
        """Log the exit, clear what the child left in its group, schedule the restart."""
        if child.proc is None:
            raise RuntimeError(f"{child.name} exited before it was started")
        pgid = child.proc.pid
        _killpg(pgid, signal.SIGKILL)  # its own children, if any survived it
        self._tell_warden(f"-{pgid}")
        if rc == EXIT_BAD_CONFIG:
            child.given_up = True
            log.error("%s exited with code %d (bad configuration): NOT restarting it; see its log", child.name, rc)
            return
        if rc == EXIT_ALREADY_RUNNING:
            delay = self.backoff_cap_s
        elif now_s - child.started_s >= self.stable_s or child.backoff_s == 0.0:
            delay = self.backoff_base_s
        else:
            delay = min(2.0 * child.backoff_s, self.backoff_cap_s)
        child.backoff_s, child.restart_at_s = delay, now_s + delay
        log.error("%s exited with code %d after %.1f s: restarting it in %.1f s (restart %d; see its log)",
                  child.name, rc, now_s - child.started_s, delay, child.restarts + 1)

    def poll_once(self, now_s: float | None = None) -> None:
        """One supervision step: notice exits, restart those whose back-off has passed."""
        now_s = time.monotonic() if now_s is None else now_s
        with self._lock:
            items = list(self.items)
        for c in items:
            if self._stopping.is_set():
                return
            if c.given_up or c.proc is None:
                continue
            if c.restart_at_s is None:
                rc = c.proc.poll()
                if rc is not None:
                    self._on_exit(c, rc, now_s)
            elif now_s >= c.restart_at_s:
                c.restarts += 1
                try:
                    self._start(c)
                except OSError as e:
                    log.error("cannot restart %s: %s", c.name, e)
                    c.restart_at_s = now_s + self.backoff_cap_s

    def supervise(self, period_s: float = 0.2) -> threading.Thread:
        """A daemon thread running :meth:`poll_once` until :meth:`stop`. It must live as long
        as the children it restarts (their parent-death signal is tied to the spawning thread)."""

        def loop() -> None:
            while not self._stopping.wait(period_s):
                try:
                    self.poll_once()
                except Exception:  # keep supervising: this thread's end would kill its children
                    log.exception("supervision step failed")

        t = threading.Thread(target=loop, name="children-supervisor", daemon=True)
        t.start()
        return t

    def stop(self, grace_s: float = STOP_GRACE_S) -> None:
        """SIGTERM every child's process group (last started first: runtimes before plants),
        wait up to ``grace_s`` in total, SIGKILL what is left; then release the warden."""
        self._stopping.set()
        with self._lock:
            items = list(self.items)
        for c in reversed(items):
            if c.proc is not None and c.proc.poll() is None:
                _killpg(c.proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for c in items:
            if c.proc is None:
                continue
            try:
                c.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s: killing it", c.name, grace_s)
                c.proc.kill()
                c.proc.wait(timeout=5.0)
            _killpg(c.proc.pid, signal.SIGKILL)  # leftovers of its group
        if self._warden is not None:
            if self._warden.stdin is not None:  # always a pipe
                self._warden.stdin.close()  # EOF: the warden finds no group left and exits
            try:
                self._warden.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._warden.kill()
