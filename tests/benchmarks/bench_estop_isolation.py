"""E-STOP isolation: click (HTTP POST /api/machines/m1/estop) -> first neutral ValveCommand of the
healthy machine m1 while the runtimes of the other machines are frozen (SIGSTOP) and eight
clients keep pressing those machines' E-STOPs. Goal: p99 <= 100 ms (issue 24, build 1).

The stack (tests/fault_stack.py: server, worker, and for each machine the simulated machine and
the runtime as separate processes) runs m1 plus ``--frozen`` more machines (m2, m3, ...). Their
runtimes are frozen for ``--freeze-s`` and thawed for 0.5 s in turn, so their Zenoh links stay up
(lease 10 s) and the server keeps treating them as online-but-silent, the worst case for a
shared E-STOP path. ``--clients`` threads, each with its own HTTP connection, press the frozen
machines' E-STOPs in a loop (each press is answered 503 after its deadline, 2 s).

Each m1 click stops a throw mid-swing (the deployed 2D policy, swing ~1.5 s), as
tests/benchmarks/bench_estop_latency.py does: preview, throw, wait for ``swinging``, a random
0-0.4 s, click; then reset, reload the simulated machine and wait until ready. A click counts only
if the valve command just before it was not neutral.

Run: ``PYTHONPATH=. python tests/benchmarks/bench_estop_isolation.py --clicks 30 --out reports/estop_isolation``
(writes <out>.json and <out>.md with date, commit, host, load and this command).
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import logging
import os
import platform
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from tests.benchmarks.bench_estop_latency import click_cycle  # noqa: E402
from tests.fault_stack import FaultStack, ValveWatch, orphans, stop_proc  # noqa: E402

log = logging.getLogger("bench_estop_isolation")


def stats_ms(values: list[float]) -> dict:
    """{n, p50, p95, p99, max} of ``values`` (s) in ms; n only when empty."""
    a = np.asarray(values, dtype=float) * 1e3
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), **{f"p{q}": round(float(np.percentile(a, q)), 1) for q in (50, 95, 99)},
            "max": round(float(a.max()), 1)}


def _fmt(s: dict) -> str:
    if not s.get("n"):
        return "n=0"
    return f"n={s['n']} p50={s['p50']} p95={s['p95']} p99={s['p99']} max={s['max']} ms"


class Freezer:
    """Freezes processes (SIGSTOP) for ``freeze_s`` and thaws them (SIGCONT) for ``thaw_s`` in
    turn until stopped; thaws them at the end."""

    def __init__(self, procs: list[subprocess.Popen], freeze_s: float, thaw_s: float = 0.5):
        self.procs, self.freeze_s, self.thaw_s = procs, freeze_s, thaw_s
        self.frozen_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _signal(self, sig: int) -> None:
        for p in self.procs:
            if p.poll() is None:
                os.kill(p.pid, sig)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._signal(signal.SIGSTOP)
            t0 = time.monotonic()
            self._stop.wait(self.freeze_s)
            self.frozen_s += time.monotonic() - t0
            self._signal(signal.SIGCONT)
            self._stop.wait(self.thaw_s)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self._signal(signal.SIGCONT)


def _press_loop(base_url: str, cookies, machine_ids: list[str], stop: threading.Event, out: list) -> None:
    """One client pressing the frozen machines' E-STOPs in turn until ``stop``; appends
    (machine id, HTTP status, seconds) per press."""
    with httpx.Client(base_url=base_url, cookies=cookies, timeout=30) as c:
        i = 0
        while not stop.is_set():
            mid = machine_ids[i % len(machine_ids)]
            i += 1
            t0 = time.monotonic()
            try:
                code = c.post(f"/api/machines/{mid}/estop", json={"reason": "isolation benchmark"}).status_code
            except httpx.HTTPError:
                code = -1
            out.append((mid, code, time.monotonic() - t0))


def run(clicks: int, frozen: int, clients: int, policy: Path, freeze_s: float, seed: int = 0,
        max_minutes: float = 10.0) -> dict:
    rng = random.Random(seed)
    stop_at = time.monotonic() + 60.0 * max_minutes
    neutral_s, reply_s, refusals, not_moving = [], [], [], 0
    others = [f"m{i + 2}" for i in range(frozen)]
    presses: list = []
    with tempfile.TemporaryDirectory(prefix="bench-estop-iso-") as tmp:
        stack = FaultStack(Path(tmp), policy)
        stack.start_timeout_s = 400.0
        with stack:
            for mid in others:
                stack.spawn(f"plant-{mid}", stack.plant_argv(mid))
                stack.spawn(f"runtime-{mid}", stack.runtime_argv(mid))
            for mid in others:
                stack.wait_ready(400, mid, ("server", f"plant-{mid}", f"runtime-{mid}"))
            watch = ValveWatch(stack.endpoint)
            freezer = Freezer([stack.procs[f"runtime-{m}"] for m in others], freeze_s)
            stop = threading.Event()
            pressers = [threading.Thread(target=_press_loop, args=(stack.base_url, stack.http.cookies, others, stop, presses),
                                         daemon=True) for _ in range(clients)]
            for t in pressers:
                t.start()
            try:
                attempts = 0
                while len(neutral_s) < clicks and attempts < clicks * 4 and time.monotonic() < stop_at:
                    attempts += 1
                    c = click_cycle(stack, watch, rng, "isolation benchmark")
                    refusals += c["refusals"]
                    not_moving += c["moving"] is False
                    if c["neutral_s"] is not None:
                        neutral_s.append(c["neutral_s"])
                        reply_s.append(c["reply_s"])
                        log.info("click %d: neutral after %.1f ms, reply after %.1f ms (%d presses of frozen machines so far)",
                                 len(neutral_s), c["neutral_s"] * 1e3, c["reply_s"] * 1e3, len(presses))
            finally:
                stop.set()
                for t in pressers:
                    t.join(timeout=30)
                freezer.stop()
                watch.close()
        left = orphans(tmp)
    frozen_press_s = [s for _, code, s in presses]
    return {"neutral_s": neutral_s, "reply_s": reply_s, "refusals": refusals, "orphans": left,
            "not_moving": not_moving, "frozen_presses": len(presses),
            "frozen_press_codes": {str(c): sum(1 for _, k, _ in presses if k == c) for c in sorted({k for _, k, _ in presses})},
            "frozen_press_s": frozen_press_s, "frozen_s": freezer.frozen_s}


def host_info() -> dict:
    """CPU model, core count, load averages and the git commit of this checkout."""
    model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), platform.processor())
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                                capture_output=True, text=True).stdout.strip())
    return {"cpu_model": model, "cpu_count": os.cpu_count(), "loadavg": list(os.getloadavg()),
            "commit": commit + ("-dirty" if dirty else ""), "hostname": platform.node()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clicks", type=int, default=30)
    parser.add_argument("--frozen", type=int, default=2, help="machines besides m1 whose runtimes are frozen")
    parser.add_argument("--clients", type=int, default=8, help="clients pressing the frozen machines' E-STOPs")
    parser.add_argument("--freeze-s", type=float, default=5.0, help="freeze period (thawed 0.5 s between)")
    parser.add_argument("--policy", type=Path, default=REPO / "policies" / "throw2d.onnx")
    parser.add_argument("--max-minutes", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=None, help="write <out>.json and <out>.md")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    load_before = list(os.getloadavg())
    started = dt.datetime.now(dt.timezone.utc)
    out = run(args.clicks, args.frozen, args.clients, args.policy, args.freeze_s, max_minutes=args.max_minutes)
    host = host_info()
    report = {
        "benchmark": "E-STOP isolation: click -> first neutral ValveCommand of a healthy machine, other runtimes frozen",
        "date_utc": started.isoformat(timespec="seconds"),
        "duration_s": round((dt.datetime.now(dt.timezone.utc) - started).total_seconds(), 1),
        "command": "PYTHONPATH=. python tests/benchmarks/bench_estop_isolation.py " + " ".join(sys.argv[1:]),
        "host": {**host, "loadavg_before": load_before},
        "policy": {"path": str(args.policy.relative_to(REPO)) if args.policy.is_relative_to(REPO) else str(args.policy),
                   "sha256": hashlib.sha256(args.policy.read_bytes()).hexdigest()},
        "setup": {"frozen_machines": args.frozen, "clients_pressing_frozen": args.clients, "freeze_s": args.freeze_s,
                  "thaw_s": 0.5, "simulated_machines": True},
        "click_to_neutral_ms": stats_ms(out["neutral_s"]),
        "click_to_reply_ms": stats_ms(out["reply_s"]),
        "goal_p99_ms": 100.0,
        "frozen_machine_presses": out["frozen_presses"],
        "frozen_machine_press_status_codes": out["frozen_press_codes"],
        "frozen_machine_press_reply_ms": stats_ms(out["frozen_press_s"]),
        "clicks_discarded_not_moving": out["not_moving"],
        "refusals": out["refusals"],
        "orphaned_processes": len(out["orphans"]),
    }
    print(f"E-STOP click -> first neutral ValveCommand of m1 ({args.frozen} frozen runtimes, {args.clients} clients "
          f"pressing them): {_fmt(report['click_to_neutral_ms'])}")
    print(f"E-STOP click -> HTTP reply (runtime confirmed, latch on disk):  {_fmt(report['click_to_reply_ms'])}")
    print(f"presses of the frozen machines meanwhile: {out['frozen_presses']} {out['frozen_press_codes']}")
    print(f"clicks discarded (valves already neutral): {out['not_moving']}; refusals: {len(out['refusals'])}")
    print(f"orphaned processes: {len(out['orphans'])}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
        args.out.with_suffix(".md").write_text(markdown(report))
    return 0


def markdown(r: dict) -> str:
    """The report as a short Markdown page."""
    h = r["host"]
    n, rep = r["click_to_neutral_ms"], r["click_to_reply_ms"]
    row = lambda s: f"{s.get('n', 0)} | {s.get('p50', '-')} | {s.get('p95', '-')} | {s.get('p99', '-')} | {s.get('max', '-')}"  # noqa: E731
    return f"""# E-STOP isolation (simulated machines)

