"""The far-target throw style of a 2D from-scratch run (tests/benchmarks/training_throw_style.py):
read from the last seed-0 gate matrix by iteration 250, and, on the committed runs, the style
separates the runs that met every bar from those that stalled (docs/training.md "Why a run stalls")."""

import json
import subprocess
from pathlib import Path

import pytest

from tests.benchmarks.training_throw_style import (
    LONG_STYLE_S,
    RunSource,
    duration_spread,
    far_throw,
    kept_rows,
    run_style,
    spread_by_duration,
    style_of,
    swing_switch,
)

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "policies" / "training"
ARCHIVED_AT = "903fcd522fe5a44b5c6daa7d89c5afda847bee06"
"""The last commit with the archived runs -ab and -ad (policies/training/ARCHIVE.md)."""
NO_LIMITS_AT = "b334ef6655c3b3201352094f53724193351729e4"
"""The last commit with the archived run -aj (policies/training/ARCHIVE.md)."""
PROBES_AT = "27dac7e0990367acc838115f9160f0dc789184af"
"""The last commit with the archived run -ak (policies/training/ARCHIVE.md)."""
COMMITTED_65536 = ["throw2d-scratch-u", "throw2d-scratch-aa", f"{ARCHIVED_AT}:policies/training/throw2d-scratch-ab",
                   "throw2d-scratch-ac", f"{ARCHIVED_AT}:policies/training/throw2d-scratch-ad",
                   "throw2d-scratch-ai", f"{NO_LIMITS_AT}:policies/training/throw2d-scratch-aj",
                   f"{PROBES_AT}:policies/training/throw2d-scratch-ak"]
"""The committed 2D from-scratch runs with 65536 environments and γ 0.998 or 0.999 (-ai and -aj on the
training model without joint-limit constraints, -ak with the bfloat16 update): in the tree, or ``REV:PATH`` for those kept in git
history only."""


def _matrix(duration_s: float, sigma_m: float = 0.1) -> dict:
    cell = {"target_m": 10.0, "mean_duration_s": duration_s, "sigma_downrange_m": sigma_m, "bias_m": 0.02}
    return {"policy_version": "t", "profiles": [{"name": "windy_site", "targets": [dict(cell, mean_duration_s=9.0)]},
                                                 {"name": "nominal", "targets": [cell]}]}


def _run(tmp_path: Path, durations: dict[int, float], results: list[dict], passes: list[dict]) -> Path:
    run = tmp_path / "throw2d-scratch-t"
    (run / "matrices").mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"num_envs": 64, "runner": {"algorithm": {"gamma": 0.999}}, "training": {"seed": 7}}))
    for it, d in durations.items():
        (run / "matrices" / f"site_matrix_2d_it{it}.json").write_text(json.dumps(_matrix(d)))
    (run / "matrices" / "site_matrix_2d_it100_seed1.json").write_text(json.dumps(_matrix(1.0)))  # not seed 0: ignored
    gate = {"mode": "2d", "seeds": [0, 1], "results": results, "passes": passes, "passed": passes[0] if passes else None}
    (run / "matrices" / "matrix_gate.json").write_text(json.dumps(gate))
    return run


def _result(it: int, seed: int, missing: int) -> dict:
    return {"iteration": it, "seed": seed, "passed": missing == 0, "missing_cells": missing, "train_wall_s": it * 2.0}


def test_the_style_is_read_from_the_last_seed0_matrix_by_iteration_250(tmp_path):
    run = _run(tmp_path, {100: 4.0, 250: 3.1, 300: 4.2},
               [_result(100, 0, 5), _result(250, 0, 4), _result(300, 0, 0), _result(300, 1, 2)], [])
    row = run_style(RunSource(str(run)))
    assert (row["style_iteration"], row["far_duration_s"], row["style"]) == (250, 3.1, "short")
    assert (row["gamma"], row["num_envs"], row["training_seed"]) == (0.999, 64, 7)
    # not met: the last verdicts, seed by seed
    assert row["outcome"] == {"met": False, "last_iteration": 300, "last_train_wall_min": 10.0, "missing_cells": {"0": 0, "1": 2}}


