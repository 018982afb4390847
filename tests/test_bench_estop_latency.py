"""tests/benchmarks/bench_estop_latency.py's report: built from a run's clicks, in the committed layout."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.benchmarks.bench_estop_latency import report

ROOT = Path(__file__).resolve().parents[1]


def test_the_report_of_the_committed_clicks_gives_the_committed_figures():
    committed = json.loads((ROOT / "reports" / "estop_latency.json").read_text())
    clicks = committed["clicks"]
    run = {"neutral_s": [c["neutral_ms"] / 1e3 for c in clicks], "reply_s": [c["reply_ms"] / 1e3 for c in clicks],
           "refusals": [], "orphans": [], "not_moving": 0}
    r = report(run, burners=2)
    assert r["clicks"] == clicks
    assert r["figures"] == committed["figures"]


def test_a_slow_stop_fails_the_bar_and_no_click_is_an_error():
    run = {"neutral_s": [0.01] * 98 + [0.25, 0.3], "reply_s": [0.05] * 100, "refusals": ["busy"], "orphans": [], "not_moving": 3}
    r = report(run, burners=2)
    assert r["figures"][0]["met"] is False and r["figures"][0]["value"].endswith("/ 300.0")
    assert "3 clicks discarded, 1 throws refused" in r["figures"][1]["conditions"]
    with pytest.raises(ValueError, match="no click"):
        report({"neutral_s": [], "reply_s": [], "refusals": [], "orphans": [], "not_moving": 0}, burners=2)
