"""Cost of a throw's telemetry in ROS 2 form (runtime.telemetry.write_mcap / read_telemetry) for
throws of 300, 600 and 1000 ticks at 100 Hz: CPU seconds (process time, median of 5) and file size,
beside the JSON layout of before (tests/data/telemetry_json_v1.mcap is one; its writer is gone, so
The runtime writes the file when a throw ends, under its lock.

Run: ``python tests/benchmarks/bench_telemetry_ros2.py [--out reports/telemetry_ros2.json]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    from runtime.telemetry import read_telemetry, write_mcap
    from tests.test_telemetry import _recording

    rows = []
    for n in (300, 600, 1000):
        rec = _recording(n)
        write_mcap(rec)  # warm (URDF, typestore)
        w, r = [], []
        for _ in range(5):
            t = time.process_time()
            blob = write_mcap(rec, {"throw_id": "b", "target_m": "[8, 0, 0]", "impact_m": "[8.2, 0.1, 0]"})
            w.append(time.process_time() - t)
            t = time.process_time()
            read_telemetry(blob)
            r.append(time.process_time() - t)
        rows.append({"ticks": n, "write_cpu_s": statistics.median(w), "read_cpu_s": statistics.median(r), "bytes": len(blob)})
        print(f"{n:5d} ticks: write {rows[-1]['write_cpu_s'] * 1e3:6.0f} ms CPU, read {rows[-1]['read_cpu_s'] * 1e3:6.0f} ms CPU, "
              f"{len(blob) / 1024:6.0f} KiB")
    from server.site.results_page import host_description

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True, check=False).stdout.strip()
    report = {
        "provenance": {"title": "Telemetry in ROS 2 form: write and read cost",
                       "date": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"), "commit": commit or "not recorded", "policies": [],
                       "host": host_description(),
                       "command": "python tests/benchmarks/bench_telemetry_ros2.py --out reports/telemetry_ros2.json",
                       "recorded": "at run time by the benchmark",
                       "note": "CPU seconds (process time, median of 5) of runtime.telemetry.write_mcap / read_telemetry on a "
                               "synthetic recording; the runtime writes the file when a throw ends"},
        "figures": [f for r in rows for f in (
            {"what": f"write, {r['ticks']} ticks ({r['ticks'] / 100:.0f} s throw)", "value": round(r["write_cpu_s"], 3), "unit": "s CPU"},
            {"what": f"read, {r['ticks']} ticks", "value": round(r["read_cpu_s"], 3), "unit": "s CPU"},
            {"what": f"file size, {r['ticks']} ticks", "value": round(r["bytes"] / 1024), "unit": "KiB"})],
    }
    if args.out:
        args.out.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
