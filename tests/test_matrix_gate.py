"""Site-matrix gate: seeds in order, a miss ends a candidate, the first candidate meeting every bar
on every seed stops the gate; its state survives a restart."""

from __future__ import annotations

import json
import sys

from sim_twin.training.matrix_gate import MatrixGate


class FakeGate(MatrixGate):
    """Writes a one-cell matrix report instead of running the site matrix: iterations in
    ``passing`` meet the bar, others miss it."""

    passing: set[int] = set()

    def command(self, onnx, seed, out):
        it = int(onnx.rsplit("_", 1)[1].split(".")[0])
        ok = it in self.passing
        rep = {"pass": ok, "profiles": [{"name": "nominal", "targets": [{"target_m": 10.0, "bars": {"success": True, "accuracy": ok}}]}]}
        return [sys.executable, "-c", f"import json; open({out!r}, 'w').write(json.dumps({rep!r}))"]


def _run(gate, it):
    assert gate.submit(it, f"cand/checkpoint_{it}.onnx", train_wall_s=60.0 * it)
    assert not gate.submit(it + 1, f"cand/checkpoint_{it + 1}.onnx", 0.0)  # busy: one candidate at a time
    return gate.wait(60)


def test_gate_runs_seeds_in_order_and_stops_at_first_pass(tmp_path):
    FakeGate.passing = {3}
    gate = FakeGate(tmp_path, "2d", seeds=[0, 1], workers=1, clock=lambda: 1.0)
    assert _run(gate, 2) is None  # missed on seed 0: seed 1 is not run
    assert [(r.iteration, r.seed, r.passed, r.missing_cells) for r in gate.results] == [(2, 0, False, 1)]
    assert gate.results[0].misses == ["nominal@10: accuracy"]
    passed = _run(gate, 3)
    assert passed["iteration"] == 3 and passed["train_wall_s"] == 180.0
    assert [(r.iteration, r.seed, r.passed) for r in gate.results[1:]] == [(3, 0, True), (3, 1, True)]
    assert (tmp_path / "site_matrix_2d_it3_seed1.json").exists()
    assert not gate.submit(4, "cand/checkpoint_4.onnx", 0.0)  # passed: nothing more to judge
    again = FakeGate(tmp_path, "2d", seeds=[0, 1], workers=1)
    assert again.passed["iteration"] == 3 and len(again.results) == 3
    assert json.loads((tmp_path / "matrix_gate.json").read_text())["passed"]["iteration"] == 3


def test_gate_reports_a_crashed_matrix_and_goes_on(tmp_path):
    class Crashing(MatrixGate):
        def command(self, onnx, seed, out):
            return [sys.executable, "-c", "raise SystemExit(3)"]

    gate = Crashing(tmp_path, "2d", seeds=[0], workers=1)
    assert gate.submit(1, "x.onnx", 0.0)
    assert gate.wait(60) is None and not gate.busy and gate.results == []
    assert gate.submit(2, "y.onnx", 0.0)  # idle again: the next candidate starts
    gate.stop()


def test_the_matrix_runs_at_a_lower_priority_than_the_training(tmp_path):
    """The matrix process (and the pool it starts) runs GATE_NICENESS below the training process,
    which keeps the cores it launches its GPU work from."""
    import os

    from sim_twin.training.matrix_gate import GATE_NICENESS

    seen = tmp_path / "niceness"

    class Probe(FakeGate):
        def command(self, onnx, seed, out):
            rep = {"pass": True, "profiles": []}
            return [sys.executable, "-c", f"import json, os, time; time.sleep(0.5); open({str(seen)!r}, 'w').write(str(os.nice(0))); "
                                          f"open({out!r}, 'w').write(json.dumps({rep!r}))"]

    gate = Probe(tmp_path, "2d", seeds=[0], workers=1)
    assert gate.submit(1, "cand/checkpoint_1.onnx", 0.0)
    gate.wait(60)
    assert int(seen.read_text()) == min(19, os.nice(0) + GATE_NICENESS)


