"""False alarms and detections of the drift watch's CUSUM (server.analysis.drift.Cusum) on simulated impact errors.

Run: ``nice -n 10 python tests/benchmarks/bench_drift.py [--runs 1000] [--seed 0] [--sigma 0.05 --sigma 0.1 ...]``.

Per noise sigma (normal, m, both axes): ``runs`` noise-only sequences of the baseline and 500 throws
(false alarm: any alarm in the first 100, or in all 500: about the throws of an hour's soak), ``runs`` sequences whose downrange mean moves by one sigma right
after the baseline, and ``runs`` where it moves after 100 more in-control throws (found: an alarm
within 30 throws of the shift, none before it). The same counts for the previous watch (mean and
spread of the first 30 throws taken as the truth, z = (e - mean) / spread, K = 0.5, H = 8) show
what the self-starting reference changed. Prints one row per sigma and watch with the host, commit
and CPU time. No assertions (tests/test_drift.py holds the bars).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from server.analysis import drift
from server.analysis.drift import Cusum


class TruthBaseline:
    """The previous watch's CUSUM: the first BASELINE_THROWS throws' mean and spread (spread at least
    SIGMA_FLOOR_M) taken as the truth, K = 0.5, H = 8 (Page 1954). Same ``update`` signature as
    :class:`Cusum`, returns True on an alarm."""

    def __init__(self):
        self.base: list = []
        self.hi, self.lo = np.zeros(2), np.zeros(2)
        self.mu = self.sigma = None

    def update(self, throw_id: str, e: np.ndarray) -> bool:
        if self.mu is None:
            self.base.append(e)
            if len(self.base) == drift.BASELINE_THROWS:
                b = np.array(self.base)
                self.mu, self.sigma = b.mean(axis=0), np.maximum(b.std(axis=0, ddof=1), drift.SIGMA_FLOOR_M)
            return False
        z = (e - self.mu) / self.sigma
        self.hi, self.lo = np.maximum(0.0, self.hi + z - 0.5), np.maximum(0.0, self.lo - z - 0.5)
        return bool(max(self.hi.max(), self.lo.max()) > 8.0)


def first_alarm(make, errors: np.ndarray) -> int | None:
    """Index of the first throw that alarms (None: none). errors: (N, 2), m."""
    c = make()
    for i, e in enumerate(errors):
        if c.update(f"t{i}", e):
            return i
    return None


def rates(make, sigma: float, runs: int, seed: int) -> dict:
    """False-alarm and detection shares (module doc) of one watch at one noise sigma (m)."""
    rng = np.random.default_rng(seed)
    n0 = drift.BASELINE_THROWS
    first = [first_alarm(make, rng.normal(0, sigma, (n0 + 500, 2))) for _ in range(runs)]
    out = {"false_alarm_100": float(np.mean([i is not None and i < n0 + 100 for i in first])),
           "false_alarm_500": float(np.mean([i is not None for i in first]))}
    for name, at in (("found_30_at_baseline", n0), ("found_30_after_100", n0 + 100)):
        found = []
        for _ in range(runs):
            e = rng.normal(0, sigma, (at + 30, 2))
            e[at:, 0] += sigma
            i = first_alarm(make, e)
            found.append(i is not None and at <= i < at + 30)
        out[name] = float(np.mean(found))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sigma", type=float, action="append")
    a = ap.parse_args()
    from sim_twin.provenance import short_commit

    commit = short_commit() or "unknown"
    print(f"host {platform.node()} commit {commit} runs {a.runs} seed {a.seed} K {drift.K} H {drift.H}")
    for sigma in a.sigma or [0.05, 0.1]:
        for name, make in (("self-starting", Cusum), ("truth-baseline", TruthBaseline)):
            t = time.process_time()
            r = rates(make, sigma, a.runs, a.seed)
            print(f"sigma {sigma:.3f} m  {name:15s} false alarm in 100 throws {r['false_alarm_100']:.3f}, in 500 {r['false_alarm_500']:.3f}  "
                  f"1-sigma found in 30: at baseline {r['found_30_at_baseline']:.3f}, after 100 {r['found_30_after_100']:.3f}  "
                  f"cpu {time.process_time() - t:.0f} s", flush=True)


if __name__ == "__main__":
    main()
