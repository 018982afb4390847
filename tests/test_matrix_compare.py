"""Deploy comparison of two policies' site matrices (sim_twin.evaluation.matrix_compare): matched throws by
seed, per-cell paired tests with Holm's correction; noise alone is not called worse, a real
regression is, and bad input is refused with the reason."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sim_twin.evaluation import matrix_compare


def _report(errors: dict[tuple[str, float], list[float | None]], mode: str = "2d", seed0: int = 0) -> dict:
    """A site-matrix report whose cells hold the given downrange errors (None: not landed)."""
    profiles: dict[str, list[dict]] = {}
    for (name, target), errs in errors.items():
        profiles.setdefault(name, []).append({"target_m": target, "per_throw": {
            "seed": list(range(seed0, seed0 + len(errs))), "downrange_error_m": errs,
            "crossrange_error_m": [None if e is None else 0.0 for e in errs]}})
    return {"mode": mode, "profiles": [{"name": n, "targets": t} for n, t in profiles.items()]}


CELLS = [("nominal", 8.5), ("nominal", 10.0), ("heavy_load", 8.5)]


def _draw(rng, scale=0.06, n=100):
    return {cell: list(rng.normal(0.0, scale, n)) for cell in CELLS}


def test_noise_alone_is_not_worse_and_a_real_regression_is():
    rng = np.random.default_rng(0)
    dep = _draw(rng)
    # another policy as good: throws of the same seeds with fresh noise, over 20 draws
    assert sum(matrix_compare.compare([_report(dep)], [_report(_draw(rng))]).worse_cells for _ in range(20)) <= 1
    # far-target spread doubled on one cell: that cell, and only it, is worse
    worse = {**_draw(rng), ("nominal", 10.0): list(rng.normal(0.0, 0.12, 100))}
    comp = matrix_compare.compare([_report(dep)], [_report(worse)])
    assert [(c.profile, c.target_m, c.worse_on) for c in comp.cells if c.worse] == [("nominal", 10.0, ("landing error",))]
    assert "candidate worse on 1 of 3 cells" in matrix_compare.table(comp)


def test_failed_throws_where_the_deployed_policy_landed_are_worse_on_success():
    dep = {cell: [0.05] * 100 for cell in CELLS}
    cand = {**dep, ("heavy_load", 8.5): [None] * 20 + [0.05] * 80}
    comp = matrix_compare.compare([_report(dep)], [_report(cand)])
    bad = [c for c in comp.cells if c.worse]
    assert [(c.profile, c.worse_on, c.landed_deployed, c.landed_candidate) for c in bad] == [("heavy_load", ("success",), 100, 80)]


def test_failures_spread_thinly_over_the_cells_fail_more_often_though_no_cell_is_worse(capsys):
    """Two ground-stops in each of many cells: no cell's McNemar test can see them (p 0.25 each),
    the pooled one does (p 2^-24), and the deploy rule's verdict is worse; one stop in all is not."""
    cells = [("nominal", 7.0 + 0.5 * k) for k in range(12)]
    dep = {cell: [0.05] * 100 for cell in cells}
    cand = {cell: [None, None] + [0.05] * 98 for cell in cells}
    comp = matrix_compare.compare([_report(dep)], [_report(cand)])
    assert comp.worse_cells == 0 and (comp.pooled_lost, comp.pooled_won) == (24, 0)
    assert comp.fails_more and comp.worse and comp.p_pooled_success == pytest.approx(0.5 ** 24)
    assert "FAILS MORE OFTEN" in matrix_compare.table(comp)
    one = {**dep, cells[0]: [None] + [0.05] * 99}
    assert not matrix_compare.compare([_report(dep)], [_report(one)]).worse


def test_the_command_exits_1_when_the_candidate_fails_more_often(tmp_path):
    cells = [("nominal", 7.0 + 0.5 * k) for k in range(12)]
    (tmp_path / "d.json").write_text(json.dumps(_report({cell: [0.05] * 100 for cell in cells})))
    (tmp_path / "c.json").write_text(json.dumps(_report({cell: [None, None] + [0.05] * 98 for cell in cells})))
    assert matrix_compare.main(["--deployed", str(tmp_path / "d.json"), "--candidate", str(tmp_path / "c.json"),
                                "--out", str(tmp_path / "o.json")]) == 1
    out = json.loads((tmp_path / "o.json").read_text())
    assert out["worse_cells"] == 0 and out["fails_more"] is True and out["pooled_lost"] == 24


def test_seeds_pool_into_one_comparison_per_cell():
    rng = np.random.default_rng(1)
    dep = [_report(_draw(rng), seed0=s * 1000) for s in range(3)]
    comp = matrix_compare.compare(dep, dep)
    assert comp.worse_cells == 0 and {c.pairs for c in comp.cells} == {300}


def test_bad_input_is_refused_with_the_reason(tmp_path):
    rng = np.random.default_rng(2)
    rep = _report(_draw(rng))
    old = json.loads(json.dumps(rep))
    del old["profiles"][0]["targets"][0]["per_throw"]
    with pytest.raises(ValueError, match="no per-throw data"):
        matrix_compare.compare([old], [rep])
    with pytest.raises(ValueError, match="different throws"):
        matrix_compare.compare([rep], [_report(_draw(rng), seed0=500)])
    with pytest.raises(ValueError, match="different modes"):
        matrix_compare.compare([rep], [_report(_draw(rng), mode="3d")])
    with pytest.raises(ValueError, match="alpha"):
        matrix_compare.compare([rep], [rep], alpha=1.5)
    with pytest.raises(ValueError, match="at least one"):
        matrix_compare.compare([], [rep])
    # the command line: 2 and the reason on bad input, 0 when worse on no cell, 1 when worse
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(rep))
    b.write_text(json.dumps(old))
    assert matrix_compare.main(["--deployed", str(a), "--candidate", str(b)]) == 2
    assert matrix_compare.main(["--deployed", str(a), "--candidate", str(tmp_path / "missing.json")]) == 2
    assert matrix_compare.main(["--deployed", str(a), "--candidate", str(a), "--out", str(tmp_path / "c.json")]) == 0
    assert json.loads((tmp_path / "c.json").read_text())["worse_cells"] == 0
    worse = {**_draw(rng), ("nominal", 8.5): list(rng.normal(0.3, 0.06, 100))}
    b.write_text(json.dumps(_report(worse)))
    assert matrix_compare.main(["--deployed", str(a), "--candidate", str(b)]) == 1
