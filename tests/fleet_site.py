"""A fleet site as separate processes, without Docker (tests and benchmarks).

Hosts: the *site host* (this network namespace: PostgreSQL at 127.0.0.1:5432, the Zenoh router
``slinger router``, the server ``slinger server`` and a job worker ``slinger worker``, both on
PostgreSQL) and one *machine host* per simulated machine: with ``netns=True`` a network
namespace made here (``ip netns add`` + a veth pair, 10.201.<i>.2 on the machine side,
10.201.<i>.1 on the site side; needs root), else the site host's loopback. On every machine
host the simulated machine (``slinger plant``) and its runtime (``slinger runtime``) run as Zenoh
*clients* of the router, so cutting a machine host's link (:meth:`Site.cut`) cuts that machine
alone. docker/compose.yaml describes the same services (tests/test_fleet.py checks the names).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import uuid
from pathlib import Path

import httpx
from sqlalchemy import create_engine, text

from server.stack import slinger_command
from tests.conftest import ADMIN, free_port, login, wait_for

PG_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
SERVICES = ("router", "server", "worker", "plant", "runtime")
"""What this site starts; docker/compose.yaml must name each."""


def netns_available() -> str | None:
    """None if this process may make network namespaces, else the reason it may not."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "iproute2 (ip) is not installed"
    name = f"slf-probe-{uuid.uuid4().hex[:6]}"
    r = subprocess.run(["ip", "netns", "add", name], capture_output=True, text=True)
    if r.returncode != 0:
        return f"ip netns add is not permitted here: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", name], capture_output=True)
    return None


def _ip(*args: str, ns: str | None = None) -> None:
    argv = ["ip", *(("netns", "exec", ns, "ip") if ns else ()), *args]
    subprocess.run(argv, check=True, capture_output=True, text=True)


