"""Memory of the job worker's preview loop, in one process without a stack: ``--n`` preview jobs
(console-style: nominal rollout only, the 2D policy, random start poses of
sim_twin.twin.initial_pose.sample_pose, target 8 m) through the worker's own path
(server.jobs.tasks.execute: job row in SQLite, policy runner cache, preview_throw on the
SimulatedMachine twin, result written back), run in one long-lived thread as a Huey thread
consumer runs them. Every ``--every`` jobs it prints and records the resident memory (VmRSS),
glibc's heap in use and free (mallinfo2(3)), Python's allocated blocks (without forcing a
garbage collection: objects in reference cycles count until the cyclic GC frees them) and, with
``--tracemalloc``, the Python-level memory, whose biggest growers since job 20 are listed at the
end. Growth is the least-squares slope of RSS against jobs after ``--warmup`` jobs, MiB per 100.

``--before REPORT`` puts an earlier run's samples (another commit's) beside this one's in the
report and its plot (``<out>.png``: RSS and heap in use against jobs).

Run: ``PYTHONPATH=. python tests/benchmarks/bench_preview_memory.py --n 300 --out reports/preview_memory``
"""

from __future__ import annotations

import argparse
import ctypes
import datetime as dt
import gc
import hashlib
import json
import shutil
import sys
import tempfile
import threading
import time
import tracemalloc
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from tests.benchmarks.bench_estop_isolation import host_info  # noqa: E402
from tests.benchmarks.bench_soak import _slope_per_100  # noqa: E402


class _MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                                               "uordblks", "fordblks", "keepcost")]


def sample(libc) -> dict:
    """RSS, glibc heap in use / free (MiB) and Python's allocated blocks of this process."""
    m = libc.mallinfo2()
    with open("/proc/self/statm") as f:
        rss = int(f.read().split()[1]) * 4096
    return {"rss_mib": round(rss / 2**20, 2), "heap_in_use_mib": round(m.uordblks / 2**20, 2),
            "heap_free_mib": round(m.fordblks / 2**20, 2), "py_blocks": sys.getallocatedblocks(),
            "py_traced_mib": round(tracemalloc.get_traced_memory()[0] / 2**20, 2) if tracemalloc.is_tracing() else None}


def run(n: int, every: int, policy: Path, trace: bool) -> dict:
    """``n`` preview jobs through server.jobs.tasks.execute in one thread; samples every ``every``."""
    import numpy as np

    from server.config import Settings
    from server.db.migrate import upgrade
    from server.db.session import make_engine, make_sessionmaker
    from server.jobs import tasks
    from sim_twin.twin.initial_pose import sample_pose

    libc = ctypes.CDLL("libc.so.6")
    libc.mallinfo2.restype = _MallInfo2
    samples: list[dict] = []
    top: list[str] = []
    with tempfile.TemporaryDirectory(prefix="bench-preview-memory-") as tmp_s:
        tmp = Path(tmp_s)
        (tmp / "policies").mkdir()
        for f in (policy, policy.with_suffix(".json")):
            if f.exists():
                shutil.copy(f, tmp / "policies" / f.name)
        sha = hashlib.sha256(policy.read_bytes()).hexdigest()
        url = f"sqlite:///{tmp}/slinger.db"
        upgrade(url)
        settings = Settings(database_url=url, data_dir=tmp)
        ctx = tasks.WorkerContext(make_sessionmaker(make_engine(url, 10.0)), tmp, settings)
        tasks.bind(ctx)
        rng = np.random.default_rng(0)

        def loop() -> None:
            snap0 = None
            t0 = time.monotonic()
            for i in range(n + 1):
                req = dict(mode="2d", target_m=[8.0, -0.292, 0.0], q=sample_pose(rng, cabin_turn=0.0).tolist(),
                           qd=[0.0] * 6, rollouts=1, clearance_radius_m=settings.clearance_radius_m, release_check_radius_m=settings.release_check_radius_m)
                jid = ctx.store.create("preview", {"onnx_path": f"policies/{policy.name}", "sha256": sha,
                                                   "request": req, "meta": {"machine_id": "m1"}, "profile_path": None},
                                       subject="m1")
                tasks.execute(jid)
                if trace and i == 20:
                    gc.collect()
                    snap0 = tracemalloc.take_snapshot()
                if i % every == 0:  # no gc.collect() here: what the cyclic GC leaves between its runs counts
                    row = {"jobs": i, "t_s": round(time.monotonic() - t0, 1), "status": ctx.store.get(jid)["status"],
                           **sample(libc)}
                    samples.append(row)
                    print(f"{i:5d} jobs {row['t_s']:7.1f} s: RSS {row['rss_mib']:.1f} MiB, heap in use "
                          f"{row['heap_in_use_mib']:.1f} / free {row['heap_free_mib']:.1f} MiB, Python blocks "
                          f"{row['py_blocks']}", flush=True)
            if snap0 is not None:
                gc.collect()
                for st in tracemalloc.take_snapshot().compare_to(snap0, "lineno")[:10]:
                    top.append(str(st))

        if trace:
            tracemalloc.start(10)
        th = threading.Thread(target=loop, name="preview-jobs")
        th.start()
        th.join()
        ctx.close()
    return {"samples": samples, "tracemalloc_top": top}


