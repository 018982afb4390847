"""Wall time to the 2D bar: evaluate a training run's kept checkpoints in the CPU twin.

Train with ``slinger train --mode 2d --keep-every 50 --log-dir RUN`` (GPU), then::

    python tests/benchmarks/bar_scan.py RUN --iterations 100 150 200 250 300 350 --throws 30

Each checkpoint ``RUN/checkpoint_<it>.pt`` is exported to ONNX and evaluated by the paper's 2D
protocol (7.5-10 m, ``--throws`` per target); the bar is |bias| <= 10 cm and sigma <= 10 cm
downrange at every target with >= 98 % success. ``RUN/curve.csv`` gives each iteration's wall
time. Prints one line per checkpoint and writes ``RUN/bar_scan.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from sim_twin.evaluation.evaluate import evaluate
from sim_twin.training.export import export_checkpoint
from sim_twin.training.config import load_config

TARGETS_M = [7.5, 8.0, 8.5, 9.0, 9.5, 10.0]


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("run", type=Path)
    p.add_argument("--iterations", type=int, nargs="+", required=True)
    p.add_argument("--throws", type=int, default=30)
    a = p.parse_args()
    cfg = load_config("2d", None)
    out = {}
    for it in a.iterations:
        onnx = export_checkpoint(a.run / f"checkpoint_{it}.pt", cfg, a.run / f"scan_{it}.onnx", name=f"scan-{it}")
        rep = evaluate(onnx, "2d", TARGETS_M, a.throws, workers=2)
        rows = [(t["target_m"], round(t["bias_m"], 3), round(t["sigma_downrange_m"], 3), t["success_rate"]) for t in rep["targets"]]
        ok = all(abs(b) <= 0.10 and s <= 0.10 and sr >= 0.98 for _, b, s, sr in rows)
        out[it] = {"rows": rows, "bar_met": ok}
        print(it, ok, rows, flush=True)
    (a.run / "bar_scan.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
