"""The whole stack as separate processes, for fault injection (tests/test_faults.py and
tests/benchmarks/bench_estop_latency.py).

``slinger server`` (API + fleet link, Zenoh peer listening on loopback), a ``slinger worker``
(previews), ``slinger plant`` and
``slinger runtime`` for machine m1 (each also listening on an ephemeral loopback port so that
Zenoh gossip links plant and runtime directly), the machine's command key in the server's site
dir and given to the runtime. Every process is a direct child of the test, so a test can kill -9
any one of them and start it again. Every argv names the stack's directory, so a ``ps`` scan for
it finds any process left behind (:func:`orphans`).

Short reconciliation bounds (result grace 4 s, runtime gone 8 s, pass every 0.5 s) keep the
fault cases lean; the defaults (15 s, 30 s, 2 s) are what a site runs.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from runtime.protocol import keys
from runtime.protocol.messages import MachineState, SimReset, ValveCommand, decode, encode
from runtime.zenoh_session import open_session
from server.site.stack import slinger_command
from tests.conftest import ADMIN, TEST_POLICY_CHECK, free_port, login, machine_key, wait_for

log = logging.getLogger(__name__)

TARGET_2D = [8.0, -0.292, 0.0]
FINAL = ("landed", "failed", "aborted", "lost")
FAST_BOUNDS = {"SLINGER_RESULT_GRACE_S": "4", "SLINGER_RUNTIME_GONE_S": "8", "SLINGER_RECONCILE_PERIOD_S": "0.5"}


def orphans(marker: Path | str) -> list[str]:
    """Command lines of live processes that mention ``marker`` (the test's directory)."""
    out = subprocess.run(["ps", "-eo", "pid=,stat=,args="], capture_output=True, text=True).stdout
    mine = {str(os.getpid()), str(os.getppid())}  # this process and its launcher (e.g. `timeout ... --keep DIR`)
    return [line.strip() for line in out.splitlines()
            if str(marker) in line and line.split()[0] not in mine and not line.split()[1].startswith("Z")]


def burner() -> subprocess.Popen:
    """A CPU-burning process (a busy loop), stopped with :func:`stop_proc`."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def stop_proc(proc: subprocess.Popen | None, sig: int = signal.SIGTERM, timeout_s: float = 15.0) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(sig)
    try:
        proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)


class ValveWatch:
    """Records what a machine does, seen on Zenoh: its ValveCommands (receive time.monotonic(),
    u) and the largest active joint speed of each MachineState (time, max |qd[:4]|)."""

    def __init__(self, endpoint: str, machine_id: str = "m1"):
        self.samples: list[tuple[float, list[float]]] = []
        self.speeds: list[tuple[float, float]] = []
        self.session = open_session(mode="peer", connect=(endpoint,), listen=("tcp/127.0.0.1:0",))
        self._subs = [self.session.declare_subscriber(keys.valve_cmd(machine_id), self._on),
                      self.session.declare_subscriber(keys.state(machine_id), self._on_state)]

    def _on(self, sample) -> None:
        try:
            u = decode(ValveCommand, sample.payload.to_bytes()).u
        except Exception:
            return
        self.samples.append((time.monotonic(), u))

    def _on_state(self, sample) -> None:
        try:
            qd = decode(MachineState, sample.payload.to_bytes()).qd
        except Exception:
            return
        self.speeds.append((time.monotonic(), max(abs(v) for v in qd[:4])))

    def still_since(self, t0: float, max_speed: float = 0.05) -> float | None:
        """Time of the first state after ``t0`` from which on every active joint stays slower
        than ``max_speed`` (rad/s or m/s), or None if it is still moving."""
        after = [(t, v) for t, v in list(self.speeds) if t >= t0]
        still = None
        for t, v in after:
            if v >= max_speed:
                still = None
            elif still is None:
                still = t
        return still

    def first_neutral_after(self, t0: float) -> float | None:
        """Receive time of the first all-zero command after ``t0``, or None."""
        return next((t for t, u in list(self.samples) if t >= t0 and not any(u)), None)

    def reload(self, machine_id: str = "m1") -> None:
        """Ask the simulated machine for a new payload at a random collision-free pose (SimReset,
        what the operator picking up the next object stands for)."""
        self.session.put(keys.sim_reset(machine_id), encode(SimReset(machine_id=machine_id, stamp_s=time.monotonic())))

    def last_before(self, t0: float) -> list[float] | None:
        """The last valve command received before ``t0`` (None if none)."""
        before = [u for t, u in list(self.samples) if t < t0]
        return before[-1] if before else None

    def moving_since(self, t0: float) -> bool:
        """True if any non-neutral command arrived after ``t0``."""
        return any(any(u) for t, u in list(self.samples) if t >= t0)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self.session.close()


class FaultStack:
    """Server, plant and runtime of m1 as separate child processes (context manager).

    Args:
        root: the stack's directory (data dir, logs, outbox, policy).
        policy: the 2D policy ONNX (its manifest beside it).
        env: extra environment of the server (e.g. FAST_BOUNDS).
    """

    def __init__(self, root: Path, policy: Path, env: dict[str, str] | None = None, extra_listen: tuple[str, ...] = ()):
        self.root, self.policy = Path(root), Path(policy)
        self.extra_listen = list(extra_listen)
        self.data_dir = self.root / "var"
        self.port, self.viser_port, self.zport = free_port(), free_port(), free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.zport}"
        self.base_url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, "SLINGER_VISER_ENABLED": "false", **(env or {})}
        self.procs: dict[str, subprocess.Popen] = {}
        self.key_path = self.data_dir / "site" / "machines" / "m1" / "command.key"
        self.http: httpx.Client | None = None
        self.thrown: list[str] = []
        self.start_timeout_s = 120.0
        """How long the start may take (server serving HTTP, then m1 ready), s each."""

    # --- processes --------------------------------------------------------------------------
    def spawn(self, name: str, argv: list[str], env: dict | None = None) -> subprocess.Popen:
        log_dir = self.root / "logs"
        log_dir.mkdir(parents=True, exist_ok=True)
        with open(log_dir / f"{name}.log", "ab") as out:
            proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=env or self.env, cwd=self.root)
        self.procs[name] = proc
        return proc

    def start_server(self) -> subprocess.Popen:
        return self.spawn("server", slinger_command(
            "server", "--data-dir", str(self.data_dir), "--port", str(self.port), "--viser-port",
            str(self.viser_port), "--listen", self.endpoint, *[a for e in self.extra_listen for a in ("--listen", e)],
            "--migrate"))

    def start_worker(self) -> subprocess.Popen:
        """The job worker that runs the previews (server.jobs.worker)."""
        from server.config import Settings
        from server.jobs.worker import worker_argv

        return self.spawn("worker", worker_argv(Settings(data_dir=self.data_dir)))

    def link(self, connect: str | None = None, listen_host: str = "127.0.0.1") -> list[str]:
        return ["--connect", connect or self.endpoint, "--listen", f"tcp/{listen_host}:0"]

    def plant_argv(self, machine_id: str = "m1", link: list[str] | None = None) -> list[str]:
        return slinger_command("plant", "--machine-id", machine_id, "--seed", "3", *(link or self.link()))

    def runtime_argv(self, machine_id: str = "m1", link: list[str] | None = None) -> list[str]:
        machine_key(self.data_dir / "site", machine_id)  # made if missing
        key = self.data_dir / "site" / "machines" / machine_id / "command.key"
        return slinger_command("runtime", "--machine-id", machine_id, "--policy-2d", str(self.policy),
                               *(link or self.link()), "--outbox-dir", str(self.data_dir / "outbox" / machine_id),
                               "--command-key", str(key), *TEST_POLICY_CHECK)

    def start_plant(self) -> subprocess.Popen:
        return self.spawn("plant", self.plant_argv())

    def start_runtime(self) -> subprocess.Popen:
        return self.spawn("runtime", self.runtime_argv())

    def kill(self, name: str) -> None:
        """kill -9 one process and reap it."""
        proc = self.procs[name]
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)

    def log_text(self, name: str) -> str:
        return (self.root / "logs" / f"{name}.log").read_text(errors="replace")

    # --- lifecycle --------------------------------------------------------------------------
    def __enter__(self) -> "FaultStack":
        from server.site.stack import register_policies

        subprocess.run(slinger_command("user", "add", "--admin", "--password", ADMIN[1], "--data-dir", str(self.data_dir)),
                       check=True, capture_output=True, timeout=120, env=self.env, cwd=self.root)
        register_policies(f"sqlite:///{self.data_dir / 'slinger.db'}", self.data_dir, {"2d": self.policy})
        machine_key(self.data_dir / "site", "m1")
        try:
            self.start_server()
            self.start_worker()
            self.start_plant()
            self.start_runtime()
            self.connect_http(self.start_timeout_s)
            self.wait_ready(self.start_timeout_s)
        except BaseException:  # a failed start must not leave its processes behind
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc) -> None:
        if self.http is not None:
            self.http.close()
        for name in ("runtime", "plant", "worker", "server"):
            stop_proc(self.procs.get(name))
        for proc in self.procs.values():
            stop_proc(proc)

    # --- API --------------------------------------------------------------------------------
    def connect_http(self, timeout_s: float = 120.0) -> httpx.Client:
        def up():
            try:
                return httpx.get(f"{self.base_url}/api/health", timeout=2).status_code == 200
            except httpx.HTTPError:
                if self.procs["server"].poll() is not None:
                    raise AssertionError(f"server exited:\n{self.log_text('server')[-3000:]}")
                return False

        wait_for(up, timeout_s, "server serving HTTP")
        if self.http is not None:
            self.http.close()
        self.http = httpx.Client(base_url=self.base_url, timeout=15)
        login(self.http, *ADMIN)
        return self.http

    def machine(self, machine_id: str = "m1") -> dict | None:
        try:
            ms = self.http.get("/api/machines", timeout=5).json()
        except httpx.HTTPError:
            return None
        return next((m for m in ms if m["id"] == machine_id), None)

    def wait_ready(self, timeout_s: float = 120.0, machine_id: str = "m1",
                   watched: tuple[str, ...] = ("server", "plant", "runtime")) -> dict:
        """Until the machine's runtime is online, has machine state and would accept a throw."""
        def ready():
            for name in watched:
                proc = self.procs[name]
                if proc.poll() is not None:
                    raise AssertionError(f"{name} exited ({proc.returncode}):\n{self.log_text(name)[-3000:]}")
            m = self.machine(machine_id)
            return m if m and m["online"] and m["cabin_turn_rad"] is not None and m["ready"] else None

        wait_for(ready, timeout_s, f"{machine_id} ready")
        time.sleep(1.0)  # the runtime publishes its RuntimeInfo at 2 Hz: ready must hold a second later
        return wait_for(ready, timeout_s, f"{machine_id} ready")

    def try_throw(self, target=TARGET_2D, machine_id: str = "m1") -> httpx.Response:
        """Preview then throw (as the console does); the throw's response (accepted ids are kept
        in :attr:`thrown`)."""
        body = {"machine_id": machine_id, "mode": "2d", "target": list(target)}
        p = self.http.post("/api/previews", json={**body, "rollouts": 1})
        assert p.status_code == 200 and p.json()["status"] == "ok", p.text
        r = self.http.post("/api/throws", json={**body, "preview_id": p.json()["id"]})
        if r.status_code == 202:
            self.thrown.append(r.json()["id"])
        return r

    def throw(self, target=TARGET_2D, machine_id: str = "m1") -> str:
        """:meth:`try_throw` that must be accepted; returns the throw id."""
        r = self.try_throw(target, machine_id)
        assert r.status_code == 202, r.text
        return r.json()["id"]

    def row(self, throw_id: str) -> dict | None:
        try:
            r = self.http.get(f"/api/throws/{throw_id}", timeout=5)
        except httpx.HTTPError:
            return None
        return r.json() if r.status_code == 200 else None

    def wait_phase(self, throw_id: str, phases=("swinging", "released"), timeout_s: float = 30.0) -> dict:
        return wait_for(lambda: (r := self.row(throw_id)) and (r["status"] in phases or r["status"] in FINAL) and r,
                        timeout_s, f"throw {throw_id[:8]} in {phases}")

    def wait_final(self, throw_id: str, timeout_s: float) -> tuple[dict, float]:
        """(row, seconds it took) once the throw is final; fails the test past ``timeout_s``."""
        t0 = time.monotonic()
        row = wait_for(lambda: (r := self.row(throw_id)) and r["status"] in FINAL and r, timeout_s,
                       f"throw {throw_id[:8]} final")
        return row, time.monotonic() - t0


class Netns:
    """A network namespace joined to the host by a veth pair (host 10.231.N.1/24, namespace
    10.231.N.2/24), made and removed with ``ip`` (needs root / CAP_NET_ADMIN).

    Raises:
        PermissionError: the namespace cannot be made here (with ip's message).
    """

    def __init__(self, tag: int):
        self.name, self.host_if, self.ns_if = f"slg{tag}", f"slgh{tag}", f"slgn{tag}"
        n = tag % 200 + 20
        self.host_ip, self.ns_ip = f"10.231.{n}.1", f"10.231.{n}.2"
        steps = [
            ["ip", "netns", "add", self.name],
            ["ip", "link", "add", self.host_if, "type", "veth", "peer", "name", self.ns_if],
            ["ip", "link", "set", self.ns_if, "netns", self.name],
            ["ip", "addr", "add", f"{self.host_ip}/24", "dev", self.host_if],
            ["ip", "link", "set", self.host_if, "up"],
            ["ip", "netns", "exec", self.name, "ip", "addr", "add", f"{self.ns_ip}/24", "dev", self.ns_if],
            ["ip", "netns", "exec", self.name, "ip", "link", "set", self.ns_if, "up"],
            ["ip", "netns", "exec", self.name, "ip", "link", "set", "lo", "up"],
        ]
        for step in steps:
            r = subprocess.run(step, capture_output=True, text=True)
            if r.returncode != 0:
                self.remove()
                raise PermissionError(f"{' '.join(step)}: {r.stderr.strip() or r.returncode}")

    def prefix(self) -> list[str]:
        """argv prefix that runs a command inside the namespace."""
        return ["ip", "netns", "exec", self.name]

    def link_up(self, up: bool) -> None:
        """Take the host side of the veth down (a cut cable) or up again."""
        subprocess.run(["ip", "link", "set", self.host_if, "up" if up else "down"], check=True)

    def remove(self) -> None:
        subprocess.run(["ip", "link", "del", self.host_if], capture_output=True)
        subprocess.run(["ip", "netns", "del", self.name], capture_output=True)