def test_gate_judges_on_after_a_pass_for_a_run_past_the_bars(tmp_path):
    """judge_after_pass (slinger train --no-stop-at-bars): newer candidates are judged after the
    first pass; ``passes`` lists every candidate that passed and survives a restart, ``passed``
    stays the first."""
    FakeGate.passing = {3, 5}
    gate = FakeGate(tmp_path, "2d", seeds=[0], workers=1, clock=lambda: 1.0, judge_after_pass=True)
    assert _run(gate, 3)["iteration"] == 3
    assert _run(gate, 4)["iteration"] == 3  # judged (and missed) after the pass
    _run(gate, 5)
    assert [p["iteration"] for p in gate.passes] == [3, 5] and gate.passed["iteration"] == 3
    assert [(r.iteration, r.passed) for r in gate.results] == [(3, True), (4, False), (5, True)]
    again = FakeGate(tmp_path, "2d", seeds=[0], workers=1, judge_after_pass=True)
    assert [p["iteration"] for p in again.passes] == [3, 5]


def test_a_watched_gate_records_each_verdict_when_its_matrix_ends(tmp_path):
    """watch(): the verdict of every seed is on disk when its matrix ends, with no poll() from the
    training (whose machine may be taken away before its next checkpoint), and the next seed starts
    on its own; stop() ends the thread."""
    import time

    FakeGate.passing = {7}
    gate = FakeGate(tmp_path, "2d", seeds=[0, 1], workers=1, clock=lambda: 42.0)
    gate.watch(interval_s=0.05)
    assert gate.submit(7, "cand/checkpoint_7.onnx", train_wall_s=30.0)
    deadline = time.time() + 60
    while gate.busy and time.time() < deadline:
        time.sleep(0.05)
    state = json.loads((tmp_path / "matrix_gate.json").read_text())
    assert [(r["seed"], r["passed"], r["verdict_wall_s"]) for r in state["results"]] == [(0, True, 42.0), (1, True, 42.0)]
    assert state["passed"]["iteration"] == 7 and gate.passed["iteration"] == 7
    gate.stop()
    assert gate._watcher is None


def test_an_unreadable_matrix_report_ends_its_candidate_without_a_verdict(tmp_path):
    """A matrix process that exits 0 but leaves a report that is not JSON, or JSON without the
    matrix's keys, is logged as failed and leaves no verdict; the gate is idle again."""
    for body in ("not json", '{"profiles": []}', '{"pass": true, "profiles": [{"targets": 3}]}'):
        class Garbled(MatrixGate):
            def command(self, onnx, seed, out, body=body):
                return [sys.executable, "-c", f"open({out!r}, 'w').write({body!r})"]

        gate = Garbled(tmp_path, "2d", seeds=[0], workers=1)
        assert gate.submit(1, "x.onnx", 0.0)
        assert gate.wait(60) is None and not gate.busy and gate.results == []
        assert gate.submit(2, "y.onnx", 0.0)
        gate.stop()


class SlowSecondSeed(FakeGate):
    """Seed 0's matrix ends at once; seed 1's runs until stopped (a machine taken away mid-matrix)."""

    def command(self, onnx, seed, out):
        if seed == self.seeds[1]:
            return [sys.executable, "-c", "import time; time.sleep(600)"]
        return super().command(onnx, seed, out)


def test_a_resumed_run_judges_the_candidate_under_test_again_from_its_seed(tmp_path):
    """The candidate under test is in matrix_gate.json with the seed it reached; a gate built on that
    state (the resumed run) judges it again from that seed, the seed it met staying met, and its
    verdict counts with the checkpoint's own training wall time."""
    import time

    FakeGate.passing = {5}
    onnx = tmp_path / "cand" / "checkpoint_5.onnx"
    onnx.parent.mkdir()
    for suffix in (".onnx", ".json", ".pt"):  # the candidate's files: policy, manifest, checkpoint
        onnx.with_suffix(suffix).write_text("policy")
    gate = SlowSecondSeed(tmp_path, "2d", seeds=[0, 1], workers=1, clock=lambda: 700.0)
    assert gate.submit(5, str(onnx), train_wall_s=645.0)
    deadline = time.time() + 60
    while not gate.results and time.time() < deadline:
        gate.poll()
        time.sleep(0.05)
    state = json.loads((tmp_path / "matrix_gate.json").read_text())
    assert state["pending"] == {"iteration": 5, "onnx": str(onnx), "train_wall_s": 645.0, "seed_index": 1}
    gate.stop()  # the machine goes away while seed 1's matrix runs

    resumed = FakeGate(tmp_path, "2d", seeds=[0, 1], workers=1, clock=lambda: 900.0, judge_after_pass=True)
    assert resumed.resume_pending()
    assert not resumed.resume_pending()  # once
    passed = resumed.wait(60)
    assert [(r.iteration, r.seed, r.passed) for r in resumed.results] == [(5, 0, True), (5, 1, True)]
    assert passed["iteration"] == 5 and passed["train_wall_s"] == 645.0 and passed["verdict_wall_s"] == 900.0
    assert json.loads((tmp_path / "matrix_gate.json").read_text())["pending"] is None


