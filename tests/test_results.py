"""docs/results.md is generated from reports/ (server.site.results_page) and stays true to them.

Fails when docs/results.md is stale, when a report that claims to describe a deployed policy
(``provenance.policies[].deployed_as``) names another SHA-256 or version than policies/*.onnx, when a
report lacks provenance, or when reports/safety_bounds.json disagrees with the constants in the code.
Reads JSON and source text only (no MuJoCo, no database).
"""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest

from server.site import results_page as results

ROOT = Path(__file__).resolve().parents[1]


def test_docs_results_md_is_generated_from_the_current_reports():
    reports = results.load_reports(ROOT)
    want = results.render(reports)
    have = (ROOT / "docs" / "results.md").read_text()
    assert have == want, "docs/results.md is stale: run `slinger results` and commit it"


def test_reports_of_deployed_policies_name_the_deployed_files_sha256():
    reports = results.load_reports(ROOT)
    assert any(p.get("deployed_as") for _, r in reports for p in r["provenance"]["policies"]), "no report names a deployed policy"
    assert results.check_deployed(reports, ROOT) == []


def test_every_json_report_has_provenance():
    """Every JSON file directly under reports/ (and reports/fleet_load/) is a report with provenance."""
    have = {rel for rel, _ in results.load_reports(ROOT)}
    files = {p.relative_to(ROOT).as_posix() for d in ("reports", "reports/fleet_load") for p in (ROOT / d).glob("*.json")}
    assert files - have == set()


def _fake_repo(tmp_path: Path, sha: str) -> Path:
    (tmp_path / "policies").mkdir()
    (tmp_path / "reports").mkdir()
    (tmp_path / "policies" / "throw2d.onnx").write_bytes(b"not really onnx")
    (tmp_path / "policies" / "throw2d.json").write_text(json.dumps({"name": "throw2d-x"}))
    prov = {"title": "T", "date": "2026-01-01T00:00:00Z", "commit": "abc1234", "host": "h", "command": "c", "recorded": "r",
            "policies": [{"name": "throw2d-x", "sha256": sha, "deployed_as": "policies/throw2d.onnx"}]}
    report = {"provenance": prov, "figures": [{"what": "a figure", "value": 1.5, "unit": "m"}]}
    (tmp_path / "reports" / "r.json").write_text(json.dumps(report))
    return tmp_path


def test_a_report_naming_another_sha256_than_the_deployed_file_fails(tmp_path):
    root = _fake_repo(tmp_path, "0" * 64)
    problems = results.check_deployed(results.load_reports(root), root)
    assert len(problems) == 1 and "reports/r.json" in problems[0] and "SHA-256" in problems[0]
    good = results.sha256_file(root / "policies" / "throw2d.onnx")
    (tmp_path / "ok").mkdir()
    root2 = _fake_repo(tmp_path / "ok", good)
    assert results.check_deployed(results.load_reports(root2), root2) == []


def test_check_fails_on_a_stale_results_md_and_passes_after_regenerating(tmp_path, capsys):
    root = _fake_repo(tmp_path, "0" * 64)
    sha = results.sha256_file(root / "policies" / "throw2d.onnx")
    (root / "reports" / "r.json").write_text((root / "reports" / "r.json").read_text().replace("0" * 64, sha))
    assert results.main(["--root", str(root), "--check"]) == 1  # no docs/results.md yet
    assert "stale" in capsys.readouterr().err
    assert results.main(["--root", str(root)]) == 0
    assert "a figure" in (root / "docs" / "results.md").read_text()
    assert results.main(["--root", str(root), "--check"]) == 0
    report = json.loads((root / "reports" / "r.json").read_text())
    report["figures"][0]["value"] = 2.5
    (root / "reports" / "r.json").write_text(json.dumps(report))
    assert results.main(["--root", str(root), "--check"]) == 1


def test_a_report_without_complete_provenance_is_refused(tmp_path):
    root = _fake_repo(tmp_path, "0" * 64)
    report = json.loads((root / "reports" / "r.json").read_text())
    del report["provenance"]["command"]
    (root / "reports" / "r.json").write_text(json.dumps(report))
    with pytest.raises(results.ReportError, match="command"):
        results.load_reports(root)
    assert results.main(["--root", str(root), "--check"]) == 2


def _constant(module_path: str, name: str) -> float:
    tree = ast.parse((ROOT / module_path).read_text())
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        if any(isinstance(t, ast.Name) and t.id == name for t in targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"{name} not found in {module_path}")


