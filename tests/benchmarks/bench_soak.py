"""Soak: preview and throw in a loop on one machine as the console does, for ``--minutes``
(default 60; SIGTERM or SIGINT ends it early, with its report), with the whole stack as separate processes (tests/fault_stack.py: server, worker,
simulated machine, runtime; the deployed 2D policy).

Per throw, as the console: wait until the machine is READY, preview (one rollout), send the throw
with that preview; a throw refused because the preview no longer matches the machine (409) is
previewed again. A machine not ready for ``READY_WAIT_S`` (a failed throw left the arm outside the
envelope) is sent back to its ready pose as the operator would (``POST .../return-to-ready``). The resident memory (VmRSS) of each process is sampled every minute and every
``--sample-every`` throws (the server's and the worker's are printed every 100 throws). Prints and
writes (``--out``): throws per minute, previews needed per throw, final statuses, and memory per
process over time (MiB; first sample after a warm-up of ``--warmup-min`` minutes, last sample,
growth, and the least-squares slope of RSS against throws after warm-up in MiB per 100 throws),
and with ``--out`` a plot of every process's memory over time (``<out>.png``). With
``--probe-dir`` the server, the worker and the runtime also record, every 30 s, where their memory is
(tests/benchmarks/memprobe: glibc's heap in use and free, SQLite's caches, Python's objects); the
rows go into the JSON and the plot. Goal: memory flat after warm-up, one preview per throw.

Run: ``PYTHONPATH=. python tests/benchmarks/bench_soak.py --minutes 60 --probe-dir /tmp/soak-probe --out reports/soak``
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import logging
import os
import signal
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from tests.benchmarks.bench_estop_isolation import host_info  # noqa: E402
from tests.fault_stack import TARGET_2D, FaultStack, orphans  # noqa: E402

log = logging.getLogger("bench_soak")

PROCESSES = ("server", "worker", "plant", "runtime")
STOP = threading.Event()
"""Set by SIGTERM or SIGINT: the loop ends early and the report is written for the time run."""
READY_WAIT_S = 30.0
"""A machine not ready this long is sent back to its ready pose (counted in ``recoveries``)."""
PROBE = Path(__file__).resolve().parent / "memprobe"
"""The folder whose sitecustomize records the server's, worker's and runtime's memory (``--probe-dir``)."""


