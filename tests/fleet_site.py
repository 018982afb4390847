"""A fleet site as separate processes, without Docker (tests and benchmarks).

Hosts, with ``netns=True`` (root; tests/fleet_net.py): each group on its own network namespace,
all on one bridge in the root namespace (``10.201.<s>.0/24``):

* the *router host*: the Zenoh router ``slinger router``;
* the *site host*: the server ``slinger server`` and a job worker ``slinger worker``, both on
  PostgreSQL, reached through a relay on the bridge address (PostgreSQL itself stays on the
  root namespace's 127.0.0.1, see tests/fleet_net.TcpRelay);
* one *machine host* per simulated machine: ``slinger plant`` and ``slinger runtime``.

Every Zenoh link is mutual TLS with the site's certificates (``slinger certs`` layout in
``<data_dir>/site``, the router's address in the subjectAltNames) and the site's access control;
server, runtimes and plants are Zenoh *clients* of the router, so cutting a machine host's link
(:meth:`Site.cut`) cuts that machine alone. Without ``netns`` everything runs on this namespace's
loopback (the load benchmark). docker/compose.yaml describes the same services (tests/test_fleet.py
checks the names).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import uuid
from pathlib import Path

import httpx
from sqlalchemy import create_engine, text

from server.site.stack import slinger_command
from tests.conftest import ADMIN, TEST_POLICY_CHECK, free_port, login, serving, wait_for
from tests.fleet_net import Net, TcpRelay

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


class Site:
    """The fleet site (context manager). Attributes after entering: ``base_url``, ``http``
    (logged in as the admin), ``database_url`` (from this process), ``machines`` (ids),
    ``procs`` (name -> Popen), ``router_endpoint`` (the router's Zenoh endpoint), ``site_dir``
    (the site's certificates and command keys), ``net`` (tests.fleet_net.Net or None).

    Args:
        tmp: folder for logs, data, outboxes.
        machines: number of simulated machines (m1..mN).
        policy: the 2D policy ONNX file (manifest beside it) the runtimes run.
        netns: router, site and each machine on their own network namespace (root only).
        tls: Zenoh links over mutual TLS with the site's access control (default), else plain TCP.
        server_env: extra ``SLINGER_*`` settings of the server.
    """

    def __init__(self, tmp: Path, machines: int, policy: Path, netns: bool = False, tls: bool = True,
                 server_env: dict | None = None):
        self.tmp, self.n, self.policy, self.netns, self.tls = Path(tmp), machines, Path(policy), netns, tls
        self.server_env = server_env or {}
        self.tag = uuid.uuid4().hex[:5]
        self.machines = [f"m{i}" for i in range(1, machines + 1)]
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs: list = []
        self.db_name = f"slinger_site_{self.tag}"
        self.database_url = f"postgresql+psycopg://postgres@127.0.0.1:5432/{self.db_name}"
        self.host_db = "127.0.0.1:5432"  # PostgreSQL as the site host reaches it
        self.zport, self.port = free_port(), free_port()
        self.data_dir = self.tmp / "site"
        self.site_dir = self.data_dir / "site"  # the server's default site dir
        self.http: httpx.Client | None = None
        self.net: Net | None = None
        self._relay: TcpRelay | None = None

    # --- hosts -------------------------------------------------------------------------------
    def cut(self, machine_id: str) -> None:
        """Take the machine host's link down (bridge side of its veth); needs ``netns``."""
        self.net.cut(machine_id)

    def restore(self, machine_id: str) -> None:
        self.net.restore(machine_id)

    def _hosts(self) -> dict[str, tuple[str | None, str]]:
        """(namespace, address) of the router host, the site host and every machine host."""
        names = ["router", "site", *self.machines]
        if not self.netns:
            return {n: (None, "127.0.0.1") for n in names}
        self.net = Net(self.tag[:5], int(self.tag[:2], 16))
        hosts = {n: self.net.add_host(n) for n in names}
        self._relay = TcpRelay(self.net.gateway, ("127.0.0.1", 5432))
        self.host_db = f"{self.net.gateway}:{self._relay.port}"
        return hosts

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
        from server.site.certs import make_site
        from server.db.migrate import upgrade
        from server.site.stack import register_policies

        upgrade(self.database_url)
        register_policies(self.database_url, self.data_dir, {"2d": self.policy})
        subprocess.run(slinger_command("user", "add", "--admin", "--password", ADMIN[1], "--database-url",
                                       self.database_url), check=True, capture_output=True, timeout=120)
        hosts = self._hosts()
        router_ns, router_ip = hosts["router"]
        site_ns, site_ip = hosts["site"]
        make_site(self.site_dir, self.machines, ips=[router_ip])  # CA, certificates, command keys
        scheme, tls = ("tls", ["--tls-dir", str(self.site_dir)]) if self.tls else ("tcp", [])
        self.router_endpoint = f"{scheme}/{router_ip}:{self.zport}"
        host_db_url = f"postgresql+psycopg://postgres@{self.host_db}/{self.db_name}"
        db = ["--database-url", host_db_url, "--data-dir", str(self.data_dir)]
        self._spawn("router", slinger_command("router", "--listen", f"{scheme}/0.0.0.0:{self.zport}", *tls), router_ns)
        self._spawn("server", slinger_command("server", "--host", site_ip, "--port", str(self.port), "--zenoh-mode",
                                              "client", "--connect", self.router_endpoint, *tls, *db),
                    site_ns, env={"SLINGER_VISER_ENABLED": "false", "SLINGER_JOB_QUEUE_URL": self.queue_url,
                                  **self.server_env})
        self._spawn("worker", slinger_command("worker", *db, "--queue-url", self.queue_url), site_ns)
        for i, mid in enumerate(self.machines, start=1):
            ns = hosts[mid][0]
            link = ["--mode", "client", "--connect", self.router_endpoint, *tls]
            self._spawn(f"plant-{mid}", slinger_command("plant", "--machine-id", mid, "--seed", str(i), *link), ns)
            self._spawn(f"runtime-{mid}", slinger_command(
                "runtime", "--machine-id", mid, "--policy-2d", str(self.policy), *link, "--command-key",
                str(self.site_dir / "machines" / mid / "command.key"), *TEST_POLICY_CHECK,
                "--outbox-dir", str(self.tmp / "outbox" / mid)), ns)
        self.base_url = f"http://{site_ip}:{self.port}"

        def up():
            for name, p in self.procs.items():
                if p.poll() is not None:
                    raise RuntimeError(f"{name} exited: {self.log(name)[-2000:]}")
            return serving(self.base_url)

        wait_for(up, 120, "fleet server serving")
        self.http = httpx.Client(base_url=self.base_url, timeout=30)
        login(self.http, *ADMIN)

    @property
    def queue_url(self) -> str:
        """The job queue (PostgreSQL) as the site host reaches it."""
        return f"postgresql://postgres@{self.host_db}/{self.db_name}"

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
        if self._relay is not None:
            self._relay.close()
        if self.net is not None:
            self.net.close()
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
