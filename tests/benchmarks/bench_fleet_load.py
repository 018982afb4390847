"""Fleet load on one host: N simulated machines online (default 20) for a while (default 10 min)
through the fleet topology of tests/fleet_site.py (Zenoh router, server and worker on
PostgreSQL, each machine's plant and runtime as Zenoh clients), clients throwing on up to 4
machines at a time (preview in the worker, then throw) and a reader polling history and
accuracy meanwhile.

Run (root not needed; PostgreSQL at 127.0.0.1:5432):
``nice -n 10 python tests/benchmarks/bench_fleet_load.py [--machines 20] [--minutes 10]``.
Prints: machines online (min over the run), throws by final status, lost and stuck throws,
throw and history latencies, the host's load; no assertions.
"""

from __future__ import annotations

import argparse
import logging
import os
import random
import statistics
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
POLICY = REPO / "policies" / "throw2d.onnx"
FINAL = ("landed", "failed", "aborted", "lost")
COOLDOWN_S = 3.0
"""A machine rests this long after its throw before a client picks it again (the runtime reloads
the simulated machine after each throw; a preview taken meanwhile would be stale)."""
log = logging.getLogger("bench_fleet_load")


def p95(xs: list[float]) -> float:
    xs = sorted(xs)
    return xs[int(0.95 * (len(xs) - 1))] if xs else float("nan")


def run(site, minutes: float, clients: int) -> None:
    import httpx

    from tests.conftest import ADMIN, login

    machines, lock, stop = list(site.machines), threading.Lock(), threading.Event()
    idle = set(machines)
    thrown: list[tuple[str, str]] = []
    throw_s, read_ms, online_n, errors = [], [], [], Counter()

    def client(k: int) -> None:
        http = httpx.Client(base_url=site.base_url, timeout=60)
        login(http, *ADMIN)
        rng = random.Random(k)
        while not stop.is_set():
            with lock:
                mid = rng.choice(sorted(idle)) if idle else None
                if mid:
                    idle.discard(mid)
            if mid is None:
                time.sleep(0.5)
                continue
            try:
                target = [round(rng.uniform(7.5, 9.5), 2), -0.292, 0.0]
                t0 = time.monotonic()
                p = http.post("/api/previews", json={"machine_id": mid, "mode": "2d", "target": target, "rollouts": 50})
                if p.status_code != 200 or p.json()["status"] != "ok":
                    errors[f"preview {p.status_code}: {p.text[:80]}"] += 1
                    continue
                r = http.post("/api/throws", json={"machine_id": mid, "mode": "2d", "target": target,
                                                   "preview_id": p.json()["id"]})
                if r.status_code != 202:
                    errors[f"throw {r.status_code}: {r.text[:80]}"] += 1
                    continue
                tid = r.json()["id"]
                with lock:
                    thrown.append((mid, tid))
                while not stop.is_set() and time.monotonic() - t0 < 120:
                    if http.get(f"/api/throws/{tid}").json()["status"] in FINAL:
                        throw_s.append(time.monotonic() - t0)
                        break
                    time.sleep(0.5)
            except httpx.HTTPError as e:
                errors[f"http {type(e).__name__}"] += 1
            finally:
                time.sleep(COOLDOWN_S)
                with lock:
                    idle.add(mid)
        http.close()

    def reader() -> None:
        http = httpx.Client(base_url=site.base_url, timeout=60)
        login(http, *ADMIN)
        n = 0
        while not stop.wait(1.0):
            for path in ("/api/throws", "/api/throws/accuracy"):
                t0 = time.perf_counter()
                http.get(path, params={"limit": 50} if path == "/api/throws" else {})
                read_ms.append((time.perf_counter() - t0) * 1e3)
            n += 1
            if n % 10 == 0:
                online_n.append(len(site.online()))
        http.close()

    threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)] + [threading.Thread(target=reader)]
    t_start, load0 = time.monotonic(), os.getloadavg()
    for t in threads:
        t.start()
    time.sleep(minutes * 60)
    stop.set()
    for t in threads:
        t.join()
    elapsed = time.monotonic() - t_start
    time.sleep(30)  # results still on their way
    listed = site.http.get("/api/throws", params={"limit": 500}).json()
    rows = {r["id"]: r["status"] for r in listed}
    reasons = Counter((r["failure_reason"] or "")[:60] for r in listed if r["status"] != "landed")
    statuses = Counter(rows.get(tid, "missing") for _, tid in thrown)
    stuck = sum(n for s, n in statuses.items() if s not in FINAL)
    print(f"{len(site.machines)} simulated machines, {elapsed / 60:.1f} min, {clients} clients throwing, 1 reader; "
          f"load average {load0[0]:.1f} at start, {os.getloadavg()[0]:.1f} at end (2 cores, shared)")
    print(f"machines online (sampled every ~10 s): min {min(online_n, default=0)}, mean "
          f"{statistics.mean(online_n) if online_n else 0:.1f} of {len(site.machines)}")
    print(f"throws: {len(thrown)} sent; final statuses {dict(statuses)}; lost {statuses.get('lost', 0)}, stuck {stuck}")
    if reasons:
        print("reasons of the throws that did not land:", dict(reasons))
    print(f"throw round trip (preview + throw + final status): median {statistics.median(throw_s) if throw_s else float('nan'):.1f} s, "
          f"p95 {p95(throw_s):.1f} s")
    print(f"history + accuracy reads meanwhile: {len(read_ms)}, p50 {statistics.median(read_ms) if read_ms else float('nan'):.0f} ms, "
          f"p95 {p95(read_ms):.0f} ms")
    if errors:
        print("refused requests:", dict(errors))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=20)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--clients", type=int, default=4)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    from tests.conftest import wait_for
    from tests.fleet_site import Site

    with tempfile.TemporaryDirectory(prefix="slinger-load-") as tmp:
        t0 = time.monotonic()
        # a loaded shared host: give previews 60 s before the API gives up (the bar is measured
        # by bench_preview, not here)
        with Site(Path(tmp), args.machines, POLICY, server_env={"SLINGER_PREVIEW_TIMEOUT_S": "60"}) as site:
            wait_for(lambda: len(site.online()) == args.machines, 900, f"{args.machines} machines online")
            print(f"{args.machines} machines online after {time.monotonic() - t0:.0f} s")
            run(site, args.minutes, args.clients)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
