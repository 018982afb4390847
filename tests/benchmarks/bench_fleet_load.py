"""Fleet load on one host: N simulated machines online (default 20) for a while (default 10 min)
through the fleet topology of tests/fleet_site.py (Zenoh router, server and worker on
PostgreSQL, each machine's plant and runtime as Zenoh clients; every Zenoh link mutual TLS;
``--netns``: each group on its own network namespace, root only), clients throwing on up to 4
machines at a time (preview in the worker, then throw) and a reader polling history and
accuracy meanwhile.

A client that finds a machine not ready because of its pose (it stopped outside the envelope
after a failed or E-STOPped throw) does what an operator does: ``POST
/api/machines/{id}/return-to-ready``, then waits until the machine reports ready (counted).

Accounting is strict: every throw the server accepted (202) is followed until a final status
(landed, failed, aborted, lost); when the run ends, throws still running get a drain period
(``--drain-s``), and any still not final after it count as *stuck*.

Run (PostgreSQL at 127.0.0.1:5432; at normal priority so that it gets its share of a shared host):
``python tests/benchmarks/bench_fleet_load.py [--machines 20] [--minutes 10] [--json out.json]``.
Prints: machines online, throws by final status with the reasons of those that did not land,
lost and stuck throws, refusals and returns to the ready pose, round-trip and history/accuracy
read latencies (p50/p95), CPU use of plants, runtimes, server, worker and router, the host's load
average and the busiest other processes; no assertions.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import random
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from tests.benchmarks.fleet_load_stats import (  # noqa: E402
    FINAL,
    Tally,
    host_cpu_s,
    is_pose_refusal,
    percentile,
    proc_cpu_s,
    tree_cpu_s,
)

POLICY = REPO / "policies" / "throw2d.onnx"
COOLDOWN_S = 3.0
"""A machine rests this long after its throw before a client picks it again (a preview taken
while it settles would be stale)."""
RETURN_WAIT_S = 120.0
"""How long a client waits for a machine to report ready after its return to the ready pose."""
RETURN_POLL_S = 2.0
"""How often it asks meanwhile (GET /api/machines)."""
log = logging.getLogger("bench_fleet_load")


def group_of(name: str) -> str:
    """Process group of a site process name ("plant-m3" -> "plant")."""
    return name.split("-", 1)[0]


def cpu_by_group(site) -> dict[str, float]:
    """CPU seconds so far of the site's processes, summed per group (plant, runtime, server, ...)."""
    out: dict[str, float] = {}
    for name, p in site.procs.items():
        out[group_of(name)] = out.get(group_of(name), 0.0) + tree_cpu_s(p.pid)
    out["bench"] = proc_cpu_s(os.getpid())  # this process: the clients and the reader
    return out


def other_processes(exclude: set[int], n: int = 6) -> list[str]:
    """The ``n`` busiest processes that are not this run's ("pid nice %cpu elapsed command")."""
    ps = subprocess.run(["ps", "-eo", "pid,ni,pcpu,etime,args", "--sort=-pcpu", "--no-headers"],
                        capture_output=True, text=True).stdout.splitlines()
    rows = [r.strip() for r in ps if r.split() and int(r.split()[0]) not in exclude and r.split()[4] != "ps"]
    return [" ".join(r.split()[:4] + [" ".join(r.split()[4:])[:90]]) for r in rows[:n]]


