"""sim_twin.training.late_export: a run whose machine went back before ``slinger train`` finished gets
the export and model card that ``finish`` would have written, from the gate's state and candidates.

Checked against a card ``finish`` wrote (throw2d-scratch-h0, exported at the end of its run): with that
run's export turned back into the gate's candidate, the late export writes the same policy bytes, the
same manifest and the same card."""

import json
import shutil
from pathlib import Path

import pytest

from sim_twin.training.late_export import chosen_pass, late_export, main

H0 = Path(__file__).resolve().parents[1] / "policies" / "training" / "throw2d-scratch-h0"


@pytest.fixture
def unfinished(tmp_path) -> Path:
    """h0 as its machine would have left it had it gone back before finish: the export only as the
    gate's candidate of iteration 925 (its manifest without the card)."""
    run = tmp_path / "run"
    run.mkdir()
    for name in ("config.json", "accelerators.json"):
        shutil.copy(H0 / name, run / name)
    shutil.copytree(H0 / "matrices", run / "matrices", ignore=shutil.ignore_patterns("*.md"))
    (run / "candidates").mkdir()
    shutil.copy(H0 / "throw2d.onnx", run / "candidates" / "checkpoint_925.onnx")
    manifest = json.loads((H0 / "throw2d.json").read_text())
    del manifest["training"]["model_card"]
    (run / "candidates" / "checkpoint_925.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return run


def test_the_late_export_is_what_finish_wrote(unfinished):
    want = json.loads((H0 / "throw2d.card.json").read_text())
    out = late_export(unfinished, want["command"], want["git_commit"])
    assert out == unfinished / "throw2d.onnx" and out.read_bytes() == (H0 / "throw2d.onnx").read_bytes()
    assert json.loads((unfinished / "throw2d.card.json").read_text()) == want
    assert json.loads(out.with_suffix(".json").read_text()) == json.loads((H0 / "throw2d.json").read_text())
    assert (unfinished / "throw2d.card.md").read_text() == (H0 / "throw2d.card.md").read_text()


def test_newest_or_first_pass():
    gate = {"passed": {"iteration": 5}, "passes": [{"iteration": 5}, {"iteration": 9}]}
    assert chosen_pass(gate)["iteration"] == 9 and chosen_pass(gate, first=True)["iteration"] == 5
    assert chosen_pass({"passed": {"iteration": 5}})["iteration"] == 5  # a state written before ``passes``
    with pytest.raises(ValueError, match="nothing to export"):
        chosen_pass({"passed": None, "passes": []})


def test_bad_input_is_refused_and_changes_nothing(unfinished, capsys):
    manifest = unfinished / "candidates" / "checkpoint_925.json"
    kept = manifest.read_bytes()
    manifest.unlink()
    assert main([str(unfinished), "--command", "slinger train", "--commit", "abc"]) == 2
    assert "did not come back" in capsys.readouterr().err and not (unfinished / "throw2d.onnx").exists()
    with pytest.raises(ValueError, match="command"):
        late_export(unfinished, " ", "abc")
    manifest.write_bytes(kept)
    (unfinished / "throw2d.onnx").write_bytes(b"already")
    assert main([str(unfinished), "--command", "slinger train", "--commit", "abc"]) == 2
    assert "has an export" in capsys.readouterr().err and (unfinished / "throw2d.onnx").read_bytes() == b"already"


def test_another_pass_is_carded_in_place_and_the_export_left_alone(unfinished, capsys):
    """``--iteration N`` writes the card of that pass beside its candidate (the card finish would have
    written had it exported it) and copies nothing; a non-pass is refused, naming the passes."""
    want = json.loads((H0 / "throw2d.card.json").read_text())
    cand = unfinished / "candidates" / "checkpoint_925.onnx"
    before = cand.read_bytes()
    assert main([str(unfinished), "--command", want["command"], "--commit", want["git_commit"], "--iteration", "900"]) == 2
    assert "iteration 900 did not meet every bar" in capsys.readouterr().err
    assert not (unfinished / "candidates" / "checkpoint_925.card.json").exists()
    out = late_export(unfinished, want["command"], want["git_commit"], iteration=925)
    assert out == cand and cand.read_bytes() == before and not (unfinished / "throw2d.onnx").exists()
    assert json.loads((unfinished / "candidates" / "checkpoint_925.card.json").read_text()) == want
    assert json.loads(cand.with_suffix(".json").read_text())["training"]["model_card"] == want
    with pytest.raises(FileExistsError, match="has its card"):
        late_export(unfinished, want["command"], want["git_commit"], iteration=925)
