"""tests/benchmarks/keep_run.py trims a run brought back from a GPU machine to what the tree keeps: per-throw
rows only where they decide the run, no matrix plots, only the deciding gate candidates, no candidate
checkpoint but that of the pass a resume past the bars would export, TensorBoard events packed; and it
leaves the checkpoint, the gate's verdicts and the export."""

import json
import shutil
import tarfile
from pathlib import Path

import pytest

from tests.benchmarks.keep_run import candidate_iterations, decide, keep_run, row_iterations

ROOT = Path(__file__).resolve().parents[1]
H0 = ROOT / "policies" / "training" / "throw2d-scratch-h0"  # first pass 500, exported 925
G3 = ROOT / "policies" / "training" / "throw2d-scratch-g3"  # no pass; the gate judged 825 and 1050 last


def _collected(tmp_path: Path, src: Path) -> Path:
    """A copy of a kept run made to look as `collect` brings it back."""
    run = tmp_path / src.name
    shutil.copytree(src, run, ignore=shutil.ignore_patterns("checkpoint.pt", "tb.tar.gz", "logs"))
    with_rows = next(m for m in sorted((run / "matrices").glob("site_matrix_2d_it*.json"))
                     if "per_throw" in json.loads(m.read_text())["profiles"][0]["targets"][0])
    for it in (725, 1100):  # matrices the gate ran, with their rows as they come back
        shutil.copy(with_rows, run / "matrices" / f"site_matrix_2d_it{it}.json")
    (run / "matrices" / "site_matrix_2d_it725.png").write_bytes(b"png")
    (run / "candidates").mkdir(exist_ok=True)
    for it in (375, 500, 725, 925):
        for ext in (".onnx", ".json", ".pt"):
            (run / "candidates" / f"checkpoint_{it}{ext}").write_bytes(b"x")
    (run / "tb").mkdir()
    (run / "tb" / "events.out.tfevents.1").write_bytes(b"events")
    (run / "checkpoint.pt").write_bytes(b"ckpt")
    return run


def _has_rows(path: Path) -> bool:
    return any("per_throw" in t for p in json.loads(path.read_text())["profiles"] for t in p["targets"])


def test_the_deciding_iterations_of_a_run_that_met_the_bars():
    # first, style (<= 250), every pass (500, 725 and the export 925: their paired tests can be run again), last
    assert row_iterations(decide(H0)) == {25, 150, 500, 725, 925, 1200}
    assert candidate_iterations(decide(H0)) == {500}  # the first pass; the export (the newest pass) is throw2d.onnx


def test_the_pass_a_compared_run_exports_keeps_its_candidate(tmp_path):
    """With --gate-compare-with a run past the bars exports the pass worse than the deployed policy on
    the fewest cells (matrix_gate.choose_pass): a run whose export is another (the newest, written by
    hand after the run, say) keeps that pass's candidate beside the first."""
    run = tmp_path / "run"
    shutil.copytree(H0 / "matrices", run / "matrices")
    (run / "throw2d.card.json").write_text(json.dumps({"iteration": 925}))
    gate = json.loads((run / "matrices" / "matrix_gate.json").read_text())
    for p, worse in zip(gate["passes"], (3, 1, 2)):
        p["worse_than_deployed"] = worse
    (run / "matrices" / "matrix_gate.json").write_text(json.dumps(gate))
    d = decide(run)
    assert (d.first_pass, d.exported) == (500, 925) and candidate_iterations(d) == {500, 725}


def test_a_run_that_never_met_keeps_its_last_two_candidates():
    assert candidate_iterations(decide(G3)) == {825, 1050}


def test_a_collected_run_is_trimmed_and_keeps_what_decides_it(tmp_path):
    run = _collected(tmp_path, H0)
    gate_before = (run / "matrices" / "matrix_gate.json").read_text()
    done = keep_run(run)
    m = run / "matrices"
    assert not _has_rows(m / "site_matrix_2d_it1100.json")  # judged, not a pass
    assert _has_rows(m / "site_matrix_2d_it500.json") and _has_rows(m / "site_matrix_2d_it925.json")
    assert _has_rows(m / "site_matrix_2d_it725.json")  # a pass between the first and the export
    assert _has_rows(m / "site_matrix_2d_it500_seed2.json")  # a held-out seed's matrix keeps its rows
    assert json.loads((m / "site_matrix_2d_it725.json").read_text())["pass"] is not None  # the verdicts stay
    assert not list(m.glob("*.png"))
    # the first pass's ONNX file and manifest; the pass a resume past the bars would export (the newest, 925,
    # also the export) whole, its checkpoint too (MatrixGate.exportable_passes needs it)
    assert sorted(p.name for p in (run / "candidates").iterdir()) == [
        "checkpoint_500.json", "checkpoint_500.onnx", "checkpoint_925.json", "checkpoint_925.onnx", "checkpoint_925.pt"]
    assert not (run / "tb").exists()
    with tarfile.open(run / "tb.tar.gz") as tar:
        assert "tb/events.out.tfevents.1" in tar.getnames()
    assert (run / "checkpoint.pt").read_bytes() == b"ckpt" and (run / "throw2d.onnx").exists()
    assert (m / "matrix_gate.json").read_text() == gate_before
    assert any("it1100" in line for line in done)


def test_a_dry_run_changes_nothing(tmp_path):
    run = _collected(tmp_path, H0)
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    assert keep_run(run, dry_run=True)
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before


def test_more_rows_and_candidates_on_request(tmp_path):
    run = _collected(tmp_path, H0)
    keep_run(run, rows={725}, candidates={375})
    assert _has_rows(run / "matrices" / "site_matrix_2d_it725.json")
    assert (run / "candidates" / "checkpoint_375.onnx").exists() and not (run / "candidates" / "checkpoint_375.pt").exists()


def test_a_directory_without_a_gate_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="no matrices/matrix_gate.json"):
        keep_run(tmp_path)
