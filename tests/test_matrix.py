"""Site matrix (slinger evaluate --matrix): bar verdicts per cell and a tiny end-to-end run that
writes the table, the JSON and the figure (with the fixture policy: the run's form is under test,
not how well it throws)."""

from __future__ import annotations

import json

import pytest

from sim_twin.evaluation import matrix

def _cell(success=1.0, bias=0.0, down=0.05, cross=0.05):
    return {"success_rate": success, "landed": 10, "bias_m": bias, "sigma_downrange_m": down, "sigma_crossrange_m": cross}


@pytest.mark.parametrize("mode,profile,shifts,cell,ok", [
    ("2d", "nominal", False, _cell(), True),
    ("2d", "nominal", False, _cell(success=0.97), False),  # nominal 2D needs 98 %
    ("2d", "nominal", False, _cell(down=0.12), False),
    ("2d", "slow_hydraulics", False, _cell(bias=0.14, down=0.19), True),
    ("2d", "slow_hydraulics", False, _cell(bias=-0.16), False),
    ("2d", "heavy_load", True, _cell(bias=0.6, down=0.5), True),  # mean shifters: success only
    ("2d", "heavy_load", True, _cell(success=0.94), False),
    ("3d", "nominal", False, _cell(bias=0.3, cross=0.19), True),
    ("3d", "nominal", False, _cell(cross=0.21), False),
    ("3d", "sensor_noise", False, _cell(down=0.29, cross=0.31), False),
])
def test_cell_bars(mode, profile, shifts, cell, ok):
    assert all(matrix.cell_bars(mode, profile, shifts, cell).values()) is ok


def test_every_matrix_profile_is_committed(fixture_policy):
    for name, _ in matrix.MATRIX_PROFILES[1:]:
        assert (matrix.PROFILE_DIR / f"{name}.json").is_file(), name
    with pytest.raises(FileNotFoundError):
        matrix.run_matrix(fixture_policy("2d"), "2d", [8.5], 1, profiles=[("no_such_site", False)])


def test_tiny_matrix_writes_table_json_and_figure(tmp_path, fixture_policy):
    rep = matrix.run_matrix(fixture_policy("2d"), "2d", [8.5], 2, profiles=[("nominal", False), ("friction_x3", False)], workers=1)
    assert [p["name"] for p in rep["profiles"]] == ["nominal", "friction_x3"]
    assert all(p["targets"][0]["throws"] == 2 for p in rep["profiles"])
    # per-throw landing errors by seed (the same seeds in every profile: matched pairs across policies)
    for p in rep["profiles"]:
        c = p["targets"][0]
        assert c["per_throw"]["seed"] == [0, 1]
        landed = [e for e in c["per_throw"]["downrange_error_m"] if e is not None]
        assert len(landed) == c["landed"] and (not landed or abs(sum(landed) / len(landed) - c["bias_m"]) < 1e-3)
    matrix.write(rep, tmp_path / "m.json")
    assert json.loads((tmp_path / "m.json").read_text())["mode"] == "2d"
    assert "| friction_x3 | no | 8.5 |" in (tmp_path / "m.md").read_text()
    assert (tmp_path / "m.png").stat().st_size > 1000


def test_report_json_puts_value_lists_on_one_line_and_reads_back_the_same():
    rep = {"a": [1, None, -0.0123], "b": ["x,  y", "[z]"], "c": [{"d": [2, 3]}], "e": []}
    text = matrix.dumps(rep)
    assert json.loads(text) == rep
    assert '"a": [1, null, -0.0123]' in text and '"d": [2, 3]' in text
