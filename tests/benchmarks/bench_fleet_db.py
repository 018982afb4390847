"""Fleet database figures on PostgreSQL (127.0.0.1:5432, a throwaway database):

1. Throw results ingested per second through the server's own path: ThrowResult messages (with
   a 2 s, 100 Hz MCAP recording each) sent as Zenoh queries to ``keys.THROW_RESULT`` by
   concurrent senders, verified and stored by the fleet link (MCAP file staged and fsynced, then
   row + rename + accuracy aggregates in one commit per batch) and acknowledged; the throws were
   issued first (the server refuses results it never issued). Also the server process's CPU time
   per result and the load average (the host may be shared).
2. History and accuracy latency over 100 000 stored throws (20 machines, two policy versions,
   2D/3D, 7-10 m, bulk-inserted, then the accuracy aggregates rebuilt): GET /api/throws (first
   page, filtered page), GET /api/throws/accuracy (all, one machine and mode, one machine since a
   time of day, a distance filter), through the FastAPI app in-process (ASGI, no socket), p50 /
   p95 in ms.

Run: ``python tests/benchmarks/bench_fleet_db.py [--results 3000] [--throws 100000]``.
Prints the figures and the bars (>= 500 results/s, p95 <= 100 ms); no assertions.
"""

from __future__ import annotations

import argparse
import base64
import logging
import os
import statistics
import sys
import tempfile
import threading
import time
import uuid
from datetime import timedelta
from pathlib import Path

import numpy as np
from sqlalchemy import create_engine, insert, text

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
PG_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
log = logging.getLogger("bench_fleet_db")


def recording_b64(ticks: int = 200) -> str:
    """A 2 s, 100 Hz telemetry recording as base64 MCAP (the size a real result carries)."""
    from runtime.telemetry import TelemetryRecorder, write_mcap

    rec = TelemetryRecorder()
    for i in range(ticks):
        q = [0.0, -0.5 + 0.001 * i, 1.5, 0.2, 0.1 * np.sin(i / 10), 0.0]
        rec.record(0.01 * i, q, [0.0] * 6, [0.0] * 4, [0.0] * 4, i > 100, i > 110, "swinging",
                   payload_pos_m=[5.0, -0.1, 3.0], payload_vel_mps=[3.0, 0.0, -3.0])
    return base64.b64encode(write_mcap(rec, {"throw_id": "bench"})).decode()


def _sender(endpoint: str, ids: list[str], threads: int, go, out) -> None:
    """One sending process (a runtime host): ``threads`` threads deliver results and await acks."""
    from runtime.protocol import keys
    from runtime.protocol.messages import ResultAck, ThrowResult, decode, encode
    from runtime.zenoh_session import open_session

    mcap = recording_b64()
    payloads = [encode(ThrowResult(machine_id="bench", stamp_s=1.0, throw_id=i, mode="2d", status="landed",
                                   target_m=[8.0, -0.3, 0.0], impact_m=[8.1, -0.2, 0.0], policy_version="bench",
                                   policy_sha256="b" * 64, duration_s=2.0, telemetry_mcap_b64=mcap)) for i in ids]
    acked = []
    with open_session(mode="peer", connect=(endpoint,)) as s:
        time.sleep(1.0)
        go.wait()

        def send(chunk):
            for p in chunk:
                for reply in s.get(keys.THROW_RESULT, payload=p, timeout=60.0):
                    if reply.ok is not None and decode(ResultAck, reply.ok.payload.to_bytes()).stored:
                        acked.append(1)

        ts = [threading.Thread(target=send, args=(payloads[k::threads],)) for k in range(threads)]
        for t in ts:
            t.start()
        for t in ts:
            t.join()
    out.put((len(acked), len(payloads[0])))


