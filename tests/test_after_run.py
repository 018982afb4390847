"""tests/benchmarks/after_run.py: the held-out matrices and the paired deploy test that follow a run, for
its first pass and its export, and only what the run lacks; the committed comparisons come out the same."""

import shutil
import sys
from pathlib import Path

import pytest

from tests.benchmarks import after_run
from tests.benchmarks.after_run import deciding_policies, plan

ROOT = Path(__file__).resolve().parents[1]
TRAINING = ROOT / "policies" / "training"


def test_the_deciding_policies_are_the_first_pass_and_the_export():
    h0 = TRAINING / "throw2d-scratch-h0"
    assert deciding_policies(h0) == {500: h0 / "candidates" / "checkpoint_500.onnx", 925: h0 / "throw2d.onnx"}
    g1 = TRAINING / "throw2d-scratch-g1"  # seed 1 of iteration 575 judged after the run; no export
    assert deciding_policies(g1) == {575: g1 / "candidates" / "checkpoint_575.onnx",  # the first pass and
                                     1025: g1 / "candidates" / "checkpoint_1025.onnx"}  # the one it would export
    assert deciding_policies(TRAINING / "throw2d-scratch-g3") == {}  # met nothing, exported nothing


def test_a_run_stopped_before_its_export_is_followed_for_the_pass_it_would_export():
    """-n4 stopped on the device time with eight passes: the first (325) and the one with the fewest
    cells worse than the deployed policy, the newest among equals (1550), not the other 2-cell pass (1375)."""
    n4 = TRAINING / "throw2d-scratch-n4"
    assert deciding_policies(n4) == {325: n4 / "candidates" / "checkpoint_325.onnx", 1550: n4 / "candidates" / "checkpoint_1550.onnx"}
    l0 = TRAINING / "throw2d-scratch-l0"  # kept before keep_run kept that pass's ONNX: the first pass alone
    assert list(deciding_policies(l0)) == [675]


def test_only_the_missing_held_out_matrices_are_run(tmp_path):
    run = tmp_path / "throw2d-scratch-h0"
    shutil.copytree(TRAINING / "throw2d-scratch-h0", run, ignore=shutil.ignore_patterns("checkpoint.pt", "tb.tar.gz", "logs"))
    (run / "matrices" / "site_matrix_2d_it925_seed2.json").unlink()
    steps = plan(run, [2], 2, ROOT)
    runs = [argv for argv, out in steps if out is None]
    assert len(runs) == 1 and runs[0][runs[0].index("--policy") + 1] == str(run / "throw2d.onnx")
    assert runs[0][runs[0].index("--out") + 1] == str(run / "matrices" / "site_matrix_2d_it925_seed2.json")
    assert runs[0][runs[0].index("--seed") + 1] == "2" and runs[0][runs[0].index("--throws") + 1] == "100"
    assert [out.name for argv, out in steps if out is not None] == ["compare_with_deployed_it500.txt", "compare_with_deployed.txt"]
    cmp = next(argv for argv, out in steps if out is not None)
    assert cmp[cmp.index("--deployed") + 1:cmp.index("--candidate")] == [
        "reports/site_matrix_2d.json", "reports/site_matrix_2d_seed1.json", "reports/site_matrix_2d_seed2.json"]


def test_the_committed_comparison_comes_out_the_same(tmp_path, monkeypatch):
    run = tmp_path / "throw2d-scratch-g2"
    shutil.copytree(TRAINING / "throw2d-scratch-g2", run, ignore=shutil.ignore_patterns("checkpoint.pt", "tb.tar.gz", "logs"))
    (run / "compare_with_deployed.txt").unlink()
    monkeypatch.setattr(sys, "argv", ["after_run", str(run)])
    after_run.main()
    body = (run / "compare_with_deployed.txt").read_text().splitlines()[1:]
    committed = (TRAINING / "throw2d-scratch-g2" / "compare_with_deployed.txt").read_text().splitlines()[1:]
    # the committed file was written before matrix_compare's pooled success test: the cells' lines are the same,
    # the pooled line is new (g2 failed 30 throws where the lineage landed, none the other way) and the verdict says so
    assert body[:-2] == committed[:-1]
    assert body[-2].startswith("pooled over all cells: the candidate failed on 30 pairs") and body[-2].endswith("FAILS MORE OFTEN")
    assert body[-1].startswith("candidate worse on 17 of 66 cells and fails more often over all cells")


def test_a_deciding_checkpoint_without_its_onnx_is_a_clear_error(tmp_path):
    run = tmp_path / "throw2d-scratch-h1"
    shutil.copytree(TRAINING / "throw2d-scratch-h1", run, ignore=shutil.ignore_patterns("checkpoint.pt", "tb.tar.gz", "logs"))
    (run / "candidates" / "checkpoint_800.onnx").unlink()
    with pytest.raises(FileNotFoundError, match="checkpoint_800.onnx: the ONNX file of iteration 800"):
        deciding_policies(run)
