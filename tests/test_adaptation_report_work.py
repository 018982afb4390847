"""tests/benchmarks/adaptation_report.py keeps each policy version's steps apart: a resumed run never
reuses a dataset or evaluation made with another policy file."""

from pathlib import Path

from tests.benchmarks.adaptation_report import work_dir


def test_the_work_dir_is_keyed_by_the_policy_files(tmp_path: Path):
    a, b = tmp_path / "a.onnx", tmp_path / "b.onnx"
    a.write_bytes(b"policy a")
    b.write_bytes(b"policy b")
    base = tmp_path / "work"
    one = work_dir(base, {"2d": a})
    assert one.parent == base and one.name.startswith("2d-") and len(one.name) == 3 + 12
    assert work_dir(base, {"2d": a}) == one  # the same file resumes in the same place
    assert work_dir(base, {"2d": b}) != one  # another version does not
    both = work_dir(base, {"3d": b, "2d": a})
    assert both.name.startswith(one.name + "_3d-")