def test_safety_bounds_report_matches_the_code():
    bounds = json.loads((ROOT / "reports" / "safety_bounds.json").read_text())["bounds"]
    for dotted, value in bounds.items():
        module, name = dotted.rsplit(".", 1)
        assert _constant(module.replace(".", "/") + ".py", name) == value, f"{dotted} changed: update reports/safety_bounds.json"


def test_slinger_results_check_passes_on_this_checkout():
    from server.cli import main

    assert main(["results", "--check"]) == 0


@pytest.mark.parametrize("mode", ["2d", "3d"])
def test_model_card_names_the_deployed_file_and_config(mode):
    """policies/throw<mode>.md states the deployed version, its SHA-256 and its config hash."""
    manifest = json.loads((ROOT / "policies" / f"throw{mode}.json").read_text())
    card = (ROOT / "policies" / f"throw{mode}.md").read_text()
    assert manifest["name"] in card.splitlines()[0]
    assert results.sha256_file(ROOT / "policies" / f"throw{mode}.onnx") in card
    assert results.config_sha256(manifest["training"]["config"]) in card


def test_stamp_writes_a_complete_provenance_block_that_the_check_accepts(tmp_path):
    root = _fake_repo(tmp_path, "0" * 64)
    report = root / "reports" / "new.json"
    report.write_text(json.dumps({"figures": [{"what": "w", "value": 2.0, "unit": "s"}]}))
    rc = results.main(["--root", str(root), "--stamp", str(report), "--title", "New", "--command", "do it",
                       "--policy", str(root / "policies" / "throw2d.onnx")])
    assert rc == 0
    prov = json.loads(report.read_text())["provenance"]
    assert all(k in prov for k in results.REQUIRED) and prov["recorded"].startswith("at run time")
    assert prov["policies"] == [{"name": "throw2d-x", "sha256": results.sha256_file(root / "policies" / "throw2d.onnx"),
                                 "deployed_as": "policies/throw2d.onnx"}]
    assert "CPUs" in prov["host"]
    problems = results.check_deployed(results.load_reports(root), root)
    assert problems and all("reports/r.json" in p for p in problems)  # the stamped report itself is consistent


@pytest.mark.parametrize("indent", [None, 1, 2])
def test_stamp_keeps_the_reports_layout(tmp_path, indent):
    """A compact report stays on one line; an indented one keeps its indent; a re-stamp changes
    only the provenance block's lines."""
    root = _fake_repo(tmp_path, "0" * 64)
    report = root / "reports" / "new.json"
    body = {"throws": [{"impact_m": [8.0 + k / 100, 0.1]} for k in range(50)]}
    report.write_text(json.dumps(body, indent=indent) + "\n")
    stamp = ["--root", str(root), "--stamp", str(report), "--title", "New", "--host", "a host", "--command", "do it"]
    assert results.main(stamp) == 0
    first = report.read_text()
    assert json.loads(first)["throws"] == body["throws"]
    assert (len(first.splitlines()) == 1) if indent is None else (len(first.splitlines()) > 150)
    assert results.json_indent(first) == indent
    assert results.main([*stamp[:-1], "do it again"]) == 0
    changed = [a for a, b in zip(first.splitlines(), report.read_text().splitlines()) if a != b]
    assert 1 <= len(changed) <= (1 if indent is None else 2)
    assert all(c.strip().startswith(('"date"', '"command"')) for c in changed) or indent is None


def test_stamp_keeps_per_throw_lists_on_one_line(tmp_path):
    """An indented report whose per-throw lists are on one line each (a site matrix, written by
    sim_twin.provenance.compact_json) keeps them so when stamped: the lists are not spread one
    value per line, and the data read back are the same."""
    from sim_twin.provenance import compact_json

    root = _fake_repo(tmp_path, "0" * 64)
    report = root / "reports" / "matrix.json"
    body = {"profiles": [{"name": "nominal", "per_throw": {"seed": list(range(100)), "error_m": [k / 1000 for k in range(100)]}}]}
    report.write_text(compact_json(body) + "\n")
    before = len(report.read_text().splitlines())
    stamp = ["--root", str(root), "--stamp", str(report), "--title", "New", "--host", "a host", "--command", "do it"]
    assert results.main(stamp) == 0
    text = report.read_text()
    assert json.loads(text)["profiles"] == body["profiles"]
    assert '"seed": [0, 1, 2,' in text and len(text.splitlines()) < before + 20  # the provenance block's lines only
    assert results.json_indent(text) == 1


