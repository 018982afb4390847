"""The training-run report reads site matrices run after a training (tests/benchmarks/training_run_report.py):
iteration and seed from the file's name, training wall time from the run's curve.csv, and a clear
error for a name or an iteration it cannot place."""

import json
import shutil
from pathlib import Path

import pytest

from sim_twin.training.matrix_gate import summarise_matrix
from tests.benchmarks.training_run_report import after_run_row, train_wall_s

ROOT = Path(__file__).resolve().parents[1]
MATRIX = ROOT / "policies" / "training" / "throw2d-scratch-u" / "matrices" / "site_matrix_2d_it125.json"


def _run(tmp_path: Path) -> Path:
    run = tmp_path / "run"
    (run / "matrices").mkdir(parents=True)
    (run / "curve.csv").write_text("iteration,wall_s\n425.0,390.5\n450.0,412.25\n")
    return run


def test_a_later_matrix_takes_its_wall_time_from_the_curve_and_its_seed_from_the_name(tmp_path):
    run = _run(tmp_path)
    m = run / "matrices" / "site_matrix_2d_it450_seed1.json"
    shutil.copy(MATRIX, m)
    row = after_run_row(run, m, train_wall_s(run))
    n_miss, misses = summarise_matrix(json.loads(MATRIX.read_text()))
    assert (row["iteration"], row["seed"], row["train_wall_s"]) == (450, 1, 412.25)
    assert (row["missing_cells"], row["misses"], row["after_run"]) == (n_miss, misses, True)
    assert n_miss > 0 and row["passed"] is False


def test_seed_0_has_no_suffix(tmp_path):
    run = _run(tmp_path)
    m = run / "matrices" / "site_matrix_2d_it425.json"
    shutil.copy(MATRIX, m)
    assert after_run_row(run, m, train_wall_s(run))["seed"] == 0


@pytest.mark.parametrize("name", ["matrix_450.json", "site_matrix_2d_itX.json", "site_matrix_4d_it450.json"])
def test_a_name_it_cannot_read_is_refused(tmp_path, name):
    run = _run(tmp_path)
    m = run / "matrices" / name
    shutil.copy(MATRIX, m)
    with pytest.raises(ValueError, match="expected site_matrix"):
        after_run_row(run, m, train_wall_s(run))


def test_an_iteration_the_curve_lacks_is_refused(tmp_path):
    run = _run(tmp_path)
    m = run / "matrices" / "site_matrix_2d_it500.json"
    shutil.copy(MATRIX, m)
    with pytest.raises(ValueError, match="iteration 500 is not in"):
        after_run_row(run, m, train_wall_s(run))


def test_the_report_reads_the_names_the_gate_writes():
    from sim_twin.training.matrix_gate import matrix_file_name, parse_matrix_file_name

    for mode, it, seed in [("2d", 25, 0), ("3d", 1253, 1), ("2d", 701, 2)]:
        assert parse_matrix_file_name(matrix_file_name(mode, it, seed)) == (it, seed)


def test_the_curve_summary_spaces_its_rows_keeps_the_last_and_counts_time_outs(tmp_path):
    from tests.benchmarks.training_run_report import curve_summary, curve_table

    run = tmp_path / "run"
    run.mkdir()
    lines = ["iteration,wall_s,mean_reward,mean_episode_length,landed_per_done,failed_per_done,impact_err_m,action_std,"
             "control_steps_per_s"]
    lines += [f"{25 * (k + 1)},{60.0 * (k + 1)},{k},{40 + k},0.9,0.02,0.5,0.3,600000" for k in range(30)]
    (run / "curve.csv").write_text("\n".join(lines) + "\n")
    rows = curve_summary(run, rows=4)
    assert [r["iteration"] for r in rows] == [25, 275, 500, 750]
    assert rows[-1]["wall_min"] == 30.0 and rows[0]["timeouts_per_done"] == pytest.approx(0.08)
    assert len(curve_table(rows)) == 2 + 4 and "| 750 | 30.0 | 90.0% | 2.00% | 8.00% |" in curve_table(rows)[-1]
    assert curve_table(rows)[-1].endswith("| 0.300 | 0.60 |")
    assert [r["iteration"] for r in curve_summary(run, rows=40)] == [25 * (k + 1) for k in range(30)]  # fewer rows: all
    assert curve_summary(tmp_path / "no-run") == []


def test_a_gate_matrix_without_its_verdict_is_marked_as_such_and_not_as_after_the_run(tmp_path):
    from tests.benchmarks.training_run_report import UNRECORDED

    run = _run(tmp_path)
    m = run / "matrices" / "site_matrix_2d_it450.json"
    shutil.copy(MATRIX, m)
    row = after_run_row(run, m, train_wall_s(run), note=UNRECORDED)
    assert (row["iteration"], row["train_wall_s"], row["after_run"], row["note"]) == (450, 412.25, False, UNRECORDED)
    assert after_run_row(run, m, train_wall_s(run))["note"] == "after the run"


