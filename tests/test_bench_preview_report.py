"""tests/benchmarks/bench_preview.py's report figures, in docs/results.md's layout."""

from tests.benchmarks.bench_preview import report_figures


def test_report_figures_name_the_case_and_judge_the_median():
    measures = [
        {"case": "preview_throw() x1", "policy": "", "processes": 1, "clock": "wall", "rollouts": 1, "median_s": 0.044, "max_s": 0.05, "n": 10, "bar_s": 0.3},
        {"case": "preview_throw() x1", "policy": "", "processes": 1, "clock": "wall", "rollouts": 200, "median_s": 1.6, "max_s": 1.9, "n": 10, "bar_s": 1.5},
        {"case": "preview_throw() x1 CPU", "policy": "", "processes": 1, "clock": "cpu", "rollouts": 200, "median_s": 1.1, "max_s": 1.2, "n": 10, "bar_s": 1.5},
        {"case": "lineage preview_throw() x2", "policy": "lineage", "processes": 2, "clock": "wall", "rollouts": 200, "median_s": 0.4, "max_s": 0.5, "n": 10, "bar_s": 1.5},
        {"case": "POST /api/previews", "policy": "", "processes": None, "clock": "wall", "rollouts": 1, "median_s": 0.1, "max_s": 0.2, "n": 10, "bar_s": 0.3},
    ]
    f = report_figures(measures)
    assert [x["what"] for x in f] == [
        "single-rollout preview in one process, median / max",
        "200-impact ellipse preview in one process, median / max",
        "lineage 200-impact ellipse preview with 2 Monte Carlo processes, median / max",
        "POST /api/previews, single-rollout preview, median / max",
    ]
    assert f[0]["value"] == "0.044 / 0.050" and f[0]["met"] is True and f[0]["bar"] == "median <= 0.3 s"
    assert f[1]["met"] is False