class Run:
    """One load run on a started ``tests.fleet_site.Site``."""

    def __init__(self, site, clients: int, drain_s: float):
        import httpx

        self.httpx, self.site, self.clients, self.drain_s = httpx, site, clients, drain_s
        self.tally, self.lock, self.stop = Tally(), threading.Lock(), threading.Event()
        self.idle = set(site.machines)
        self.online_n: list[int] = []
        self.load: list[float] = []
        self.others: list[list[str]] = []
        self.deadline = float("inf")  # set when the throwing stops: the end of the drain

    def _http(self):
        from tests.conftest import ADMIN, login

        http = self.httpx.Client(base_url=self.site.base_url, timeout=90)
        login(http, *ADMIN)
        return http

    # --- clients -------------------------------------------------------------------------------
    def client(self, k: int) -> None:
        http, rng = self._http(), random.Random(k)
        while not self.stop.is_set():
            with self.lock:
                mid = rng.choice(sorted(self.idle)) if self.idle else None
                if mid:
                    self.idle.discard(mid)
            if mid is None:
                time.sleep(0.5)
                continue
            try:
                self.one_throw(http, mid, rng)
            except self.httpx.HTTPError as e:
                self.tally.refused("http", type(e).__name__)
            finally:
                time.sleep(COOLDOWN_S)
                with self.lock:
                    self.idle.add(mid)
        http.close()

    def one_throw(self, http, mid: str, rng: random.Random) -> None:
        target = [round(rng.uniform(7.5, 9.5), 2), -0.292, 0.0]
        t0 = time.monotonic()
        p = http.post("/api/previews", json={"machine_id": mid, "mode": "2d", "target": target, "rollouts": 50})
        if p.status_code != 200 or p.json().get("status") != "ok":
            self._refused(http, mid, "preview", p)
            return
        r = http.post("/api/throws", json={"machine_id": mid, "mode": "2d", "target": target,
                                           "preview_id": p.json()["id"]})
        if r.status_code != 202:
            self._refused(http, mid, "throw", r)
            return
        tid = r.json()["id"]
        self.tally.accepted(tid, mid)
        while time.monotonic() < self.deadline:  # followed past the run's end, until the drain ends
            row = http.get(f"/api/throws/{tid}").json()
            if row["status"] in FINAL:
                self.tally.ended(tid, row["status"], row.get("failure_reason"))
                with self.tally.lock:
                    self.tally.round_trip_s.append(time.monotonic() - t0)
                return
            time.sleep(0.5)

    def _refused(self, http, mid: str, what: str, resp) -> None:
        text = f"{resp.status_code} {resp.text[:200]}"
        self.tally.refused(what, text)
        if is_pose_refusal(text):
            self.return_to_ready(http, mid)

    def return_to_ready(self, http, mid: str) -> None:
        """The operator's recovery: return-to-ready, then wait until the machine reports ready."""
        t0 = time.monotonic()
        r = http.post(f"/api/machines/{mid}/return-to-ready")
        if r.status_code != 200:
            self.tally.returns[f"refused {r.status_code}: {r.text[:80]}"] += 1
            return
        while time.monotonic() - t0 < RETURN_WAIT_S:
            time.sleep(RETURN_POLL_S)
            m = next((m for m in http.get("/api/machines").json() if m["id"] == mid), None)
            if m is not None and m.get("ready"):
                with self.tally.lock:
                    self.tally.returns["accepted, ready again"] += 1
                    self.tally.return_s.append(time.monotonic() - t0)
                return
        self.tally.returns[f"accepted, not ready after {RETURN_WAIT_S:.0f} s"] += 1

    # --- reader and samplers -------------------------------------------------------------------
    def reader(self) -> None:
        http, n = self._http(), 0
        while not self.stop.wait(1.0):
            for what, path, params in (("history", "/api/throws", {"limit": 50}), ("accuracy", "/api/throws/accuracy", {})):
                t0 = time.perf_counter()
                try:
                    ok = http.get(path, params=params).status_code == 200
                except self.httpx.HTTPError as e:
                    ok = False
                    self.tally.read_errors[type(e).__name__] += 1
                if ok:
                    with self.tally.lock:
                        self.tally.read_ms[what].append((time.perf_counter() - t0) * 1e3)
            n += 1
            if n % 10 == 0:
                self.online_n.append(len(self.site.online()))
        http.close()

    def sampler(self, minutes: float) -> None:
        ours = {os.getpid(), *(p.pid for p in self.site.procs.values())}
        k = 0
        while not self.stop.wait(10.0):
            self.load.append(os.getloadavg()[0])
            k += 1
            if k in (3, int(minutes * 3), int(minutes * 6) - 1):  # ~30 s in, mid-run, near the end
                self.others.append(other_processes(ours))

    # --- the run -------------------------------------------------------------------------------
    def run(self, minutes: float) -> dict:
        threads = [threading.Thread(target=self.client, args=(k,)) for k in range(self.clients)]
        side = [threading.Thread(target=self.reader), threading.Thread(target=self.sampler, args=(minutes,))]
        cpu0, host0, t0 = cpu_by_group(self.site), host_cpu_s(), time.monotonic()
        for t in threads + side:
            t.start()
        last = t0
        while (now := time.monotonic()) - t0 < minutes * 60:
            time.sleep(min(5.0, t0 + minutes * 60 - now))
            if time.monotonic() - last >= 60:  # progress
                last = time.monotonic()
                o = self.tally.outcome()
                print(f"  {(last - t0) / 60:.0f} min: {o['requested']} throws accepted, {o['by_status']}, "
                      f"load {os.getloadavg()[0]:.1f}", flush=True)
        self.deadline = time.monotonic() + self.drain_s
        self.stop.set()
        for t in side:
            t.join()
        elapsed = time.monotonic() - t0
        cpu1, host1 = cpu_by_group(self.site), host_cpu_s()
        for t in threads:
            t.join()
        self._final_check()
        return self.report(minutes, elapsed, cpu0, cpu1, host0, host1)

    def _final_check(self) -> None:
        """Ask once more for every requested throw not yet final (the clients gave up at the deadline)."""
        for tid in [t for t in self.tally.requested if t not in self.tally.final]:
            row = self.site.http.get(f"/api/throws/{tid}").json()
            if row.get("status") in FINAL:
                self.tally.ended(tid, row["status"], row.get("failure_reason"))

    def report(self, minutes, elapsed, cpu0, cpu1, host0, host1) -> dict:
        n = len(self.site.machines)
        counts = {g: max(1, sum(1 for name in self.site.procs if group_of(name) == g)) for g in cpu1}
        cpu = {g: {"processes": counts[g], "cores_total": (cpu1[g] - cpu0.get(g, 0.0)) / elapsed,
                   "pct_of_core_each": 100 * (cpu1[g] - cpu0.get(g, 0.0)) / elapsed / counts[g]} for g in cpu1}
        host_busy = (host1[0] - host0[0]) / elapsed
        site_cores = sum(c["cores_total"] for c in cpu.values())
        rt = self.tally.round_trip_s
        returns, secs = dict(self.tally.returns), self.tally.return_s
        out = {
            "machines": n, "minutes": elapsed / 60, "clients": self.clients, "outcome": self.tally.outcome(),
            "online_min": min(self.online_n, default=0), "online_mean": statistics.mean(self.online_n) if self.online_n else 0,
            "refusals": dict(self.tally.refusals.most_common()), "returns_to_ready": returns,
            "return_s_median": statistics.median(secs) if secs else None,
            "round_trip_s": {"p50": percentile(rt, 0.5), "p95": percentile(rt, 0.95)},
            "reads_ms": {w: {"n": len(v), "p50": percentile(v, 0.5), "p95": percentile(v, 0.95)}
                         for w, v in self.tally.read_ms.items()},
            "read_errors": dict(self.tally.read_errors),
            "cpu": cpu, "host_busy_cores": host_busy, "others_cores": max(0.0, host_busy - site_cores),
            "load_average": {"min": min(self.load, default=0), "mean": statistics.mean(self.load) if self.load else 0,
                             "max": max(self.load, default=0)},
            "other_processes": self.others,
        }
        self.print(out)
        return out

    @staticmethod
    def print(o: dict) -> None:
        oc = o["outcome"]
        la = o["load_average"]
        print(f"{o['machines']} simulated machines, {o['minutes']:.1f} min, {o['clients']} clients throwing, 1 reader; "
              f"load average (1 min, every 10 s) min {la['min']:.1f} mean {la['mean']:.1f} max {la['max']:.1f} "
              f"on {os.cpu_count()} cores, shared")
        print(f"machines online (every ~10 s): min {o['online_min']}, mean {o['online_mean']:.1f} of {o['machines']}")
        print(f"throws accepted: {oc['requested']}; final: {oc['by_status']}; lost {oc['lost']}, stuck {oc['stuck']}")
        for r, k in oc["reasons"].items():
            print(f"  {k:4d}  {r}")
        if o["refusals"]:
            print("refused before a throw started:", o["refusals"])
        print(f"returns to the ready pose: {o['returns_to_ready'] or 'none needed'}"
              + (f" (median {o['return_s_median']:.0f} s to ready)" if o["return_s_median"] else ""))
        rt = o["round_trip_s"]
        print(f"throw round trip (preview + throw + final status): p50 {rt['p50']:.1f} s, p95 {rt['p95']:.1f} s")
        for w, r in o["reads_ms"].items():
            print(f"{w} reads meanwhile: {r['n']}, p50 {r['p50']:.0f} ms, p95 {r['p95']:.0f} ms")
        if o["read_errors"]:
            print("read errors:", o["read_errors"])
        print("CPU (cores, averaged over the run):", ", ".join(
            f"{g} {c['cores_total']:.2f} ({c['processes']} x {c['pct_of_core_each']:.1f} %)" for g, c in o["cpu"].items()),
            f"; host busy {o['host_busy_cores']:.2f} cores, of which others' jobs {o['others_cores']:.2f}")
        for i, snap in enumerate(o["other_processes"]):
            print(f"busiest other processes (sample {i + 1}; %cpu averaged since each started): pid nice %cpu elapsed command")
            for line in snap:
                print("   ", line)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--machines", type=int, default=20)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--drain-s", type=float, default=180.0, help="how long throws running at the end may take to end")
    ap.add_argument("--netns", action="store_true", help="each group on its own network namespace (root)")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args(argv)
    if args.machines < 1 or args.clients < 1 or args.minutes <= 0:
        ap.error("--machines, --clients and --minutes must be positive")
    logging.basicConfig(level=logging.WARNING)
    from tests.conftest import wait_for
    from tests.fleet_site import Site

    with tempfile.TemporaryDirectory(prefix="slinger-load-") as tmp:
        t0 = time.monotonic()
        # a loaded shared host: give previews 60 s before the API gives up (the bar is measured
        # by bench_preview, not here)
        with Site(Path(tmp), args.machines, POLICY, netns=args.netns,
                  server_env={"SLINGER_PREVIEW_TIMEOUT_S": "60"}) as site:
            wait_for(lambda: len(site.online()) == args.machines, 900, f"{args.machines} machines online")
            print(f"{args.machines} machines online after {time.monotonic() - t0:.0f} s "
                  f"(Zenoh over mutual TLS{', one network namespace per host' if args.netns else ', loopback'})", flush=True)
            out = Run(site, args.clients, args.drain_s).run(args.minutes)
            if args.json:
                args.json.write_text(json.dumps(out, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
