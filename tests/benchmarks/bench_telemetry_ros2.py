"""Cost of a throw's telemetry in ROS 2 form (runtime.telemetry.write_mcap / read_telemetry) for
throws of 300, 600 and 1000 ticks at 100 Hz: CPU seconds (process time, median of 5) and file size,
beside the JSON layout of before (tests/data/telemetry_json_v1.mcap is one; its writer is gone, so
its size per tick is the reference). The runtime writes the file when a throw ends, under its
lock; a 600-tick throw (6 s) is typical.

Run: ``python tests/benchmarks/bench_telemetry_ros2.py [--out reports/telemetry_ros2.json]``
"""

from __future__ import annotations

import argparse
import json
import platform
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
    old = (REPO / "tests" / "data" / "telemetry_json_v1.mcap").stat().st_size
    print(f"JSON layout of before: {old / 50:.0f} bytes per tick (50-tick fixture)")
    report = {"date": datetime.now(UTC).isoformat(timespec="seconds"),
              "commit": subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=False).stdout.strip(),
              "policy_sha256": None, "host": f"{platform.node()} {platform.processor() or platform.machine()}, "
                                                 f"{__import__('os').cpu_count()} cores (shared)",
              "command": "python tests/benchmarks/bench_telemetry_ros2.py --out reports/telemetry_ros2.json",
              "rows": rows, "json_layout_bytes_per_tick": old / 50}
    if args.out:
        args.out.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