class Site:
    """The fleet site (context manager). Attributes after entering: ``base_url``, ``http``
    (logged in as the admin), ``database_url``, ``machines`` (ids), ``procs`` (name -> Popen).

    Args:
        tmp: folder for logs, data, outboxes.
        machines: number of simulated machines (m1..mN).
        policy: the 2D policy ONNX file (manifest beside it) the runtimes run.
        netns: one network namespace per machine host (root only).
        server_env: extra ``SLINGER_*`` settings of the server.
    """

    def __init__(self, tmp: Path, machines: int, policy: Path, netns: bool = False, server_env: dict | None = None):
        self.tmp, self.n, self.policy, self.netns = Path(tmp), machines, Path(policy), netns
        self.server_env = server_env or {}
        self.tag = uuid.uuid4().hex[:5]
        self.machines = [f"m{i}" for i in range(1, machines + 1)]
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: list = []
        self._ns: list[str] = []
        self.db_name = f"slinger_site_{self.tag}"
        self.database_url = f"postgresql+psycopg://postgres@127.0.0.1:5432/{self.db_name}"
        self.zport, self.port = free_port(), free_port()
        self.data_dir = self.tmp / "site"
        self.http: httpx.Client | None = None

    # --- hosts -------------------------------------------------------------------------------
    def ns(self, i: int) -> str:
        return f"slf-{self.tag}-{i}"

    def router_address(self, i: int) -> str:
        return f"10.201.{i}.1" if self.netns else "127.0.0.1"

    def _make_host(self, i: int) -> None:
        ns, site_if, host_if = self.ns(i), f"vs{self.tag}{i}", f"vh{self.tag}{i}"
        _ip("netns", "add", ns)
        self._ns.append(ns)
        _ip("link", "add", site_if, "type", "veth", "peer", "name", host_if)
        _ip("link", "set", host_if, "netns", ns)
        _ip("addr", "add", f"10.201.{i}.1/24", "dev", site_if)
        _ip("link", "set", site_if, "up")
        _ip("addr", "add", f"10.201.{i}.2/24", "dev", host_if, ns=ns)
        _ip("link", "set", host_if, "up", ns=ns)
        _ip("link", "set", "lo", "up", ns=ns)

    def cut(self, machine_id: str) -> None:
        """Take the machine host's link down (site side of its veth)."""
        _ip("link", "set", f"vs{self.tag}{self.machines.index(machine_id) + 1}", "down")

    def restore(self, machine_id: str) -> None:
        _ip("link", "set", f"vs{self.tag}{self.machines.index(machine_id) + 1}", "up")

    # --- processes ---------------------------------------------------------------------------
    def _spawn(self, name: str, argv: list[str], ns: str | None = None, env: dict | None = None) -> None:
        log = open(self.tmp / f"{name}.log", "wb")
        self._logs.append(log)
        prefix = ["ip", "netns", "exec", ns] if ns else []
        self.procs[name] = subprocess.Popen([*prefix, *argv], stdout=log, stderr=subprocess.STDOUT,
                                            env={**os.environ, **(env or {})}, start_new_session=True)

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text(errors="replace")

    def __enter__(self) -> "Site":
        admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
        with admin.connect() as c:
            c.execute(text(f'CREATE DATABASE "{self.db_name}"'))
        admin.dispose()
        try:
            self._start()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _start(self) -> None:
        from server.db.migrate import upgrade
        from server.stack import register_policies

        upgrade(self.database_url)
        register_policies(self.database_url, self.data_dir, {"2d": self.policy})
        subprocess.run(slinger_command("user", "add", "--admin", "--password", ADMIN[1], "--database-url",
                                       self.database_url), check=True, capture_output=True, timeout=120)
        db = ["--database-url", self.database_url, "--data-dir", str(self.data_dir)]
        self._spawn("router", slinger_command("router", "--listen", f"tcp/0.0.0.0:{self.zport}"))
        self._spawn("server", slinger_command("server", "--port", str(self.port), "--zenoh-mode", "client",
                                              "--connect", f"tcp/127.0.0.1:{self.zport}", *db),
                    env={"SLINGER_VISER_ENABLED": "false", "SLINGER_JOB_QUEUE_URL": self.queue_url, **self.server_env})
        self._spawn("worker", slinger_command("worker", *db, "--queue-url", self.queue_url))
        from server.certs import make_site

        site = make_site(self.data_dir / "site", self.machines)  # the server's default site dir: command keys
        for i, mid in enumerate(self.machines, start=1):
            ns = None
            if self.netns:
                self._make_host(i)
                ns = self.ns(i)
            link = ["--mode", "client", "--connect", f"tcp/{self.router_address(i)}:{self.zport}"]
            self._spawn(f"plant-{mid}", slinger_command("plant", "--machine-id", mid, "--seed", str(i), *link), ns)
            self._spawn(f"runtime-{mid}", slinger_command("runtime", "--machine-id", mid, "--policy-2d", str(self.policy),
                                                          *link, "--command-key", str(site.command_key(mid)),
                                                          "--outbox-dir", str(self.tmp / "outbox" / mid)), ns)
        self.base_url = f"http://127.0.0.1:{self.port}"

        def up():
            for name, p in self.procs.items():
                if p.poll() is not None:
                    raise RuntimeError(f"{name} exited: {self.log(name)[-2000:]}")
            try:
                return httpx.get(f"{self.base_url}/api/health", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for(up, 120, "fleet server serving")
        self.http = httpx.Client(base_url=self.base_url, timeout=30)
        login(self.http, *ADMIN)

    @property
    def queue_url(self) -> str:
        return "postgresql://postgres@127.0.0.1:5432/" + self.db_name

    def online(self) -> dict[str, dict]:
        """Machines the server sees online with a state, by id."""
        return {m["id"]: m for m in self.http.get("/api/machines").json() if m["online"] and m["cabin_turn_rad"] is not None}

    def __exit__(self, *exc) -> None:
        if self.http is not None:
            self.http.close()
        for p in reversed(list(self.procs.values())):
            if p.poll() is None:
                p.terminate()
        for name, p in self.procs.items():
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, 9)
                p.wait(timeout=5)
        for f in self._logs:
            f.close()
        for ns in self._ns:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
        with admin.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{self.db_name}" WITH (FORCE)'))
        admin.dispose()


class Worker:
    """``slinger worker`` as a subprocess (context manager); SIGINT on exit. ``hostname``: run
    it in its own UTS namespace under that host name (root; ``unshare --uts``), so that it is
    "another host" for the pid checks of server.jobs.leases (the pid stays the Popen's)."""

    def __init__(self, settings, *extra: str, hostname: str | None = None):
        self.prefix = (["unshare", "--uts", "sh", "-c", f'hostname {hostname} && exec "$@"', "worker"]
                       if hostname else [])
        self.argv = slinger_command("worker", "--database-url", settings.database_url, "--data-dir",
                                    str(settings.data_dir), *(("--queue-url", settings.job_queue_url)
                                                              if settings.job_queue_url else ()), *extra)
        self.log = Path(settings.data_dir) / f"worker-{uuid.uuid4().hex[:6]}.log"

    def __enter__(self):
        self.log.parent.mkdir(parents=True, exist_ok=True)
        self._out = open(self.log, "wb")
        self.proc = subprocess.Popen([*self.prefix, *self.argv], stdout=self._out, stderr=subprocess.STDOUT)
        return self

    def __exit__(self, *exc):
        if self.proc.poll() is not None:
            self._out.close()
            return
        self.proc.send_signal(2)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        self._out.close()

    def text(self) -> str:
        return self.log.read_text(errors="replace")