{r['benchmark']}. Measured {r['date_utc']} on commit `{h['commit']}`, host {h['cpu_model']} ({h['cpu_count']} CPUs),
load average {h['loadavg_before'][0]:.1f} before / {h['loadavg'][0]:.1f} after (a shared machine).
Policy `{r['policy']['path']}` (SHA-256 `{r['policy']['sha256'][:16]}…`). {r['setup']['frozen_machines']} other
machines' runtimes frozen (SIGSTOP {r['setup']['freeze_s']} s, thawed 0.5 s, in turn), {r['setup']['clients_pressing_frozen']}
clients pressing their E-STOPs throughout ({r['frozen_machine_presses']} presses, HTTP status counts
{r['frozen_machine_press_status_codes']}). Machines are the simulated machine (sim_twin plant) behind the Zenoh interface.

| measure | n | p50 ms | p95 ms | p99 ms | max ms |
|---|---|---|---|---|---|
| click -> first neutral ValveCommand (m1) | {row(n)} |
| click -> HTTP reply (m1, confirmed, latch on disk) | {row(rep)} |

Goal: p99 <= {r['goal_p99_ms']:.0f} ms (click -> neutral). Clicks discarded (valves already neutral): {r['clicks_discarded_not_moving']};
refusals meanwhile: {len(r['refusals'])}; orphaned processes: {r['orphaned_processes']}.

Reproduce: `{r['command']}`
"""


if __name__ == "__main__":
    raise SystemExit(main())