def test_the_style_skips_a_matrix_whose_far_throws_did_not_land(tmp_path):
    """Where the last matrix by iteration 250 has no landed nominal 10 m throw (the run still held its
    far throws), the first later matrix where they landed sets the style, not an earlier one (from
    before the styles split)."""
    run = _run(tmp_path, {25: 2.0, 200: None, 275: None, 300: 3.3, 400: 4.0},
               [_result(i, 0, 9) for i in (25, 200, 275, 300, 400)], [])
    row = run_style(RunSource(str(run)))
    assert (row["style_iteration"], row["far_duration_s"], row["style"]) == (300, 3.3, "short")
    run = _run(tmp_path / "c", {100: None}, [_result(100, 0, 9)], [])
    with pytest.raises(ValueError, match="no seed-0 site matrix where a nominal 10 m throw landed"):
        run_style(RunSource(str(run)))


def test_a_run_that_met_the_bars_names_its_first_passing_checkpoint(tmp_path):
    passes = [{"iteration": 150, "train_wall_s": 270.0}, {"iteration": 300, "train_wall_s": 600.0}]
    run = _run(tmp_path, {150: 4.1}, [_result(150, 0, 0), _result(150, 1, 0)], passes)
    row = run_style(RunSource(str(run)))
    assert row["style"] == "long"
    assert row["outcome"] == {"met": True, "iteration": 150, "train_wall_min": 4.5}


def test_a_run_without_an_early_matrix_or_a_nominal_far_cell_is_refused(tmp_path):
    run = _run(tmp_path, {300: 4.0}, [_result(300, 0, 1)], [])
    with pytest.raises(FileNotFoundError, match="by iteration 250"):
        run_style(RunSource(str(run)))
    with pytest.raises(ValueError, match="no nominal cell at 10"):
        far_throw({"policy_version": "x", "profiles": [{"name": "nominal", "targets": []}]})
    with pytest.raises(FileNotFoundError, match="REV:PATH"):
        RunSource(str(tmp_path / "absent"))


def test_the_threshold_separates_the_two_styles():
    assert style_of(LONG_STYLE_S) == "long"
    assert style_of(LONG_STYLE_S - 0.01) == "short"


@pytest.mark.parametrize("name", COMMITTED_65536)
def test_on_the_committed_runs_the_long_style_is_the_one_that_met_the_bars(name):
    if ":" in name:
        rev = name.split(":", 1)[0]
        if subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", rev], capture_output=True).returncode:
            pytest.skip(f"{rev[:7]} is not in this clone's history (a shallow clone)")
        row = run_style(RunSource(name, repo=ROOT))
    else:
        row = run_style(RunSource(str(RUNS / name)))
    assert (row["style"] == "long") == row["outcome"]["met"], row


def test_term_split_says_whether_a_curve_column_separates_the_styles():
    from tests.benchmarks.training_throw_style import term_split

    rows = [{"style": "long"}, {"style": "long"}, {"style": "short"}]
    curves = [{100: {"a": 1.0, "b": 0.5}, 200: {"a": 2.0}},
              {100: {"a": 1.2, "b": float("nan")}, 200: {"a": 2.5}},
              {100: {"a": 3.0, "b": 0.4}, 200: {"a": 2.2}}]
    got = {(x["term"], x["iteration"]): x for x in term_split(rows, curves, terms=("a", "b"))}
    assert got["a", 100]["separates"] and got["a", 100]["long"] == [1.0, 1.2] and got["a", 100]["short"] == [3.0, 3.0]
    assert not got["a", 200]["separates"]  # 2.2 lies inside the long runs' 2.0-2.5
    assert got["b", 100]["runs"] == [1, 1]  # the NaN (no episode paid the term) is skipped
    assert ("b", 200) not in got  # no run logged it there


def test_kept_rows_keep_the_other_runs_of_a_report_made_the_same_way(tmp_path):
    report = tmp_path / "r.json"
    report.write_text(json.dumps({"envs": 128, "key": 7, "runs": [{"run": "throw2d-scratch-a"}, {"run": "throw2d-scratch-b"}]}))
    for name in ("throw2d-scratch-b", "throw2d-scratch-c"):
        (tmp_path / name).mkdir()
    kept = kept_rows(report, {"envs": 128, "key": 7}, [str(tmp_path / "throw2d-scratch-b"), str(tmp_path / "throw2d-scratch-c")], "runs")
    assert kept == [{"run": "throw2d-scratch-a"}]  # -b is played again now; -c was not in the report
    with pytest.raises(ValueError, match="envs 128 differs from this run's 256"):
        kept_rows(report, {"envs": 256, "key": 7}, [], "runs")
    with pytest.raises(ValueError, match="probe_key None differs"):  # a setting the report did not record
        kept_rows(report, {"envs": 128, "probe_key": 7}, [], "runs")