def test_stamp_refuses_a_missing_policy_or_title(tmp_path):
    root = _fake_repo(tmp_path, "0" * 64)
    report = root / "reports" / "r.json"
    assert results.main(["--root", str(root), "--stamp", str(report), "--command", "c"]) == 2
    assert results.main(["--root", str(root), "--stamp", str(report), "--title", "t", "--command", "c",
                         "--policy", str(root / "policies" / "nope.onnx")]) == 2
    assert json.loads(report.read_text())["provenance"]["title"] == "T"  # unchanged


def test_site_coverage_report_renders_each_part_per_policy():
    report = {"mode": "2d", "throws_per_target": 100, "seed": 0, "policies": {"a": "a.onnx", "b": "b.onnx"},
              "parts": ["worn_gripper", "worn_gripper__release_delay"],
              "cells": [{"policy": "a", "profile": "worn_gripper", "target_m": 7.5, "mean_miss_m": 0.05},
                        {"policy": "a", "profile": "worn_gripper", "target_m": 10.0, "mean_miss_m": 0.2},
                        {"policy": "b", "profile": "worn_gripper", "target_m": 7.5, "mean_miss_m": 0.07},
                        {"policy": "a", "profile": "worn_gripper__release_delay", "target_m": 7.5, "mean_miss_m": 0.04},
                        {"policy": "b", "profile": "worn_gripper__release_delay", "target_m": 7.5, "mean_miss_m": None}]}
    lines = results._body("reports/site_coverage_diagnosis_2d.json", report)
    assert "| worn_gripper | 0.05-0.2 | 0.07-0.07 |" in lines
    assert "| worn_gripper__release_delay | 0.04-0.04 | none landed |" in lines


def test_results_page_lists_current_figures_in_at_most_400_lines_every_report_under_a_topic():
    text = (ROOT / "docs" / "results.md").read_text()
    assert len(text.splitlines()) <= 400, "docs/results.md is over 400 lines: move superseded reports to the lab notebook (reports/ARCHIVE.md)"
    others = [rel for rel, _ in results.load_reports(ROOT) if results.topic_of(rel) == "Other"]
    assert others == [], f"reports without a topic in server/results_page.TOPICS: {others}"


def _matrix(seed: int, sigma: float, passed: bool) -> dict:
    prov = {"title": f"Site matrix, 2D, start-pose seed {seed}", "date": "2026-01-01T00:00:00Z", "commit": "abc1234",
            "host": "h", "command": f"slinger evaluate --matrix --seed {seed}", "recorded": "r", "policies": []}
    cells = [{"success_rate": 1.0, "bias_m": -0.05, "sigma_downrange_m": sigma, "sigma_crossrange_m": 0.02}]
    return {"provenance": prov, "seed": seed, "throws_per_target": 100, "pass": passed,
            "profiles": [{"name": "nominal", "shifts_mean": False, "pass": passed, "targets": cells}]}


def test_a_modes_site_matrices_on_several_seeds_are_one_section_seed_by_seed(tmp_path):
    reports = [("reports/site_matrix_2d_seed1.json", _matrix(1, 0.12, False)), ("reports/site_matrix_2d.json", _matrix(0, 0.08, True)),
               ("reports/login_flood.json", {"provenance": {**_matrix(0, 0, True)["provenance"], "title": "Log-in flood"},
                                             "figures": [{"what": "p99", "value": 0.5, "unit": "s"}]})]
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "site_matrix_2d.png").write_bytes(b"png")
    text = results.render(reports, tmp_path)
    assert text.count("### Site matrix, 2D") == 1 and "### Log-in flood" in text
    assert "| nominal | no | 100 % / 100 % | 0.05 / 0.05 | 0.08 / 0.12 | 0.02 / 0.02 | met / **missed** |" in text
    assert "Every bar met: **yes** / **no**" in text
    # the seed-0 report comes first, with the plot beside it linked; the topics order the page
    assert text.index("reports/site_matrix_2d.json") < text.index("reports/site_matrix_2d_seed1.json")
    assert "[`site_matrix_2d.png`](../reports/site_matrix_2d.png)" in text
    assert text.index("## Accuracy of the deployed policies") < text.index("## Fleet and server")
