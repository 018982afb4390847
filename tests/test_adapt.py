"""Adaptation to a site (sim_twin.adaptation.adapt) and the runtime's aim correction (runtime.aim):
the offset table, its seal in the ONNX file, the executor aiming with it, the correction loop
(on a fake twin evaluation) and the fine-tuning config. The real twin evaluations behind the
committed report are reports/adaptation.md."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from runtime.aim import AIM_FORMAT, AimCorrection
from runtime.executor import ThrowExecutor
from runtime.policy import PolicyError, PolicyRunner
from runtime.protocol.messages import ThrowRequest
from runtime.throw_geometry import impact_errors
from sim_twin.adaptation import adapt as ad
from sim_twin.twin.hydraulics import NOMINAL_LAG_S
from sim_twin.twin.profile import RealityProfile
from sim_twin.twin.simulated_machine import SimulatedMachine
from sim_twin.twin.twin_machine import TwinMachine
from tests.fixtures import finished_diagnosis_run, write_test_policy

TABLE = {"format": AIM_FORMAT, "distances_m": [7.0, 9.0], "downrange_offset_m": [-0.2, -0.4], "crossrange_offset_m": [0.1, 0.3]}


def test_aim_table_geometry():
    aim = AimCorrection.from_block(TABLE)
    assert aim.offsets_at(8.0) == pytest.approx((-0.3, 0.2))
    assert aim.offsets_at(5.0) == pytest.approx((-0.2, 0.1)) and aim.offsets_at(12.0) == pytest.approx((-0.4, 0.3))
    target = np.array([8.0 * math.cos(0.7), 8.0 * math.sin(0.7), 0.0])
    down, cross = impact_errors(target, aim.aim(target))  # the aim moves by the offsets in the target's frame
    assert (down, cross) == pytest.approx((-0.3, 0.2))
    assert aim.aim([0.0, 0.0, 0.0]).tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize(("change", "message"), [
    ({"format": "x"}, "format"),
    ({"distances_m": [9.0, 7.0]}, "strictly increasing"),
    ({"downrange_offset_m": [0.1]}, "equal length"),
    ({"crossrange_offset_m": [0.0, float("nan")]}, "finite"),
    ({"downrange_offset_m": [0.0, 5.0]}, "exceeds"),
    ({"distances_m": "far"}, "numeric lists"),
])
def test_bad_aim_tables_are_refused(change, message):
    with pytest.raises(ValueError, match=message):
        AimCorrection.from_block({**TABLE, **change})


@pytest.fixture(scope="module")
def sealed(tmp_path_factory):
    d = tmp_path_factory.mktemp("aim")
    base = write_test_policy(d, "2d", release_after_bias=1.95)
    out = ad.seal_version(base, d / "site.onnx", "test-site", TABLE, RealityProfile(name="site").to_dict(), {"method": "aim"})
    return base, out


def test_sealed_version_loads_and_binds_its_table(sealed, tmp_path):
    base, out = sealed
    runner = PolicyRunner.load(out)
    assert runner.version == "test-site" and runner.sha256 != PolicyRunner.load(base).sha256
    assert runner.aim_target([8.0, 0.0, 0.0]) == pytest.approx([7.7, 0.2, 0.0])
    assert PolicyRunner.load(base).aim_target([8.0, 0.0, 0.0]).tolist() == [8.0, 0.0, 0.0]
    manifest = json.loads(out.with_suffix(".json").read_text())
    assert manifest["site_profile"]["name"] == "site" and manifest["training"]["adaptation"] == {"method": "aim"}
    # a manifest whose table was edited, or dropped, no longer matches the sealed file
    for edit in ({**manifest, "aim_correction": {**TABLE, "downrange_offset_m": [0.0, 0.0]}},
                 {k: v for k, v in manifest.items() if k != "aim_correction"}):
        (tmp_path / "x.onnx").write_bytes(out.read_bytes())
        (tmp_path / "x.json").write_text(json.dumps(edit))
        with pytest.raises(PolicyError, match="sealed"):
            PolicyRunner.load(tmp_path / "x.onnx")


def test_executor_gives_the_policy_the_aimed_target(sealed):
    from tests.test_executor import RecordingPolicy

    rec = RecordingPolicy(PolicyRunner.load(sealed[1]))
    twin = TwinMachine(SimulatedMachine(seed=1), "m1")
    ex = ThrowExecutor({"2d": rec})
    target = [8.0, -0.292, 0.0]
    assert ex.start(ThrowRequest(throw_id="a", machine_id="m1", mode="2d", target_m=target), twin.state()) is None
    for _ in range(200):
        out = ex.tick(twin.state())
        twin.step(out.valve_u, out.gripper_open)
        if rec.observations:
            break
    aimed = rec.runner.aim_target(target)
    obs = rec.observations[0]
    assert not np.allclose(aimed, target)
    assert np.any(np.all(np.isclose(np.lib.stride_tricks.sliding_window_view(obs, 3), aimed.astype(np.float32), atol=5e-3), axis=1))  # the cabin angle is measured (encoder noise)


def test_correction_loop_converges_on_a_biased_twin(monkeypatch, sealed):
    """A twin whose impact error is 0.3 m + 0.02 m/m beyond 8 m and that follows only 80 % of an
    aim change: two rounds and the secant step null it."""
    calls = []

    def fake_measure(policy, mode, profile_path, distances, throws, seed, workers):
        aim = PolicyRunner.load(policy).aim_correction
        calls.append(json.loads(profile_path.read_text())["name"])
        out = {}
        for d in distances:
            off = aim.offsets_at(d)[0] if aim else 0.0
            out[float(d)] = (0.3 + 0.02 * (d - 8) + 0.8 * off, 0.0, throws, 0.1)
        return out

    monkeypatch.setattr(ad, "_measure", fake_measure)
    table, history = ad.compute_aim_correction(sealed[0], RealityProfile(name="windy"), [7.5, 8.5, 9.5], throws=5, rounds=2)
    assert calls == ["windy", "windy"] and len(history) == 2
    assert history[0]["bias_m"] == pytest.approx([0.29, 0.31, 0.33])
    residual = [0.3 + 0.02 * (d - 8) + 0.8 * o for d, o in zip(table["distances_m"], table["downrange_offset_m"])]
    assert np.abs(residual).max() < 1e-3
    assert table["crossrange_offset_m"] == [0.0, 0.0, 0.0]  # 2D aims along its plane only


def test_adapt_writes_a_version_with_the_fitted_profile(monkeypatch, sealed, tmp_path):
    monkeypatch.setattr(ad, "_measure", lambda policy, mode, pp, distances, *a: {float(d): (-0.2, 0.0, 5, 0.1) for d in distances})
    report = {"which": [{"effect": "release_delay", "params": {"mean_s": 0.34}, "sigma": {"mean_s": 0.004, "jitter_s": None}}]}
    prof = RealityProfile.from_dict({"name": "fitted-release_delay", "effects": [{"effect": "release_delay", "params": {"mean_s": 0.34}}]})
    res = ad.adapt(prof, sealed[0], tmp_path, method="aim", diagnosis_report=report, throws=3, rounds=1, distances_m=[8.0])
    runner = PolicyRunner.load(res["policy"])
    assert res["name"] == "test-linear-fitted-release_delay" and res["method"] == "aim"
    assert runner.aim_correction.offsets_at(8.0) == pytest.approx((0.2, 0.0))
    assert runner.manifest["site_profile"]["uncertainty"] == {"release_delay.mean_s": {"sigma": 0.004}}
    assert (tmp_path / f"{res['name']}.adaptation.json").is_file()
    with pytest.raises(ValueError, match="method"):
        ad.adapt(prof, sealed[0], tmp_path, method="magic")
    with pytest.raises(ValueError, match="checkpoint"):
        ad.adapt(prof, sealed[0], tmp_path, method="finetune")


def test_finetune_config_fixes_the_profiles_effects():
    cfg = {"env": {"mode": "2d", "randomization": {"dead_band": [0.03, 0.07], "valve_delay_s": [0.02, 0.06], "lag_s": [0.07, 0.13],
                                                   "release_delay_mean_s": 0.258, "release_delay_std_s": 0.015, "release_delay_shift_s": 0.01}}}
    prof = RealityProfile.load(ad.Path(ad.__file__).parent.parent / "profiles" / "worn_gripper.json")
    prof.effects.append(RealityProfile.from_dict({"effects": [{"effect": "valve_delay", "params": {"delay_s": 0.12}}]}).effects[0])
    prof.effects.append(RealityProfile.from_dict({"effects": [{"effect": "payload_drag", "params": {"drag_coefficient": 0.4}}]}).effects[0])
    new, fixed, unsupported = ad.finetune_config(cfg, prof)
    rand = new["env"]["randomization"]
    assert rand["valve_delay_s"] == [0.12, 0.12] and rand["release_delay_mean_s"] == 0.34 and rand["release_delay_std_s"] == 0.03
    assert rand["release_delay_shift_s"] == 0.0 and rand["dead_band"] == [0.05, 0.05]
    assert fixed["lag_s"] == pytest.approx(NOMINAL_LAG_S) and unsupported == ["payload_drag"]
    assert cfg["env"]["randomization"]["valve_delay_s"] == [0.02, 0.06]  # the base config is left alone
    # the critic's privileged inputs stay normalised over the base ranges, also after a second fine-tuning
    kept = {"dead_band": [0.03, 0.07], "valve_delay_s": [0.02, 0.06], "lag_s": [0.07, 0.13],
            "release_delay_mean_s": 0.258, "release_delay_std_s": 0.015, "release_delay_shift_s": 0.01}
    assert new["env"]["privileged_ranges"] == kept
    assert ad.finetune_config(new, prof)[0]["env"]["privileged_ranges"] == kept


def test_console_flow_diagnosis_to_adapted_version(client, monkeypatch, tmp_path):
    """POST /api/diagnosis/runs/{id}/adapt on a finished diagnosis makes a policy version (fake
    twin evaluation inside the adaptation; the version's own evaluation is not run here)."""
    monkeypatch.setattr(ad, "_measure", lambda policy, mode, pp, distances, *a: {float(d): (0.25, 0.0, 5, 0.1) for d in distances})
    from server.jobs import tasks as job_tasks

    monkeypatch.setitem(job_tasks.RUNNERS, "evaluation", lambda ctx, job, progress: {})  # the version's own
    base = write_test_policy(tmp_path, "2d", name="base-2d")
    client.app.state.store.register_policy(json.loads(base.with_suffix(".json").read_text()), onnx_path=base)
    run_id = finished_diagnosis_run(client.app.state, "m1", {"which": [{"effect": "release_delay", "sigma": {"mean_s": 0.01}}]},
                                    {"name": "fitted-release_delay", "effects": [{"effect": "release_delay", "params": {"mean_s": 0.34}}]})
    assert client.post("/api/diagnosis/runs/00000000-0000-0000-0000-000000000000/adapt", json={"mode": "2d"}).status_code == 404
    assert client.post(f"/api/diagnosis/runs/{run_id}/adapt", json={"mode": "2d", "base_version": "nope"}).status_code == 409
    r = client.post(f"/api/diagnosis/runs/{run_id}/adapt", json={"mode": "2d", "base_version": "base-2d", "throws": 2, "rounds": 1})
    assert r.status_code == 202, r.text
    client.app.state.adaptation_runs.wait(120)
    st = client.get(f"/api/adaptations/{r.json()['id']}").json()
    assert st["status"] == "done", st
    assert st["progress"] and st["policy_version"].startswith("base-2d-m1-")
    versions = {v["name"]: v for v in client.get("/api/policies").json()}
    assert st["policy_version"] in versions and versions[st["policy_version"]]["has_file"]
    assert client.get("/api/adaptations").json()[0]["id"] == st["id"]
    assert client.get("/api/adaptations/nope").status_code == 404
