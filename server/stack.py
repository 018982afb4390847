"""``slinger up``: the whole stack on one machine.

One process holds the server (FastAPI + viser) and an embedded Zenoh peer listening on
``tcp/127.0.0.1:<zenoh_port>``; per machine it spawns the simulated machine (``slinger plant``)
and its runtime (``slinger runtime``) as subprocesses that connect to that peer. The children
also listen on an ephemeral loopback port so that Zenoh gossip links plant and runtime directly
(peers do not forward for each other). Children run in their own process group; the stack stops
them (SIGTERM, then SIGKILL after a grace period) when the server exits, e.g. on Ctrl-C.
"""

from __future__ import annotations

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

REPO_DIR = Path(__file__).resolve().parent.parent
DEFAULT_POLICY_2D = REPO_DIR / "policies" / "throw2d.onnx"
DEFAULT_POLICY_3D = REPO_DIR / "policies" / "throw3d.onnx"
STOP_GRACE_S = 10.0


def slinger_command(*args: str) -> list[str]:
    """The argv of ``slinger <args>`` run with this interpreter (works without the script on PATH)."""
    return [sys.executable, "-m", "server.cli", *args]


@dataclass
class Child:
    name: str
    argv: list[str]
    proc: subprocess.Popen | None = None


@dataclass
class Children:
    """Spawned subprocesses; :meth:`watch` logs unexpected exits, :meth:`stop` ends them."""

    items: list[Child] = field(default_factory=list)
    _stopping: threading.Event = field(default_factory=threading.Event)

    def spawn(self, name: str, argv: list[str], log_dir: Path | None = None) -> Child:
        """Start ``argv`` in its own session (Ctrl-C in the terminal does not reach it directly).

        Output goes to ``<log_dir>/<name>.log`` when given, else is inherited."""
        out = None
        if log_dir is not None:
            log_dir.mkdir(parents=True, exist_ok=True)
            out = open(log_dir / f"{name}.log", "ab")
        child = Child(name, argv)
        child.proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT if out else None,
                                      start_new_session=True, cwd=os.getcwd())
        if out is not None:
            out.close()
        log.info("started %s (pid %d): %s", name, child.proc.pid, " ".join(argv[1:]))
        self.items.append(child)
        return child

    def watch(self, period_s: float = 1.0) -> threading.Thread:
        """A daemon thread that reports children that exit while the stack runs."""

        def loop() -> None:
            reported: set[str] = set()
            while not self._stopping.wait(period_s):
                for c in self.items:
                    rc = c.proc.poll() if c.proc else None
                    if rc is not None and c.name not in reported:
                        reported.add(c.name)
                        log.error("%s exited with code %d (see its log)", c.name, rc)

        t = threading.Thread(target=loop, name="children-watch", daemon=True)
        t.start()
        return t

    def stop(self, grace_s: float = STOP_GRACE_S) -> None:
        """SIGTERM every child, wait up to ``grace_s`` in total, SIGKILL what is left."""
        self._stopping.set()
        for c in reversed(self.items):  # runtimes before plants
            if c.proc and c.proc.poll() is None:
                c.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for c in self.items:
            if c.proc is None:
                continue
            try:
                c.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s: killing it", c.name, grace_s)
                c.proc.kill()
                c.proc.wait(timeout=5.0)


def resolve_policy(given: Path | None, default: Path) -> tuple[Path | None, str | None]:
    """(policy path, problem): the given or default ONNX file if it and its manifest exist."""
    path = given or default
    if not path.is_file():
        return None, f"no policy at {path}"
    if not path.with_suffix(".json").is_file():
        return None, f"policy {path} has no manifest {path.with_suffix('.json').name} beside it"
    return path, None


def machine_ids(n: int) -> list[str]:
    """Ids of the simulated machines: m1..mN."""
    return [f"m{i}" for i in range(1, n + 1)]


def spawn_machines(children: Children, n: int, hub: str, policies: dict[str, Path], data_dir: Path) -> None:
    """Per machine: the simulated machine, and its runtime if any policy is given."""
    log_dir = data_dir / "logs"
    for i, mid in enumerate(machine_ids(n)):
        link = ["--connect", hub, "--listen", "tcp/127.0.0.1:0"]
        children.spawn(f"plant-{mid}", slinger_command("plant", "--machine-id", mid, "--seed", str(i), *link), log_dir)
        if not policies:
            continue
        pol = [a for mode, p in sorted(policies.items()) for a in (f"--policy-{mode}", str(p))]
        children.spawn(f"runtime-{mid}", slinger_command(
            "runtime", "--machine-id", mid, *pol, *link, "--outbox-dir", str(data_dir / "outbox" / mid)), log_dir)


def register_policies(database_url: str, data_dir: Path, policies: dict[str, Path]) -> None:
    """Record the deployed policy versions (with their manifests: the target range) in the DB."""
    import json

    from server.db.session import make_engine, make_sessionmaker
    from server.results import ResultStore

    engine = make_engine(database_url)
    try:
        store = ResultStore(make_sessionmaker(engine), data_dir)
        for path in policies.values():
            store.register_policy(json.loads(path.with_suffix(".json").read_text()), onnx_path=path)
    finally:
        engine.dispose()