def rss_mib(pid: int) -> float | None:
    """Resident memory of ``pid`` in MiB (None if it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _ready(stack: FaultStack, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = stack.machine() or {}
        if m.get("ready"):
            return True
        time.sleep(0.1)
    return False


def one_throw(stack: FaultStack, max_previews: int = 5) -> tuple[int, str, str | None, str | None]:
    """(previews made, final status or "refused", last refusal, the throw's failure reason) of
    one console-style throw."""
    body = {"machine_id": "m1", "mode": "2d", "target": TARGET_2D}
    reason = None
    for n in range(1, max_previews + 1):
        p = stack.http.post("/api/previews", json={**body, "rollouts": 1})
        if p.status_code != 200 or p.json().get("status") != "ok":
            reason = f"preview {p.status_code}: {p.text[:120]}"
            time.sleep(0.5)
            continue
        r = stack.http.post("/api/throws", json={**body, "preview_id": p.json()["id"]})
        if r.status_code == 202:
            tid = r.json()["id"]
            row, _ = stack.wait_final(tid, 60)
            return n, row["status"], reason, row.get("failure_reason")
        reason = f"throw {r.status_code}: {r.json().get('detail', '')[:120]}"
        if r.status_code != 409:
            time.sleep(0.5)
    return max_previews, "refused", reason, None


def run(minutes: float, warmup_min: float, policy: Path, sample_every: int = 25) -> dict:
    stop_at = time.monotonic() + 60.0 * minutes
    previews, statuses, refusals, recoveries, memory, failures = [], Counter(), Counter(), Counter(), [], Counter()
    t_start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="bench-soak-") as tmp:
        stack = FaultStack(Path(tmp), policy)
        stack.start_timeout_s = 400.0

        def sample() -> dict:
            row = {"t_min": round((time.monotonic() - t_start) / 60.0, 2), "throws": sum(statuses.values()),
                   **{name: rss_mib(stack.procs[name].pid) for name in PROCESSES},
                   "load1": round(os.getloadavg()[0], 2), "failed": statuses["failed"]}
            memory.append(row)
            return row

        with stack:
            next_sample, next_count = time.monotonic(), sample_every
            while time.monotonic() < stop_at and not STOP.is_set():
                if time.monotonic() >= next_sample:
                    sample()
                    next_sample += 60.0
                if sum(statuses.values()) >= next_count:
                    row = sample()
                    next_count += sample_every
                    if row["throws"] % 100 == 0:
                        print(f"{row['throws']:5d} throws, {row['t_min']:6.1f} min: server {row['server']:.1f} MiB, "
                              f"worker {row['worker']:.1f} MiB, runtime {row['runtime']:.1f} MiB", flush=True)
                if not _ready(stack, READY_WAIT_S):
                    refusals[f"not ready within {READY_WAIT_S:.0f} s: " + str((stack.machine() or {}).get("not_ready_reason"))] += 1
                    try:
                        r = stack.http.post("/api/machines/m1/return-to-ready")
                        recoveries[f"return to ready: {r.status_code}"] += 1
                    except httpx.HTTPError as e:
                        recoveries[f"return to ready: {e!r}"[:160]] += 1
                    continue
                try:
                    n, status, reason, row_reason = one_throw(stack)
                except (httpx.HTTPError, AssertionError) as e:
                    refusals[f"error: {e!r}"[:160]] += 1
                    continue
                previews.append(n)
                statuses[status] += 1
                if status != "landed" and row_reason:
                    failures[row_reason[:100]] += 1
                if reason:
                    refusals[reason] += 1
                log.info("throw %d: %s after %d preview(s)%s", sum(statuses.values()), status, n,
                         f" (refused first: {reason})" if n > 1 else "")
            sample()
            plant_log = stack.log_text("plant")
            server_log = stack.log_text("server")
        left = orphans(tmp)
    faults = [line for line in plant_log.splitlines() if "behind real time by" in line and "machine fault" in line]
    trims = [line.split("heap trimmed in ")[1] for line in server_log.splitlines() if "heap trimmed in " in line]
    elapsed_min = (time.monotonic() - t_start) / 60.0
    return {"elapsed_min": elapsed_min, "previews": previews, "statuses": dict(statuses),
            "refusals": dict(refusals.most_common(10)), "recoveries": dict(recoveries), "memory": memory, "orphans": left, "warmup_min": warmup_min,
            "failure_reasons": dict(failures.most_common(10)), "plant_behind_real_time_faults": len(faults),
            "server_heap_trim_longest": trims[-1] if trims else None}


def _slope_per_100(points: list[tuple[int, float]]) -> float | None:
    """Least-squares slope of RSS (MiB) against throws, per 100 throws; None without a spread of
    throw counts."""
    n = len(points)
    mx = sum(x for x, _ in points) / n
    my = sum(y for _, y in points) / n
    sxx = sum((x - mx) ** 2 for x, _ in points)
    if sxx == 0:
        return None
    return round(100.0 * sum((x - mx) * (y - my) for x, y in points) / sxx, 2)


def memory_growth(samples: list[dict], warmup_min: float) -> dict:
    """Per process, from the samples at or after ``warmup_min``: RSS then and last (MiB), growth,
    growth per 100 throws, the least-squares slope per 100 throws, and that slope over the second
    half of the time after warm-up alone (flat there: the memory has levelled off)."""
    mem = [m for m in samples if m["t_min"] >= warmup_min] or samples
    half = [m for m in mem if m["t_min"] >= (mem[0]["t_min"] + mem[-1]["t_min"]) / 2.0]
    growth = {}
    for name in PROCESSES:
        vals = [(m["throws"], m[name]) for m in mem if m[name] is not None]
        if len(vals) >= 2:
            (_, a), (_, b) = vals[0], vals[-1]
            late = [(m["throws"], m[name]) for m in half if m[name] is not None]
            growth[name] = {"after_warmup_mib": round(a, 1), "last_mib": round(b, 1), "growth_mib": round(b - a, 1),
                            "growth_mib_per_100_throws": round(100.0 * (b - a) / max(1, mem[-1]["throws"] - mem[0]["throws"]), 2),
                            "slope_mib_per_100_throws": _slope_per_100(vals),
                            "slope_second_half_mib_per_100_throws": _slope_per_100(late) if len(late) >= 2 else None}
    return growth


def probe_summary(probe: dict[str, list[dict]], warmup_min: float) -> dict:
    """Per role (server, worker, runtime) and probe column: the value at the end of warm-up, half-way
    through the rest and at the end (MiB; Python blocks and gc objects as counts)."""
    out = {}
    for role, rows in probe.items():
        rows = [r for r in rows if r["t_s"] >= 60.0 * warmup_min] or rows
        if not rows:
            continue
        mid = min(rows, key=lambda r: abs(r["t_s"] - (rows[0]["t_s"] + rows[-1]["t_s"]) / 2.0))
        out[role] = {c: [rows[0][c], mid[c], rows[-1][c]] for c in rows[0] if c != "t_s"}
        out[role]["t_min"] = [round(r["t_s"] / 60.0, 1) for r in (rows[0], mid, rows[-1])]
    return out


def load_summary(samples: list[dict]) -> dict | None:
    """The host's 1-minute load average over the run (sampled with the memory): min, median, max
    and the value every 10 minutes."""
    loads = [(m["t_min"], m["load1"]) for m in samples if m.get("load1") is not None]
    if not loads:
        return None
    v = sorted(x for _, x in loads)
    every10, nxt = [], 0.0
    for t, x in loads:
        if t >= nxt:
            every10.append([round(t, 1), x])
            nxt += 10.0
    return {"min": v[0], "median": v[len(v) // 2], "max": v[-1], "every_10_min": every10}


def summary(out: dict) -> dict:
    """Throws per minute, previews per throw and memory growth per process after warm-up."""
    throws = sum(out["statuses"].values())
    p = out["previews"]
    return {"throws": throws, "throws_per_min": round(throws / out["elapsed_min"], 2) if out["elapsed_min"] else None,
            "previews_per_throw_mean": round(sum(p) / len(p), 3) if p else None,
            "throws_needing_more_than_one_preview": sum(1 for n in p if n > 1),
            "statuses": out["statuses"], "memory": memory_growth(out["memory"], out["warmup_min"])}


def enable_probe(probe_dir: Path) -> None:
    """Have the stack's server, worker and runtimes (started after this call) write their memory rows to
    ``probe_dir`` (tests/benchmarks/memprobe/sitecustomize.py)."""
    probe_dir.mkdir(parents=True, exist_ok=True)
    for f in probe_dir.glob("*.tsv"):
        f.unlink()
    os.environ["MEMPROBE_DIR"] = str(probe_dir)
    os.environ["PYTHONPATH"] = os.pathsep.join([str(PROBE), str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])


def read_probe(probe_dir: Path) -> dict[str, list[dict]]:
    """The probe's rows by role ("server", "worker", "runtime"): dicts of its columns, bytes turned into MiB."""
    out: dict[str, list[dict]] = {}
    for f in sorted(probe_dir.glob("*.tsv")):
        lines = f.read_text().splitlines()
        cols = lines[0].split("\t")
        rows = []
        for line in lines[1:]:
            vals = [int(v) for v in line.split("\t")]
            rows.append({c: (round(v / 2**20, 2) if c in ("rss", "arena", "hblkhd", "uordblks", "fordblks", "sqlite", "rss_anon", "rss_file", "pyarenas")
                               else v)
                         for c, v in zip(cols, vals)})
        out.setdefault(f.stem.split("-")[0], []).extend(rows)
    return out


def plot(report: dict, path: Path) -> None:
    """RSS of every process against minutes (top) and, with the probe's rows, the server's and
    worker's heap in use, heap free and SQLite's memory (bottom); written to ``path`` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    probe = report.get("probe_mib") or {}
    fig, axes = plt.subplots(2 if probe else 1, 1, figsize=(9, 7 if probe else 4), squeeze=False)
    ax = axes[0][0]
    mem = report["memory_samples_mib"]
    for name in PROCESSES:
        pts = [(m["t_min"], m[name]) for m in mem if m[name] is not None]
        ax.plot([t for t, _ in pts], [v for _, v in pts], label=name)
    ax.axvline(report["warmup_min"], color="grey", ls=":", lw=1)
    ax.set_xlabel("minutes since start")
    ax.set_ylabel("RSS [MiB]")
    ax.set_title(f"Soak: {report['throws']} throws in {report['duration_min']:.0f} min (simulated machine)")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    if probe:
        ax = axes[1][0]
        for role, style in (("server", "-"), ("worker", "--"), ("runtime", ":")):
            rows = probe.get(role, [])
            t = [r["t_s"] / 60.0 for r in rows]
            for col, label in (("uordblks", "heap in use"), ("fordblks", "heap free"), ("sqlite", "SQLite"),
                               ("pyarenas", "Python arenas"), ("rss_file", "file-backed")):
                if rows and col in rows[0]:
                    ax.plot(t, [r[col] for r in rows], style, label=f"{role}: {label}")
        ax.set_xlabel("minutes since the process started")
        ax.set_ylabel("MiB")
        ax.set_yscale("log")
        ax.legend(loc="lower right", fontsize=7, ncol=2)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(report: dict, out: Path | None) -> None:
    """Print the report's figures; with ``out``, write <out>.json, <out>.md and <out>.png."""
    print(f"{report['throws']} throws in {report['duration_min']:.1f} min ({report['throws_per_min']} / min), "
          f"statuses {report['statuses']}")
    print(f"previews per throw: mean {report['previews_per_throw_mean']}, "
          f"{report['throws_needing_more_than_one_preview']} throws needed more than one")
    for name, g in report["memory"].items():
        print(f"{name:8s} RSS {g['after_warmup_mib']} -> {g['last_mib']} MiB ({g['growth_mib']:+} MiB, "
              f"{g['growth_mib_per_100_throws']:+} MiB / 100 throws; slope {g['slope_mib_per_100_throws']}, second half "
              f"{g.get('slope_second_half_mib_per_100_throws')} MiB / 100 throws)")
    print(f"orphaned processes: {report['orphaned_processes']}; plant 'behind real time' faults: "
          f"{report.get('plant_behind_real_time_faults')}; load {report.get('load1_over_time')}; "
          f"longest heap trim {report.get('server_heap_trim_longest')}")
    if out is None:
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
    lines = [f"# Soak: preview and throw on one simulated machine ({report['duration_min']:.0f} min)", "",
             f"Measured {report['date_utc']} on commit `{report['host']['commit']}`, host {report['host']['cpu_model']} "
             f"({report['host']['cpu_count']} CPUs), load average {report['host']['loadavg_before'][0]:.1f} before / "
             f"{report['host']['loadavg'][0]:.1f} after (a shared machine). Policy `{report['policy']['path']}` "
             f"(SHA-256 `{report['policy']['sha256'][:16]}…`). The machine is the simulated machine (sim_twin plant).", "",
             f"* throws: {report['throws']} ({report['throws_per_min']} per minute), statuses {report['statuses']}",
             f"* previews per throw: mean {report['previews_per_throw_mean']}; throws needing more than one: "
             f"{report['throws_needing_more_than_one_preview']}",
             f"* machine sent back to its ready pose after {READY_WAIT_S:.0f} s not ready: {report.get('recoveries') or 'never'}",
             f"* failed throws' reasons (most frequent): {report.get('failure_reasons_top')}",
             f"* the simulated machine's 'behind real time' faults (plant log): {report.get('plant_behind_real_time_faults')}",
             f"* host 1-minute load over the run: {report.get('load1_over_time')}",
             f"* the server's longest heap trim (server log): {report.get('server_heap_trim_longest')}",
             "", f"Memory after a warm-up of {report['warmup_min']:g} min:", "",
             "| process | RSS after warm-up MiB | last MiB | growth MiB | MiB / 100 throws | slope MiB / 100 throws "
             "| slope, second half MiB / 100 throws |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {n} | {g['after_warmup_mib']} | {g['last_mib']} | {g['growth_mib']:+} | {g['growth_mib_per_100_throws']:+} "
              f"| {g['slope_mib_per_100_throws']} | {g.get('slope_second_half_mib_per_100_throws')} |"
              for n, g in report["memory"].items()]
    if report.get("probe_summary"):
        lines += ["", "Where the server's and worker's memory is (tests/benchmarks/memprobe; MiB at the end of warm-up, "
                  "half-way, at the end):", "",
                  "| process | minutes | RSS | anonymous | file-backed | glibc heap in use | glibc heap free | SQLite "
                  "| Python arenas | Python blocks |", "|---|---|---|---|---|---|---|---|---|---|"]
        for role, p in report["probe_summary"].items():
            cols = ("rss", "rss_anon", "rss_file", "uordblks", "fordblks", "sqlite", "pyarenas", "pyblocks")
            lines.append(f"| {role} | {' / '.join(map(str, p['t_min']))} | "
                         + " | ".join(" / ".join(map(str, p[c])) if c in p else "-" for c in cols) + " |")
    lines += ["", f"![memory over time]({out.with_suffix('.png').name})", "", f"Reproduce: `{report['command']}`", ""]
    out.with_suffix(".md").write_text("\n".join(lines))
    plot(report, out.with_suffix(".png"))


def figures(report: dict) -> list[dict]:
    """The report's headline figures for docs/results.md (``slinger results``): duration and
    throws, and the server's and worker's RSS slope after warm-up and over its second half."""
    out = [{"what": "soak duration", "value": round(report["duration_min"], 1), "unit": "min",
            "conditions": f"{report['throws']} throws, one simulated machine"}]
    for name in ("server", "worker"):
        g = report["memory"].get(name)
        if g is None:
            continue
        out.append({"what": f"{name} RSS slope after a {report['warmup_min']:g}-minute warm-up", "unit": "MiB / 100 throws",
                    "value": g["slope_mib_per_100_throws"],
                    "conditions": f"{g['after_warmup_mib']} -> {g['last_mib']} MiB"})
        out.append({"what": f"{name} RSS slope over the second half after warm-up", "unit": "MiB / 100 throws",
                    "value": g["slope_second_half_mib_per_100_throws"]})
    return out


def resummarise(path: Path) -> dict:
    """A report written by this script with its memory figures computed again from its samples
    (memory_growth, probe_summary) by this version of the script."""
    report = json.loads(path.read_text())
    report.setdefault("warmup_min", 2.0)  # reports written before it was recorded: the default
    report["memory"] = memory_growth(report["memory_samples_mib"], report["warmup_min"])
    if report.get("probe_mib"):
        report["probe_summary"] = probe_summary(report["probe_mib"], report["warmup_min"])
    report["figures"] = figures(report)
    return report


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=60.0)
    parser.add_argument("--warmup-min", type=float, default=2.0, help="memory growth is measured from here on")
    parser.add_argument("--sample-every", type=int, default=25, help="also sample memory every this many throws")
    parser.add_argument("--policy", type=Path, default=REPO / "policies" / "throw2d.onnx")
    parser.add_argument("--out", type=Path, default=None, help="write <out>.json, <out>.md and <out>.png")
    parser.add_argument("--probe-dir", type=Path, default=None,
                        help="record where the server's, worker's and runtime's memory is (tests/benchmarks/memprobe) here")
    parser.add_argument("--summarise", type=Path, default=None,
                        help="compute the memory figures of this report JSON again (and write --out); runs nothing")
    args = parser.parse_args()
    if args.summarise is not None:
        write(resummarise(args.summarise), args.out)
        return 0
    if args.probe_dir is not None:
        enable_probe(args.probe_dir)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: STOP.set())
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    started = dt.datetime.now(dt.UTC)
    host0 = host_info()
    out = run(args.minutes, args.warmup_min, args.policy, args.sample_every)
    s = summary(out)
    report = {
        "benchmark": "soak: console-style preview and throw loop on one simulated machine",
        "date_utc": started.isoformat(timespec="seconds"),
        "duration_min": round(out["elapsed_min"], 2),
        "warmup_min": args.warmup_min,
        "command": "PYTHONPATH=. python tests/benchmarks/bench_soak.py " + " ".join(sys.argv[1:]),
        "host": {**host_info(), "loadavg_before": host0["loadavg"], "commit": host0["commit"]},
        "policy": {"path": "policies/throw2d.onnx" if args.policy == REPO / "policies" / "throw2d.onnx" else str(args.policy),
                   "sha256": hashlib.sha256(args.policy.read_bytes()).hexdigest()},
        **s,
        "refusals_top": out["refusals"],
        "recoveries": out["recoveries"],
        "failure_reasons_top": out["failure_reasons"],
        "plant_behind_real_time_faults": out["plant_behind_real_time_faults"],
        "server_heap_trim_longest": out["server_heap_trim_longest"],
        "load1_over_time": load_summary(out["memory"]),
        "memory_samples_mib": out["memory"],
        "orphaned_processes": len(out["orphans"]),
        "probe_mib": read_probe(args.probe_dir) if args.probe_dir is not None else None,
    }
    if report["probe_mib"]:
        report["probe_summary"] = probe_summary(report["probe_mib"], args.warmup_min)
    report["figures"] = figures(report)
    write(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
