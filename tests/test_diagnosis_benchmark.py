"""The diagnosis benchmark runner without simulation: a chosen subset of cases, results written
as cases complete, resuming a run cut short, refusing to resume another benchmark's file, and
the 1-sigma coverage statistics."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sim_twin.diagnosis import benchmark

MIX = {"single": 2, "pair": 1, "outside": 0, "heldout": 0, "noise": 1}


def _fake_case(calls: list[int]):
    def run_case(case, throws, workdir, keep=False):
        calls.append(case["case"])
        params = [{"param": "p", "truth": 1.0, "fit": 1.1, "sigma": 0.2, "rel_error": 0.1, "in_1sigma": True, "z": 0.5}] if case["truth"] else []
        return {**case, "answer": "named" if case["truth"] else "no_gap", "effects": [t["effect"] for t in case["truth"]], "between": None,
                "text": "fake", "throws_used": throws, "skipped": 0, "gen_s": 0.0, "correct": True, "one_named": True,
                "confidently_wrong": False, "params": params, "held_out": None, "wall_s": 1.0, "cpu_s": 2.0}
    return run_case


def test_subset_then_resume_runs_each_case_once(tmp_path: Path, monkeypatch):
    calls: list[int] = []
    monkeypatch.setattr(benchmark, "run_case", _fake_case(calls))
    out = tmp_path / "b.json"
    first = benchmark.run(MIX, 5, 7, 1, out, only=[0, 3])
    assert sorted(calls) == [0, 3] and not first["complete"]  # a subset is never the complete benchmark
    on_disk = json.loads(out.read_text())
    assert [r["case"] for r in on_disk["cases"]] == [0, 3] and "PARTIAL" in out.with_suffix(".txt").read_text()
    calls.clear()
    res = benchmark.run(MIX, 5, 7, 1, out, resume=True)
    assert sorted(calls) == [1, 2]  # only the cases not finished before
    assert res["complete"] and [r["case"] for r in res["cases"]] == [0, 1, 2, 3]
    assert res["summary"]["cpu_s"] == pytest.approx(8.0) and res["summary"]["cpu_s_per_case"] == pytest.approx(2.0)


def test_resume_refuses_another_benchmarks_file(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(benchmark, "run_case", _fake_case([]))
    out = tmp_path / "b.json"
    benchmark.run(MIX, 5, 7, 1, out, only=[0])
    with pytest.raises(ValueError, match="cannot resume"):
        benchmark.run(MIX, 5, 8, 1, out, resume=True)  # other seed
    with pytest.raises(ValueError, match="cannot resume"):
        benchmark.run(MIX, 6, 7, 1, out, resume=True)  # other throw count


def test_profile_sigma_of_a_chi_square_parabola():
    from sim_twin.diagnosis.select import profile_sigma

    X = np.linspace(0, 1, 7)[:, None]
    T = ((X[:, 0] - 0.4) / 0.05) ** 2 + 100.0  # chi-square rises by 1 at 0.05 from the minimum
    assert profile_sigma(X, T)[0] == pytest.approx(0.05, rel=1e-6)
    X2 = np.array([[a, b] for a in np.linspace(0, 1, 4) for b in np.linspace(0, 1, 4)])
    T2 = ((X2[:, 0] - 0.5) / 0.1) ** 2 + ((X2[:, 1] - 0.3) / 0.2) ** 2
    np.testing.assert_allclose(profile_sigma(X2, T2), [0.1, 0.2], rtol=1e-6)
    assert np.isinf(profile_sigma(X, -T)[0])  # no positive curvature: the data do not bound it


def test_a_precise_fits_trajectory_rest_is_explained_but_an_impact_rest_is_not():
    from sim_twin.diagnosis import forward, noise

    C, P = len(noise.CHANNELS), len(noise.PHASES)
    D = np.zeros((20, C, P))
    traj, imp = noise.CH_INDEX["q.gripper_pitch"], noise.CH_INDEX["impact.downrange"]
    D[:, traj, 0] = 20.0
    D[:, imp, 2] = 1.0
    nominal = D.copy()
    nominal[:, traj, 0] += 5000.0  # large swing gap
    nominal[:, imp, 2] += 300.0
    after = D.copy()
    after[:, traj, 0] += 100.0  # 2 % of the nominal excess: a precise fit's visible rest
    after[:, imp, 2] += 6.0  # 2 % as well, but 6 sigma^2 per throw: a second effect's footprint
    gaps = forward.channel_gaps(after, D, nominal)
    assert "impact.downrange" in gaps and "q.gripper_pitch" not in gaps
    assert set(forward.channel_gaps(after, D)) == {"impact.downrange", "q.gripper_pitch"}  # round 1: plain noise tests


def test_a_case_that_raises_is_recorded_not_fatal(tmp_path: Path, monkeypatch):
    def broken(case, throws, workdir, keep=False):
        raise RuntimeError("replay diverged")

    monkeypatch.setattr(benchmark, "run_case", broken)
    res = benchmark.run({"single": 0, "pair": 0, "outside": 1, "heldout": 0, "noise": 1}, 5, 7, 1, tmp_path / "b.json")
    assert [r["answer"] for r in res["cases"]] == ["error", "error"] and res["summary"]["errors"] == 2
    assert res["summary"]["outside_unexplained_or_ambiguous"] == 0.0 and res["summary"]["noise_no_gap"] == 0.0
    assert "replay diverged" in res["cases"][0]["text"]


def test_benchmark_figure(tmp_path: Path, monkeypatch):
    from sim_twin.diagnosis import plots

    monkeypatch.setattr(benchmark, "run_case", _fake_case([]))
    res = benchmark.run(MIX, 5, 7, 1, tmp_path / "b.json", only=[0, 2, 3])
    png = plots.benchmark(res, tmp_path / "b.png")
    assert png.stat().st_size > 5000 and png.read_bytes()[:4] == b"\x89PNG"


def test_shards_partition_the_benchmark_with_each_kind_balanced():
    cases = benchmark.draw_cases(benchmark.MIX, 0)
    shards = [benchmark.shard_of(cases, (i, 4)) for i in range(1, 5)]
    assert sorted(c["case"] for s in shards for c in s) == [c["case"] for c in cases]  # every case exactly once
    for kind, n in benchmark.MIX.items():
        per = [sum(c["kind"] == kind for c in s) for s in shards]
        assert max(per) - min(per) <= 1 and sum(per) == n, (kind, per)
    assert max(len(s) for s in shards) - min(len(s) for s in shards) <= 1
    assert benchmark.parse_shard("2/3") == (2, 3)
    for bad in ("0/3", "4/3", "2", "a/b", "1/0"):
        with pytest.raises(ValueError, match="I/N"):
            benchmark.parse_shard(bad)


def test_shard_reports_merge_into_the_whole_benchmark(tmp_path: Path, monkeypatch):
    calls: list[int] = []
    monkeypatch.setattr(benchmark, "run_case", _fake_case(calls))
    parts = [benchmark.run(MIX, 5, 7, 1, tmp_path / f"s{i}.json", shard=(i, 2), plots=False) for i in (1, 2)]
    assert sorted(calls) == [0, 1, 2, 3] and not any(p["complete"] for p in parts) and [p["shard"] for p in parts] == [[1, 2], [2, 2]]
    whole = benchmark.run(MIX, 5, 7, 1, tmp_path / "whole.json", plots=False)
    res = benchmark.merge([tmp_path / "s1.json", tmp_path / "s2.json"], tmp_path / "m.json", plots=False)
    assert res["complete"] and res["not_run"] == [] and [r["case"] for r in res["cases"]] == [0, 1, 2, 3]
    assert res["summary"] == whole["summary"] and len(res["shards"]) == 2 and res["shards"][0]["cases"] == 2
    assert json.loads((tmp_path / "m.json").read_text())["summary"] == whole["summary"]
    half = benchmark.merge([tmp_path / "s1.json"], None, plots=False)
    assert not half["complete"] and half["not_run"] == [c["case"] for c in parts[1]["cases"]]


def test_merge_refuses_other_benchmarks_and_conflicting_cases(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(benchmark, "run_case", _fake_case([]))
    benchmark.run(MIX, 5, 7, 1, tmp_path / "a.json", only=[0], plots=False)
    benchmark.run(MIX, 5, 8, 1, tmp_path / "b.json", only=[0], plots=False)  # other seed
    with pytest.raises(ValueError, match="different benchmarks"):
        benchmark.merge([tmp_path / "a.json", tmp_path / "b.json"], None)
    body = json.loads((tmp_path / "a.json").read_text())
    body["cases"][0]["answer"] = "unexplained"
    (tmp_path / "c.json").write_text(json.dumps(body))
    with pytest.raises(ValueError, match="different answers"):
        benchmark.merge([tmp_path / "a.json", tmp_path / "c.json"], None)
    (tmp_path / "d.json").write_text("{not json")
    with pytest.raises(ValueError, match="not a readable"):
        benchmark.merge([tmp_path / "d.json"], None)
    with pytest.raises(ValueError, match="at least one"):
        benchmark.merge([], None)


def test_a_passed_deadline_starts_no_case_and_says_which_did_not_run(tmp_path: Path, monkeypatch):
    calls: list[int] = []
    monkeypatch.setattr(benchmark, "run_case", _fake_case(calls))
    res = benchmark.run(MIX, 5, 7, 1, tmp_path / "b.json", deadline_s=0.0, plots=False)
    assert calls == [] and not res["complete"] and res["not_run"] == [0, 1, 2, 3]


def test_stopping_the_workers_ends_running_cases_at_once():
    import time

    from sim_twin.twin.pools import process_pool

    pool = process_pool(2)
    futs = [pool.submit(time.sleep, 60) for _ in range(3)]
    time.sleep(1.0)
    t0 = time.time()
    benchmark.stop_workers(pool)
    assert time.time() - t0 < 20 and all(f.done() for f in futs[:2])


def test_merge_on_the_command_line_takes_options_between_the_reports(tmp_path: Path, monkeypatch):
    from sim_twin.diagnosis import cli

    monkeypatch.setattr(benchmark, "run_case", _fake_case([]))
    for i in (1, 2):
        benchmark.run(MIX, 5, 7, 1, tmp_path / f"s{i}.json", shard=(i, 2), plots=False)
    out = tmp_path / "m.json"
    assert cli.main(["merge", str(tmp_path / "s1.json"), "--out", str(out), "--no-plots", str(tmp_path / "s2.json")]) == 0
    assert [r["case"] for r in json.loads(out.read_text())["cases"]] == [0, 1, 2, 3]
    assert cli.main(["merge", "--out", str(out)]) == 2  # no reports: a clear error


def test_new_kinds_are_scored_by_what_is_confirmed_and_listed():
    """mimic: a library effect confirmed as a part is as wrong as a named one; drifting: only
    "drifting" is right; impact_pair: the trajectory member confirmed and the impact-only one listed."""
    from sim_twin.diagnosis import benchmark as b

    mimic = {"kind": "mimic", "truth": [{"effect": "sim_twin.diagnosis.unmodelled_mimic:BoomBacklash", "param": "play", "value": 0.3}]}
    assert b.score({**mimic, "answer": "unexplained", "effects": ["valve_lag"], "confirmed": []})["correct"]
    wrong = b.score({**mimic, "answer": "unexplained", "effects": ["valve_lag"], "confirmed": ["valve_lag"]})
    assert not wrong["correct"] and wrong["confidently_wrong"]
    drift = {"kind": "drifting", "truth": [{"effect": "valve_lag", "param": "lag_s_boom", "value": 0.4, "shape": "ramp"}]}
    assert b.score({**drift, "answer": "drifting", "effects": []})["correct"]
    assert not b.score({**drift, "answer": "named", "effects": ["valve_lag"], "confirmed": ["valve_lag"]})["correct"]
    pair = {"kind": "impact_pair", "truth": [{"effect": "passive_friction", "param": "viscous_per_s", "value": 0.9},
                                             {"effect": "release_delay", "param": "mean_s", "value": 0.45}]}
    ok = b.score({**pair, "answer": "consistent", "effects": ["passive_friction"], "confirmed": ["passive_friction"],
                  "consistent": ["release_delay"], "alternatives": ["payload_drag", "impact_bias"]})
    assert ok["correct"]
    assert not b.score({**pair, "answer": "unexplained", "effects": ["passive_friction"], "confirmed": ["passive_friction"]})["correct"]
    cases = b.draw_cases(b.MIX, 0)
    assert len(cases) == 100 and cases[:78] == b.draw_cases({k: b.MIX[k] for k in list(b.MIX)[:8]}, 0)  # the earlier 78 unchanged
    ramp = b.per_throw_profiles(next(c for c in cases if c["kind"] == "drifting" and c["truth"][0]["shape"] == "ramp"), 10)
    vals = [p["effects"][0]["params"]["lag_s_boom"] for p in ramp]
    from sim_twin.twin.effects import effect_class

    nominal = next(p.nominal for p in effect_class("valve_lag").params if p.name == "lag_s_boom")
    assert vals[0] == pytest.approx(nominal) and vals == sorted(vals) and len(set(vals)) == 10