def test_a_finished_or_missing_candidate_is_not_judged_again(tmp_path):
    """After the last verdict of a candidate the state names none under test; a pending candidate
    whose ONNX file did not come along with the state is dropped, and the gate takes new ones."""
    FakeGate.passing = set()
    gate = FakeGate(tmp_path, "2d", seeds=[0, 1], workers=1)
    _run(gate, 2)
    assert json.loads((tmp_path / "matrix_gate.json").read_text())["pending"] is None
    assert not FakeGate(tmp_path, "2d", seeds=[0, 1], workers=1).resume_pending()

    state = json.loads((tmp_path / "matrix_gate.json").read_text())
    state["pending"] = {"iteration": 9, "onnx": str(tmp_path / "gone.onnx"), "train_wall_s": 1.0, "seed_index": 1}
    (tmp_path / "matrix_gate.json").write_text(json.dumps(state))
    resumed = FakeGate(tmp_path, "2d", seeds=[0, 1], workers=1)
    assert not resumed.resume_pending() and not resumed.busy
    assert resumed.submit(10, "cand/checkpoint_10.onnx", 0.0)
    resumed.stop()


class CopyingGate(MatrixGate):
    """Judges committed site matrices: iteration i's matrix on every seed is a copy of ``sources[i]``
    (with its seed set to the gate's), so the comparison with the deployed policy runs on real throws."""

    sources: dict[int, str] = {}

    def command(self, onnx, seed, out):
        src = self.sources[int(onnx.rsplit("_", 1)[1].split(".")[0])]
        return [sys.executable, "-c", f"import json; r = json.load(open({src!r})); r['seed'] = {seed}; json.dump(r, open({out!r}, 'w'))"]


def test_a_run_past_the_bars_exports_the_pass_worse_than_the_deployed_on_the_fewest_cells(tmp_path):
    """With compare_with every pass is paired-tested against the deployed policy on the gate's seeds:
    the deployed policy's own matrix is worse on no cell, throw2d-scratch-n1's iteration 3075 (seed 0)
    on two (friction x3 9.5-10 m); choose_pass takes the fewest, the newest among equals."""
    from pathlib import Path

    from sim_twin.training.matrix_gate import choose_pass

    root = Path(__file__).resolve().parents[1]
    deployed = root / "reports" / "site_matrix_2d.json"
    n1 = root / "policies" / "training" / "throw2d-scratch-n1" / "matrices" / "site_matrix_2d_it3075.json"
    CopyingGate.sources = {1: str(deployed), 2: str(n1), 3: str(deployed), 4: str(n1)}
    gate = CopyingGate(tmp_path, "2d", seeds=[0], workers=1, judge_after_pass=True, compare_with=[deployed])
    for it in (1, 2):
        _run(gate, it)
    assert [(p["iteration"], p["worse_than_deployed"]) for p in gate.passes] == [(1, 0), (2, 2)]
    assert gate.passes[1]["worse_cells"] == ["friction_x3@9.5", "friction_x3@10"]
    assert choose_pass(gate.passes)["iteration"] == 1  # not the newest: it is worse on two cells
    _run(gate, 3)
    assert choose_pass(gate.passes)["iteration"] == 3  # as few worse cells, newer
    again = CopyingGate(tmp_path, "2d", seeds=[0], workers=1, judge_after_pass=True)  # the counts survive a restart
    assert [p["worse_than_deployed"] for p in again.passes] == [0, 2, 0]


def test_choose_pass_without_comparisons_is_the_newest():
    from sim_twin.training.matrix_gate import choose_pass

    assert choose_pass([]) is None
    assert choose_pass([{"iteration": 1}, {"iteration": 2}])["iteration"] == 2
    # a pass whose comparison failed ranks after every compared one
    assert choose_pass([{"iteration": 1, "worse_than_deployed": 3}, {"iteration": 2, "worse_than_deployed": None}])["iteration"] == 1