def _spread_run(tmp_path: Path, name: str, cells: dict[int, tuple[float | None, float, float]]) -> RunSource:
    """A run whose seed-0 matrices have the nominal 10 m cell (duration s, σ m, bias m) per iteration."""
    run = tmp_path / name
    (run / "matrices").mkdir(parents=True)
    for it, (dur, sigma, bias) in cells.items():
        cell = {"target_m": 10.0, "mean_duration_s": dur, "sigma_downrange_m": sigma, "bias_m": bias,
                "landed": 0 if dur is None else 100, "success_rate": 1.0}
        (run / "matrices" / f"site_matrix_2d_it{it}.json").write_text(json.dumps({"profiles": [{"name": "nominal", "targets": [cell]}]}))
    (run / "matrices" / "site_matrix_2d_it500_seed1.json").write_text("not read")  # not seed 0
    return RunSource(str(run))


def test_duration_spread_reads_the_span_and_judges_the_nominal_accuracy_bar(tmp_path):
    src = _spread_run(tmp_path, "throw2d-scratch-t", {250: (3.0, 0.2, 0.0), 300: (3.5, 0.12, 0.01), 400: (4.4, 0.06, 0.15),
                                                      500: (4.2, 0.05, -0.02), 600: (None, 0.0, 0.0), 1400: (4.5, 0.05, 0.0)})
    pts = duration_spread(src)
    assert [p["iteration"] for p in pts] == [300, 400, 500]  # 250 before the stage, 600 did not land, 1400 past the span
    assert [p["accuracy"] for p in pts] == [False, False, True]  # σ over the bar; bias over it; both within


def test_spread_by_duration_bins_the_matrices_and_counts_the_bars(tmp_path):
    pts = duration_spread(_spread_run(tmp_path, "a", {300: (3.5, 0.12, 0.0), 400: (3.7, 0.08, 0.0)}))
    pts += duration_spread(_spread_run(tmp_path, "b", {300: (4.1, 0.06, 0.12), 400: (4.7, 0.05, 0.0), 500: (4.0, 0.07, 0.0)}))
    bins = spread_by_duration(pts, edges=(3.6, 4.0))
    assert [(b["lo_s"], b["hi_s"], b["matrices"], b["runs"]) for b in bins] == [(None, 3.6, 1, 1), (3.6, 4.0, 1, 1), (4.0, None, 3, 1)]
    assert (bins[0]["sigma_share"], bins[1]["sigma_share"], bins[2]["sigma_share"]) == (0.0, 1.0, 1.0)
    assert bins[2]["accuracy_share"] == 0.67 and bins[2]["median_sigma_m"] == 0.06  # 4.1 s overshoots by 0.12 m
    assert spread_by_duration([], edges=(4.0,))[0] == {"lo_s": None, "hi_s": 4.0, "matrices": 0, "runs": 0,
                                                       "median_sigma_m": None, "sigma_share": None, "accuracy_share": None}


def _switch_run(tmp_path: Path, durations: dict[int, list[float | None]]) -> RunSource:
    """A run whose seed-0 matrices have nominal cells at 7.5-10 m (0.5 m apart) lasting ``durations`` [s]."""
    run = tmp_path / "throw2d-scratch-s"
    (run / "matrices").mkdir(parents=True)
    for it, ds in durations.items():
        cells = [{"target_m": 7.5 + 0.5 * i, "mean_duration_s": d} for i, d in enumerate(ds)]
        (run / "matrices" / f"site_matrix_2d_it{it}.json").write_text(json.dumps({"profiles": [{"name": "nominal", "targets": cells[::-1]}]}))
    return RunSource(str(run))


def test_swing_switch_is_the_nearest_target_thrown_on_a_later_swing_and_its_median(tmp_path):
    src = _switch_run(tmp_path, {200: [4.0] * 6, 300: [2.1, 2.2, 2.3, 3.3, 4.0, 4.5], 400: [2.1, 2.2, 2.3, 2.6, 3.0, 3.6],
                                 500: [2.0, 2.1, 2.2, 2.5, 2.9, 3.1], 600: [2.0, 2.1, 3.5, None, 4.0, 4.2]})
    sw = swing_switch(src)
    assert sw["per_matrix"] == {300: 9.0, 400: 10.0, 500: None, 600: 8.5}  # 200 before the stage; 500 all on the first swing
    assert sw["median_target_m"] == 9.0
    assert swing_switch(_switch_run(tmp_path / "b", {300: [2.0] * 6}))["median_target_m"] is None