class IngestProfile:
    """Instrumentation of the server's result path during ingestion (``--profile``): batch sizes
    and wall time of ``ResultStore.store_results`` on the fleet's DB thread, with a cProfile of
    those calls, the wall time spent in the Zenoh result callback and in staging the telemetry."""

    def __init__(self, app):
        import cProfile

        self.prof, self.batches, self.store_s, self.callback_s, self.callbacks = cProfile.Profile(), [], 0.0, 0.0, 0
        store, fleet = app.state.store, app.state.fleet
        real_store, real_cb = store.store_results, fleet._on_result

        def store_results(*args):
            t0 = time.perf_counter()
            try:
                return self.prof.runcall(real_store, *args)
            finally:
                self.store_s += time.perf_counter() - t0
                self.batches.append(len(args[0]))

        def on_result(query):
            t0 = time.perf_counter()
            try:
                real_cb(query)
            finally:
                self.callback_s += time.perf_counter() - t0
                self.callbacks += 1

        real_stage = store.stage_telemetry
        self.stage_s, self.staged = 0.0, 0

        def stage_telemetry(result):
            t0 = time.perf_counter()
            try:
                return real_stage(result)
            finally:
                self.stage_s += time.perf_counter() - t0
                self.staged += 1

        store.store_results, store.stage_telemetry = store_results, stage_telemetry
        fleet._on_result = on_result  # the queryable was declared with a bound method: re-declare below
        self._redeclare(fleet)

    @staticmethod
    def _redeclare(fleet) -> None:
        from runtime.protocol import keys

        for i, d in enumerate(fleet._decls):
            if str(d.key_expr) == keys.THROW_RESULT:
                d.undeclare()
                fleet._decls[i] = fleet.session.declare_queryable(keys.THROW_RESULT, fleet._on_result, complete=True)

    def report(self) -> None:
        import io
        import pstats

        b = self.batches
        print(f"  profile: {len(b)} store batches, mean {statistics.mean(b):.1f} results (max {max(b)}), "
              f"{self.store_s:.2f} s storing = {1e3 * self.store_s / max(sum(b), 1):.2f} ms/result on the DB thread; "
              f"{self.callbacks} result callbacks, {1e3 * self.callback_s / max(self.callbacks, 1):.2f} ms each; "
              f"telemetry staged (written + fsynced) in {1e3 * self.stage_s / max(self.staged, 1):.1f} ms each")
        out = io.StringIO()
        pstats.Stats(self.prof, stream=out).sort_stats("cumulative").print_stats(25)
        print("\n".join("    " + line for line in out.getvalue().splitlines()[:60]))


def ingest(app, endpoint: str, n: int, processes: int, threads: int, profile: bool = False) -> float:
    """Issue ``n`` throws, deliver their results from ``processes`` sender processes with
    ``threads`` concurrent deliveries each (like that many runtimes' outboxes); returns results/s.
    Also prints the server process's CPU time per result (all its threads, Zenoh's included)."""
    import multiprocessing as mp
    import resource

    from server.db.models import Machine, Throw

    ids = [str(uuid.uuid4()) for _ in range(n)]
    with app.state.sessions.begin() as db:
        db.merge(Machine(id="bench", simulated=True))
        db.execute(insert(Throw), [dict(id=i, machine_id="bench", mode="2d", target_x_m=8.0, target_y_m=-0.3,
                                        target_z_m=0.0, status="released") for i in ids])
    ctx = mp.get_context("spawn")
    go, out = ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_sender, args=(endpoint, ids[k::processes], threads, go, out)) for k in range(processes)]
    for p in procs:
        p.start()
    time.sleep(8.0)  # the senders import, build their messages and connect
    prof = IngestProfile(app) if profile else None
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    go.set()
    got = [out.get() for _ in procs]
    dt = time.perf_counter() - t0
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu_s = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    for p in procs:
        p.join()
    with app.state.sessions() as db:
        stored = db.scalar(text("SELECT count(*) FROM throws WHERE machine_id = 'bench' AND status = 'landed'"))
    print(f"ingestion: {n} results ({got[0][1] / 1024:.0f} kB each, 2 s of 100 Hz telemetry) from {processes} processes x "
          f"{threads} concurrent deliveries in {dt:.2f} s = {n / dt:.0f} results/s; acknowledged "
          f"{sum(a for a, _ in got)}, stored {stored}  (bar >= 500/s)")
    print(f"  server process CPU {cpu_s:.2f} s (user {cpu1.ru_utime - cpu0.ru_utime:.2f}, system "
          f"{cpu1.ru_stime - cpu0.ru_stime:.2f}) = {1e3 * cpu_s / n:.2f} ms per result; load average "
          f"{load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end ({os.cpu_count()} CPUs)")
    if prof is not None:
        prof.report()
    return n / dt


def fill(app, total: int) -> None:
    """Bulk-insert synthetic landed/failed throws up to ``total`` rows."""
    from server.db.models import Machine, Throw
    from server.db.types import utcnow

    rng = np.random.default_rng(0)
    sessions = app.state.sessions
    with sessions() as db:
        have = db.scalar(text("SELECT count(*) FROM throws"))
    t0 = utcnow() - timedelta(days=30)
    with sessions.begin() as db:
        for m in range(1, 21):
            db.merge(Machine(id=f"m{m}", simulated=True))
    rows, batch = [], 10_000
    for k in range(total - have):
        d = rng.uniform(7.0, 10.0)
        landed = rng.random() > 0.05
        down, cross = (float(rng.normal(0.0, 0.05)), float(rng.normal(0.0, 0.03))) if landed else (None, None)
        sha = ("a" if k % 3 else "c") * 64
        rows.append(dict(id=str(uuid.uuid4()), machine_id=f"m{k % 20 + 1}", mode="2d" if k % 4 else "3d",
                         target_x_m=d, target_y_m=-0.29, target_z_m=0.0, status="landed" if landed else "failed",
                         downrange_error_m=down, crossrange_error_m=cross, policy_version=f"p-{sha[0]}",
                         policy_sha256=sha, requested_at=t0 + timedelta(seconds=20 * k), duration_s=1.7))
        if len(rows) == batch:
            with sessions.begin() as db:
                db.execute(insert(Throw), rows)
            rows = []
    if rows:
        with sessions.begin() as db:
            db.execute(insert(Throw), rows)
    from server.db.aggregates import rebuild

    t0 = time.perf_counter()
    with sessions.begin() as db:  # the bulk insert bypassed the ORM flush that keeps the aggregates
        summed = rebuild(db)
    print(f"accuracy aggregates rebuilt from {summed} landed throws in {time.perf_counter() - t0:.1f} s")
    with sessions.begin() as db:
        db.execute(text("ANALYZE throws"))
        db.execute(text("ANALYZE throw_accuracy"))