def test_deployed_matrices_that_do_not_fit_the_gate_are_refused_before_training(tmp_path):
    import pytest
    from pathlib import Path

    reports = Path(__file__).resolve().parents[1] / "reports"
    with pytest.raises(ValueError, match="2 gate seeds"):
        MatrixGate(tmp_path, "2d", seeds=[0, 1], compare_with=[reports / "site_matrix_2d.json"])
    with pytest.raises(ValueError, match="not 2d on gate seed 0"):
        MatrixGate(tmp_path, "2d", seeds=[0], compare_with=[reports / "site_matrix_2d_seed1.json"])
    with pytest.raises(ValueError, match="not 3d"):
        MatrixGate(tmp_path, "3d", seeds=[0], compare_with=[reports / "site_matrix_2d.json"])
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="not a site-matrix report"):
        MatrixGate(tmp_path, "2d", seeds=[0], compare_with=[tmp_path / "bad.json"])
    with pytest.raises(OSError):
        MatrixGate(tmp_path, "2d", seeds=[0], compare_with=[tmp_path / "missing.json"])


def test_finish_chooses_among_the_passes_whose_checkpoint_is_here(tmp_path):
    """A run resumed from a state that lacks a pass's checkpoint (throw2d-scratch-n1's 3075) cannot
    export that pass: exportable_passes leaves it out, so finish chooses among the rest."""
    from sim_twin.training.matrix_gate import choose_pass

    FakeGate.passing = {1, 2}
    cand = tmp_path / "candidates"
    cand.mkdir()
    gate = FakeGate(tmp_path / "matrices", "2d", seeds=[0], workers=1, judge_after_pass=True)
    for it in (1, 2):
        assert gate.submit(it, str(cand / f"checkpoint_{it}.onnx"), train_wall_s=60.0 * it)
        gate.wait(60)
    assert [p["iteration"] for p in gate.passes] == [1, 2] and gate.exportable_passes() == []
    (cand / "checkpoint_1.pt").write_bytes(b"x")
    assert [p["iteration"] for p in gate.exportable_passes()] == [1]
    assert choose_pass(gate.exportable_passes())["iteration"] == 1  # not the newest (2): its checkpoint is gone


def test_a_run_resumed_with_a_comparison_it_did_not_have_ranks_its_earlier_passes_too(tmp_path):
    """throw2d-scratch-o0 stopped at the bars without --gate-compare-with and resumes past them with it:
    the passes in its saved state are compared when the gate loads it (from the matrices beside it, their
    recorded paths relative to another working directory), so choose_pass can still export the earlier
    pass that is worse on fewer cells than a newer one."""
    import shutil
    from pathlib import Path

    from sim_twin.training.matrix_gate import choose_pass

    root = Path(__file__).resolve().parents[1]
    deployed = root / "reports" / "site_matrix_2d.json"
    n1 = root / "policies" / "training" / "throw2d-scratch-n1" / "matrices" / "site_matrix_2d_it3075.json"
    CopyingGate.sources = {1: str(deployed), 2: str(n1)}
    first = CopyingGate(tmp_path, "2d", seeds=[0], workers=1, judge_after_pass=True)  # no comparison
    _run(first, 1)
    assert [p["iteration"] for p in first.passes] == [1] and "worse_than_deployed" not in first.passes[0]
    moved = tmp_path / "elsewhere"  # the run's directory as another machine unpacks it
    shutil.copytree(tmp_path, moved, ignore=shutil.ignore_patterns("elsewhere"))
    state = json.loads((moved / "matrix_gate.json").read_text())
    for r in state["results"]:
        r["matrix_path"] = "runs/gone/matrices/" + Path(r["matrix_path"]).name
    (moved / "matrix_gate.json").write_text(json.dumps(state))
    resumed = CopyingGate(moved, "2d", seeds=[0], workers=1, judge_after_pass=True, compare_with=[deployed])
    assert [(p["iteration"], p["worse_than_deployed"]) for p in resumed.passes] == [(1, 0)]
    _run(resumed, 2)
    assert [(p["iteration"], p["worse_than_deployed"]) for p in resumed.passes] == [(1, 0), (2, 2)]
    assert choose_pass(resumed.passes)["iteration"] == 1
