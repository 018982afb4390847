"""Supervision of `slinger up`'s children (server.site.supervise, server.site.warden): they die with the
stack on kill -9 (grandchildren too), dead ones are restarted with back-off, bad configuration
is not retried in a loop."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from server.site.supervise import STACK_ENV, Children
from tests.conftest import SlingerUp, wait_for


def stack_processes(stack_dir: Path) -> dict[int, str]:
    """pid -> command line of every live process whose environment names ``stack_dir``."""
    marker = f"{STACK_ENV}={stack_dir}".encode() + b"\0"
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if marker in (entry / "environ").read_bytes() + b"\0":
                stat = (entry / "stat").read_text()
                if stat.rsplit(")", 1)[1].split()[0] != "Z":  # zombies are dead already
                    found[int(entry.name)] = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
    return found


HARNESS = """
import sys, time
from pathlib import Path
from server.site.supervise import Children
c = Children(stack_dir=Path(sys.argv[1]))
grand = "import subprocess, time; subprocess.Popen(['sleep', '300']); time.sleep(300)"
c.spawn("kid", [sys.executable, "-c", grand])
c.supervise()
time.sleep(300)
"""


def test_kill_9_of_the_supervisor_takes_children_and_grandchildren(tmp_path):
    stack_dir = tmp_path / "stack"
    harness = subprocess.Popen([sys.executable, "-c", HARNESS, str(stack_dir)], start_new_session=True)
    try:
        # the child, its `sleep` grandchild and the warden
        wait_for(lambda: len(stack_processes(stack_dir)) >= 3, 20, "child, grandchild and warden")
        # the grandchild is a fork of the child until it has exec'd `sleep`
        wait_for(lambda: any(cmd.startswith("sleep") for cmd in stack_processes(stack_dir).values()), 20,
                 "the grandchild running sleep")
        os.kill(harness.pid, signal.SIGKILL)
        harness.wait(timeout=5)
        wait_for(lambda: not stack_processes(stack_dir), 10, "no process of the stack left")
    finally:
        if harness.poll() is None:
            harness.kill()
        for pid in stack_processes(stack_dir):
            os.kill(pid, signal.SIGKILL)


def _exited(child) -> None:
    child.proc.wait(timeout=20)


def test_restart_back_off_doubles_to_the_cap_and_bad_config_is_not_retried(tmp_path):
    children = Children(warden=False, backoff_base_s=1.0, backoff_cap_s=4.0, stable_s=100.0)
    flaky = children.spawn("flaky", [sys.executable, "-c", "raise SystemExit(1)"])
    bad = children.spawn("bad", [sys.executable, "-c", "raise SystemExit(2)"])
    taken = children.spawn("taken", [sys.executable, "-c", "raise SystemExit(3)"])
    try:
        delays = []
        for _ in range(4):
            _exited(flaky), _exited(bad), _exited(taken)
            now = time.monotonic()
            children.poll_once(now)
            delays.append(flaky.backoff_s)
            assert flaky.restart_at_s == pytest.approx(now + flaky.backoff_s)
            children.poll_once(now + flaky.backoff_s - 0.01)  # not yet
            assert flaky.restart_at_s is not None
            children.poll_once(now + flaky.backoff_s)  # restarts flaky (and taken, at the cap)
        assert delays == [1.0, 2.0, 4.0, 4.0] and flaky.restarts == 4
        assert bad.given_up and bad.restarts == 0 and bad.restart_at_s is None
        assert taken.backoff_s == 4.0 and taken.restarts >= 1  # exit 3: retried, only ever at the cap
    finally:
        children.stop(grace_s=2)


def test_slinger_up_restarts_a_killed_runtime_and_leaves_nothing_on_kill_9(tmp_path):
    with SlingerUp(tmp_path) as up:
        up.wait_machine_online()
        stack_dir = up.data_dir.resolve()
        procs = stack_processes(stack_dir)
        runtime = [pid for pid, cmd in procs.items() if " runtime " in cmd]
        assert len(runtime) == 1 and any(" plant " in cmd for cmd in procs.values()), procs
        os.kill(runtime[0], signal.SIGKILL)
        wait_for(lambda: "runtime-m1 exited with code -9" in up.log_text(), 10, "the exit logged")
        up.wait_machine_online(timeout_s=60)
        new = [pid for pid, cmd in stack_processes(stack_dir).items() if " runtime " in cmd]
        assert len(new) == 1 and new != runtime
        assert "restarting it in 1.0 s (restart 1" in up.log_text()

        os.kill(up.proc.pid, signal.SIGKILL)
        wait_for(lambda: not stack_processes(stack_dir), 15, "no process of the stack after kill -9 of slinger up")