def _cpu_s() -> float:
    """CPU time of this process (the app: all its threads; not PostgreSQL's), s."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def latency(client, repeats: int) -> None:
    """p50 / p95 of history and accuracy requests. Accuracy without a distance filter is served
    by the incremental aggregates (a time inside a day adds a scan of that partial day); the
    distance filter falls back to the row scan (server.analysis.accuracy). Also the app process's CPU time
    per request (p50; the database server's CPU is not included): on a shared host the wall time
    includes waiting for a CPU."""
    from server.db.types import utcnow

    since = (utcnow() - timedelta(days=10, hours=5, minutes=17)).isoformat()
    cases = {
        "history first page (50)": ("/api/throws", {"limit": 50}),
        "history filtered page (machine, 2d, landed)": ("/api/throws", {"machine_id": "m7", "mode": "2d", "status": "landed", "limit": 50, "offset": 100}),
        "accuracy, all throws": ("/api/throws/accuracy", {}),
        "accuracy, one machine and mode": ("/api/throws/accuracy", {"machine_id": "m7", "mode": "2d"}),
        "accuracy, one machine, since a time of day": ("/api/throws/accuracy", {"machine_id": "m7", "since": since}),
        "accuracy, distance filter (row scan)": ("/api/throws/accuracy", {"min_distance_m": 8.0}),
    }
    total = client.get("/api/throws", params={"limit": 1}).headers["X-Total-Count"]
    print(f"latency over {total} stored throws, {repeats} requests each (bar p95 <= 100 ms):")
    for name, (path, params) in cases.items():
        client.get(path, params=params)  # warm
        ms, cpu_ms = [], []
        for _ in range(repeats):
            c0, t0 = _cpu_s(), time.perf_counter()
            r = client.get(path, params=params)
            ms.append((time.perf_counter() - t0) * 1e3)
            cpu_ms.append((_cpu_s() - c0) * 1e3)
            assert r.status_code == 200, r.text
        ms.sort()
        print(f"  {name:52s} p50 {statistics.median(ms):6.1f} ms   p95 {ms[int(0.95 * (len(ms) - 1))]:6.1f} ms   "
              f"server CPU p50 {statistics.median(cpu_ms):5.1f} ms")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--results", type=int, default=3000, help="results to ingest")
    p.add_argument("--processes", type=int, default=4, help="result sending processes (runtime hosts)")
    p.add_argument("--threads", type=int, default=16, help="concurrent deliveries per sending process")
    p.add_argument("--throws", type=int, default=100_000, help="stored throws for the latency part (0: skip it)")
    p.add_argument("--repeats", type=int, default=40)
    p.add_argument("--debug", action="store_true", help="log each stored batch")
    p.add_argument("--profile", action="store_true", help="profile the result path during ingestion")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    if args.debug:
        logging.getLogger("server.fleet.link").setLevel(logging.DEBUG)
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.config import Settings
    from tests.conftest import ADMIN, add_user, free_port, login

    name = f"slinger_bench_{uuid.uuid4().hex[:8]}"
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as c:
        c.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        with tempfile.TemporaryDirectory() as tmp:
            settings = Settings(data_dir=Path(tmp), database_url=f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}",
                                zenoh_listen=[endpoint], viser_enabled=False, auto_migrate=True, job_queue_url="immediate",
                                runtime_gone_s=3600.0, result_grace_s=3600.0)
            with TestClient(create_app(settings)) as client:
                add_user(client.app.state.sessions, *ADMIN, "admin")
                login(client, *ADMIN)
                ingest(client.app, endpoint, args.results, args.processes, args.threads, args.profile)
                if args.throws > 0:
                    t0 = time.perf_counter()
                    fill(client.app, args.throws)
                    print(f"filled to {args.throws} throws in {time.perf_counter() - t0:.0f} s")
                    latency(client, args.repeats)
    finally:
        with admin.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