def test_the_report_names_the_exported_policy_by_its_model_cards_onnx_hash(tmp_path):
    from tests.benchmarks.training_run_report import exported_policy_sha256

    run = _run(tmp_path)
    assert exported_policy_sha256(run) is None  # no checkpoint met the bars: nothing exported
    card = ROOT / "policies" / "training" / "throw2d-scratch-aa" / "throw2d.card.json"
    shutil.copy(card, run / "throw2d.card.json")
    assert exported_policy_sha256(run) == json.loads(card.read_text())["onnx_sha256"]
    (run / "throw2d.card.json").write_text("{}")
    with pytest.raises(KeyError):
        exported_policy_sha256(run)


def test_several_runs_make_one_report_with_each_runs_wall_time_style_and_command(tmp_path, monkeypatch):
    """Two kept runs of one recipe: one JSON with a row per run, the table names each run's
    training seed, far-target style and outcome, and each run's command has its own seed."""
    import sys

    from tests.benchmarks import training_run_report

    runs = [ROOT / "policies" / "training" / n for n in ("throw2d-scratch-ax", "throw2d-scratch-ay")]
    out = tmp_path / "both"
    monkeypatch.setattr(sys, "argv", ["training_run_report", *map(str, runs), "--out", str(out), "--title", "two seeds",
                                      "--command", "slinger train --seed {seed} --log-dir runs/{name}"])
    training_run_report.main()
    rep = json.loads(out.with_suffix(".json").read_text())
    assert [Path(r["run"]).name for r in rep["runs"]] == ["throw2d-scratch-ax", "throw2d-scratch-ay"]
    ax, ay = rep["runs"]
    assert ax["command"] == "slinger train --seed 25 --log-dir runs/throw2d-scratch-ax"
    assert ax["bars_wall_min"] == round(ax["passed"]["train_wall_s"] / 60, 1) and ay["passed"] is None
    assert (ax["far_style"]["style"], ay["far_style"]["style"]) == ("long", "short")
    table = out.with_suffix(".md").read_text()
    assert "| throw2d-scratch-ay | 26 | short" in table and "| no | not met |" in table
    import csv
    import statistics

    for r, run in zip(rep["runs"], runs, strict=True):  # the median throughput, read from the curve on its own
        rows = list(csv.DictReader((run / "curve.csv").open()))
        want = statistics.median(float(x["control_steps_per_s"]) for x in rows if float(x["iteration"]) >= 50)
        assert r["median_control_steps_per_s"] == pytest.approx(want)
        assert f"| {want / 1e6:.2f} |" in table
    assert out.with_suffix(".png").stat().st_size > 0


def test_a_command_per_run_or_a_clear_error(tmp_path, monkeypatch):
    import sys

    from tests.benchmarks import training_run_report

    runs = [str(ROOT / "policies" / "training" / n) for n in ("throw2d-scratch-ax", "throw2d-scratch-ay")]
    out = tmp_path / "r"
    monkeypatch.setattr(sys, "argv", ["r", *runs, "--out", str(out), "--command", "first", "--command", "second"])
    training_run_report.main()
    assert [r["command"] for r in json.loads(out.with_suffix(".json").read_text())["runs"]] == ["first", "second"]
    monkeypatch.setattr(sys, "argv", ["r", *runs, runs[0], "--out", str(tmp_path / "bad"), "--command", "a", "--command", "b"])
    with pytest.raises(SystemExit):
        training_run_report.main()
    assert not (tmp_path / "bad.json").exists()


def test_a_run_given_twice_is_refused_before_anything_is_written(tmp_path, monkeypatch, capsys):
    """A run listed twice would get two table rows and two sections (a re-run once did: -n3 three times)."""
    import sys

    from tests.benchmarks import training_run_report

    run = ROOT / "policies" / "training" / "throw2d-scratch-ax"
    other = ROOT / "policies" / "training" / "throw2d-scratch-ay"
    monkeypatch.setattr(sys, "argv", ["r", str(run), str(other), str(run / ".." / run.name), "--out", str(tmp_path / "dup")])
    with pytest.raises(SystemExit):
        training_run_report.main()
    err = capsys.readouterr().err
    assert "given more than once" in err and "throw2d-scratch-ax" in err and "throw2d-scratch-ay" not in err
    assert not (tmp_path / "dup.json").exists()