def plot(report: dict, path: Path) -> None:
    """RSS (solid) and glibc heap in use (dashed) against jobs, this run and ``before`` if any."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    runs = [("this run", report)] + ([("before", report["before"])] if report.get("before") else [])
    for (label, r), color in zip(runs, ("tab:blue", "tab:red")):
        commit = r["host"]["commit"][:7]
        x = [s["jobs"] for s in r["samples"]]
        ax.plot(x, [s["rss_mib"] for s in r["samples"]], color=color, label=f"{label} ({commit}): RSS")
        ax.plot(x, [s["heap_in_use_mib"] for s in r["samples"]], color=color, ls="--", label=f"{label} ({commit}): heap in use")
    ax.set_xlabel("preview jobs")
    ax.set_ylabel("MiB")
    ax.set_title("Job worker's preview loop in one process (simulated machine twin)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=300, help="preview jobs")
    parser.add_argument("--every", type=int, default=10, help="sample memory every this many jobs")
    parser.add_argument("--warmup", type=int, default=50, help="growth is fitted from this job on")
    parser.add_argument("--tracemalloc", action="store_true", help="trace Python allocations (slower)")
    parser.add_argument("--policy", type=Path, default=REPO / "policies" / "throw2d.onnx")
    parser.add_argument("--out", type=Path, default=None, help="write <out>.json and <out>.png")
    parser.add_argument("--before", type=Path, default=None, help="an earlier run's report to show beside this one")
    args = parser.parse_args()
    started = dt.datetime.now(dt.UTC)
    host0 = host_info()
    out = run(args.n, args.every, args.policy, args.tracemalloc)
    after = [s for s in out["samples"] if s["jobs"] >= args.warmup]
    slope = _slope_per_100([(s["jobs"], s["rss_mib"]) for s in after]) if len(after) >= 2 else None
    growth = round(after[-1]["rss_mib"] - after[0]["rss_mib"], 2) if len(after) >= 2 else None
    print(f"RSS after job {args.warmup}: {after[0]['rss_mib'] if after else None} -> "
          f"{after[-1]['rss_mib'] if after else None} MiB ({growth:+} MiB; slope {slope} MiB / 100 jobs)")
    for line in out["tracemalloc_top"]:
        print("  ", line)
    if args.out is not None:
        report = {"benchmark": "worker preview loop memory, one process, no stack", "date_utc": started.isoformat(timespec="seconds"),
                  "command": "PYTHONPATH=. python tests/benchmarks/bench_preview_memory.py " + " ".join(sys.argv[1:]),
                  "host": {**host_info(), "loadavg_before": host0["loadavg"], "commit": host0["commit"]},
                  "policy": {"path": str(args.policy.relative_to(REPO)) if args.policy.is_relative_to(REPO) else str(args.policy),
                             "sha256": hashlib.sha256(args.policy.read_bytes()).hexdigest()},
                  "jobs": args.n, "warmup_jobs": args.warmup, "rss_growth_mib": growth, "slope_mib_per_100_jobs": slope,
                  **out}
        if args.before is not None:
            before = json.loads(args.before.read_text())
            report["before"] = {k: before[k] for k in ("date_utc", "command", "host", "rss_growth_mib",
                                                       "slope_mib_per_100_jobs", "samples")}
        report["figures"] = [
            {"what": f"worker preview loop, RSS slope after job {args.warmup}", "value": slope, "unit": "MiB / 100 jobs",
             "conditions": f"{args.n} jobs in one process, commit {host0['commit'][:7]}"},
            *([{"what": f"the same before the fix, RSS slope after job {args.warmup}",
                "value": report["before"]["slope_mib_per_100_jobs"], "unit": "MiB / 100 jobs",
                "conditions": f"commit {report['before']['host']['commit'][:7]}"}] if args.before is not None else [])]
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
        plot(report, args.out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
