"""/api/health latency while a flood of wrong-password log-ins hits the server.

Starts ``slinger server`` (SQLite in a temporary directory, no 3D view, argon2 with the
library's default cost) as a subprocess, adds an admin, then for ``--seconds`` runs
``--clients`` concurrent clients (asyncio, in a process of their own) that post wrong
passwords as fast as the server answers, while one thread
probes GET /api/health every 100 ms. Prints the health latency (p50/p95/max, ms) without and with
the flood, and what the log-ins got back (401 checked, 429 refused).

Two kinds of flood:
  same      one address, one user name (the lockout stops it after a few attempts);
  spread    a new user name and ``X-Forwarded-For`` address per attempt, the server started with
            loopback as a trusted proxy (``SLINGER_TRUSTED_PROXIES``; no proxy is trusted by
            default), so only the bounded password-check pool stands in the way.

Run from the repository root, e.g.::

    PYTHONPATH=$PWD python tests/benchmarks/bench_login_flood.py --flood spread

To measure an older tree (the "before" figure) point PYTHONPATH at its checkout instead.

Measured 2026-11-21 on the shared 2-core development machine (load average 40-50 from other
work, so absolute numbers are pessimistic), 32 clients, spread flood, 10 s:

    before (2262ac8: argon2 on the 40 request threads): health p50 134 ms, p95 15.1 s, max 30 s
        (a probe timed out); log-ins 401 x21 and 500 x11 (3/s)
    after (lockout + 1-thread check pool, max 8 pending): health p50 164 ms, p95 340 ms, max
        452 ms; log-ins 401 x13, 429 x93 (10/s), no 500
    after, same-user flood: health p50 214 ms, p95 677 ms; 401 x10 then 429 x58
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import logging
import multiprocessing
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from tests.conftest import free_port

log = logging.getLogger("bench_login_flood")
PASSWORD = "bench-admin-password"


def start_server(data_dir: Path, port: int) -> subprocess.Popen:
    env = dict(os.environ, SLINGER_DATA_DIR=str(data_dir), SLINGER_VISER_ENABLED="false",
               SLINGER_TRUSTED_PROXIES='["127.0.0.1"]')  # the spread flood plays a proxy's many clients
    cli = [sys.executable, "-m", "server.cli"]
    subprocess.run([*cli, "user", "add", "admin", "--admin", "--password", PASSWORD], env=env, check=True,
                   capture_output=True, timeout=120)
    proc = subprocess.Popen([*cli, "server", "--port", str(port), "--migrate"], env=env,
                            stdout=open(data_dir / "server.log", "wb"), stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=1).status_code == 200:
                return proc
        except httpx.HTTPError:
            time.sleep(0.2)
    proc.kill()
    raise SystemExit(f"server did not come up; see {data_dir / 'server.log'}")


def probe_health(base: str, seconds: float) -> list[float]:
    """Health latencies in ms, one probe every 100 ms (a timed-out probe counts as 30 s)."""
    out = []
    with httpx.Client(base_url=base, timeout=30) as c:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            t0 = time.perf_counter()
            try:
                c.get("/api/health")
                out.append((time.perf_counter() - t0) * 1e3)
            except httpx.HTTPError:
                out.append(30_000.0)
            time.sleep(max(0.0, 0.1 - (time.perf_counter() - t0)))
    return out


def flood_process(base: str, clients: int, seconds: float, spread: bool, out) -> None:
    """In a process of its own (it must not steal the prober's CPU time slices or GIL):
    ``clients`` concurrent asyncio clients posting wrong passwords for ``seconds``; puts the
    answer counts on the queue ``out``."""
    out.put(asyncio.run(_flood(base, clients, seconds, spread)))


async def _flood(base: str, clients: int, seconds: float, spread: bool) -> dict:
    counts: collections.Counter = collections.Counter()
    end = time.monotonic() + seconds

    async def client(c: httpx.AsyncClient) -> None:
        while time.monotonic() < end:
            user, headers = "admin", {}
            if spread:
                user = f"u{random.getrandbits(32):x}"
                headers["X-Forwarded-For"] = f"10.{random.randrange(256)}.{random.randrange(256)}.{random.randrange(1, 255)}"
            try:
                r = await c.post("/api/auth/login", json={"username": user, "password": "wrong-password"},
                                 headers=headers)
                counts[r.status_code] += 1
            except httpx.HTTPError:
                counts["error"] += 1

    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=base, timeout=60, limits=limits) as c:
        await asyncio.gather(*(client(c) for _ in range(clients)))
    return dict(counts)


def summary(ms: list[float]) -> str:
    a = np.asarray(ms)
    return f"n={len(a)} p50={np.percentile(a, 50):.1f} ms p95={np.percentile(a, 95):.1f} ms max={a.max():.1f} ms"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--flood", choices=("same", "spread"), default="spread")
    ap.add_argument("--clients", type=int, default=32, help="concurrent log-in clients")
    ap.add_argument("--seconds", type=float, default=10.0, help="flood duration")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with tempfile.TemporaryDirectory(prefix="bench-login-") as tmp:
        port = free_port()
        base = f"http://127.0.0.1:{port}"
        server = start_server(Path(tmp), port)
        try:
            quiet = probe_health(base, 2.0)
            queue = multiprocessing.Queue()
            flooder = multiprocessing.Process(target=flood_process, args=(
                base, args.clients, args.seconds + 1.0, args.flood == "spread", queue))
            flooder.start()
            time.sleep(1.0)  # let the flood build up
            loaded = probe_health(base, args.seconds)
            counts = queue.get(timeout=120)
            flooder.join(timeout=30)
        finally:
            server.terminate()
            server.wait(timeout=30)
    log.info("code under test: %s", Path(sys.modules["tests.conftest"].__file__).parent.parent)
    log.info("health, no flood:             %s", summary(quiet))
    log.info("health, %2d-client %-6s flood: %s", args.clients, args.flood, summary(loaded))
    log.info("log-in answers during the flood: %s (%.0f /s)", counts,
             sum(counts.values()) / (args.seconds + 1.0))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