def test_the_far_target_bias_is_the_farthest_targets_and_its_mean_counts_only_late_first_seed_matrices(tmp_path):
    """far_bias reads the nominal and sensor-latency bias at the farthest target; the run's mean takes
    the first gate seed's matrices from FAR_BIAS_FROM on, not earlier ones or other seeds'."""
    from tests.benchmarks.training_run_report import FAR_BIAS_FROM, far_bias, run_report

    rep = json.loads(MATRIX.read_text())
    nominal = next(p for p in rep["profiles"] if p["name"] == "nominal")
    far = max(nominal["targets"], key=lambda t: t["target_m"])
    assert far["target_m"] == 10.0 and far_bias(rep)["nominal"] == round(far["bias_m"], 3)
    assert far_bias({**rep, "mode": "3d"}) == {}

    run = tmp_path / "run"
    (run / "matrices").mkdir(parents=True)
    results = []
    for it, seed, shift in [(FAR_BIAS_FROM - 25, 0, 1.0), (FAR_BIAS_FROM, 0, 0.1), (FAR_BIAS_FROM + 25, 0, 0.3), (FAR_BIAS_FROM, 1, 5.0)]:
        m = json.loads(MATRIX.read_text())
        for p in m["profiles"]:
            for t in p["targets"]:
                t["bias_m"] = shift
        name = f"site_matrix_2d_it{it}" + (f"_seed{seed}" if seed else "") + ".json"
        (run / "matrices" / name).write_text(json.dumps(m))
        results.append({"iteration": it, "seed": seed, "passed": False, "missing_cells": 1, "train_wall_s": 60.0 * it / 50,
                        "misses": ["x"], "matrix_path": f"runs/run/matrices/{name}"})
    (run / "matrices" / "matrix_gate.json").write_text(json.dumps({"seeds": [0, 1], "passed": None, "results": results}))
    out, md = run_report(run, "gpu", "cmd", [], [])
    assert out["mean_far_bias_m"] == {"nominal": 0.2, "sensor_latency": 0.2}
    assert out["sd_far_bias_m"] == {"nominal": 0.141, "sensor_latency": 0.141}  # 0.1 and 0.3: sample standard deviation
    assert [r["far_bias_m"]["nominal"] for r in out["results"]] == [1.0, 0.1, 5.0, 0.3]
    assert any(line.startswith(f"Mean far-target bias over the seed-0 matrices from iteration {FAR_BIAS_FROM} on (2)") for line in md)


def test_the_first_pass_counts_a_gate_seed_judged_after_the_run_but_not_a_held_out_seed():
    """throw2d-scratch-g1: the gate passed iteration 575 on seed 0 and the machine went back while it ran
    seed 1, which an after-run matrix met; the run met the bars there (10.8 min), not at the gate's
    first full pass (775). A held-out seed's matrix alone does not make a pass, nor does a failed seed."""
    from tests.benchmarks.training_run_report import first_pass, first_pass_text

    def row(it, seed, ok, after=False):
        return {"iteration": it, "seed": seed, "passed": ok, "after_run": after, "train_wall_s": it * 1.0, "note": None}

    rows = [row(450, 0, True), row(450, 2, True, after=True), row(575, 0, True), row(575, 1, True, after=True),
            row(775, 0, True), row(775, 1, True)]
    first = first_pass(rows, [0, 1])
    assert first == {"iteration": 575, "train_wall_s": 575.0, "after_run_seeds": [1]}
    assert first_pass_text(first) == "iteration 575 (seed 1 after the run)"
    assert first_pass(rows[4:], [0, 1])["after_run_seeds"] == [] and first_pass_text(first_pass(rows[4:], [0, 1])) == "iteration 775"
    assert first_pass([row(575, 0, True), row(575, 1, False)], [0, 1]) is None


def test_the_committed_g1_run_reports_its_bars_at_iteration_575():
    from tests.benchmarks.training_run_report import run_report

    run = ROOT / "policies" / "training" / "throw2d-scratch-g1"
    out, md = run_report(run, "gpu", "cmd", [run / "matrices" / "site_matrix_2d_it575_seed1.json"], [])
    assert out["passed"]["iteration"] == 775  # the gate's own verdict stays as it recorded it
    assert out["first_pass"]["iteration"] == 575 and out["bars_wall_min"] == 10.8
    assert "**yes, iteration 575 (seed 1 after the run) (10.8 min)**" in md[0]


def test_the_summary_keeps_held_out_seeds_apart_from_the_last_gate_verdict(tmp_path, monkeypatch):
    """-g2: the gate's last verdict is iteration 1075 on seed 1 (met); the after-run matrix of held-out
    seed 2 is its own column, naming the cell it missed, not the run's last verdict."""
    import sys

    from tests.benchmarks import training_run_report

    run = ROOT / "policies" / "training" / "throw2d-scratch-g2"
    out = tmp_path / "g2"
    monkeypatch.setattr(sys, "argv", ["training_run_report", str(run), str(ROOT / "policies" / "training" / "throw2d-scratch-g3"),
                                      "--after-run", str(run / "matrices" / "site_matrix_2d_it1075_seed2.json"), "--out", str(out)])
    training_run_report.main()
    row = next(line for line in out.with_suffix(".md").read_text().splitlines() if line.startswith("| throw2d-scratch-g2 |"))
    assert "| iteration 1075, seed 1: 0 cells missing | iteration 1075, seed 2: worn_gripper@8.5: success |" in row
