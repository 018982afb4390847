"""The effects library: each effect changes the simulated machine as documented, the nominal
machine is unchanged, profiles carry effects (library and user code) and bad ones fail clearly."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from runtime.machine import ACTIVE_VELOCITY_LIMITS, forward_kinematics
from sim_twin.twin.effects import EFFECTS, Effect, effect_from_dict, load_effect, make_effect
from sim_twin.twin.effects.payload import integrate_flight
from sim_twin.twin.physics import ballistic_impact_time, ballistic_position
from sim_twin.twin.profile import RealityProfile, SensorParams
from sim_twin.twin.simulated_machine import SimulatedMachine

POSE = [0.0, -0.6, 1.5, 0.9]


def machine(*effects: Effect, **profile) -> SimulatedMachine:
    profile.setdefault("sensing", SensorParams.ideal())  # exact comparisons: perfect sensors
    sim = SimulatedMachine(RealityProfile(effects=list(effects), **profile), seed=0)
    sim.reset(q_active=POSE)
    return sim


def run(sim: SimulatedMachine, u, steps: int, gripper: bool = False) -> tuple[np.ndarray, np.ndarray]:
    qs, qds = [], []
    for _ in range(steps):
        sim.step(np.asarray(u, dtype=float), gripper)
        qs.append(sim.q)
        qds.append(sim.qd)
    return np.array(qs), np.array(qds)


def test_effects_at_nominal_values_reproduce_the_nominal_machine():
    u = [0.0, 0.6, -0.5, 0.8]
    q_ref, qd_ref = run(machine(), u, 120)
    for name, cls in EFFECTS.items():
        q, qd = run(machine(cls()), u, 120)
        np.testing.assert_allclose(q, q_ref, atol=1e-9, err_msg=name)
        np.testing.assert_allclose(qd, qd_ref, atol=1e-9, err_msg=name)


def test_every_library_effect_documents_its_parameters():
    for name, cls in EFFECTS.items():
        d = cls.describe()
        assert d["name"] == name and d["summary"] and d["params"]
        for p in d["params"]:
            assert p["unit"] and p["doc"] and p["source"] and p["lo"] <= p["nominal"] <= p["hi"]


def test_release_delay_sets_when_the_payload_is_free():
    sim = machine(make_effect("release_delay", mean_s=0.5, jitter_s=0.0))
    run(sim, np.zeros(4), 1, gripper=True)
    t_cmd = sim.time_s - 0.01
    while sim.payload_attached:
        sim.step(np.zeros(4), True)
    assert sim.time_s - t_cmd == pytest.approx(0.5, abs=0.0101)


def test_passive_friction_damps_the_swing():
    def swing_amplitude(viscous):
        sim = machine(make_effect("passive_friction", viscous_per_s=viscous))
        run(sim, [0, 0, 0, 1.0], 60)  # telescope out fast, then stop: the gripper swings
        q, _ = run(sim, np.zeros(4), 300)
        return np.ptp(q[-100:, 4])

    assert swing_amplitude(1.5) < 0.3 * swing_amplitude(0.03)


def test_valve_dead_band_swallows_small_commands():
    small = [0, 0, 0, 0.12]
    _, qd_nom = run(machine(), small, 50)
    _, qd_db = run(machine(make_effect("valve_dead_band", dead_band=0.2)), small, 50)
    assert qd_nom[-1, 3] > 0.05 and abs(qd_db[-1, 3]) < 0.1 * qd_nom[-1, 3]  # servo sag only


def test_valve_delay_and_lag_shape_the_step_response():
    def first_motion(sim):
        _, qd = run(sim, [0, 0, 0, 1.0], 60)
        return int(np.argmax(qd[:, 3] > 0.01))

    from sim_twin.twin.hydraulics import NOMINAL_DELAY_S

    shift = first_motion(machine(make_effect("valve_delay", delay_s=0.2))) - first_motion(machine())
    assert shift == pytest.approx(round((0.2 - NOMINAL_DELAY_S) / 0.01), abs=1)
    _, qd = run(machine(make_effect("valve_lag", lag_s=0.4)), [0, 0, 0, 1.0], 200)
    t63 = (np.argmax(qd[:, 3] > 0.63 * ACTIVE_VELOCITY_LIMITS[3]) + 1) * 0.01
    assert t63 == pytest.approx(NOMINAL_DELAY_S + 0.4, abs=0.05)  # transport delay + time constant


def test_joint_rate_limit_caps_the_speed():
    _, qd = run(machine(make_effect("joint_rate_limit", fraction=0.6)), [0, 1.0, 0, 1.0], 100)
    assert np.abs(qd[-1, [1, 3]]) == pytest.approx(0.6 * ACTIVE_VELOCITY_LIMITS[[1, 3]], rel=0.02)


def test_cabin_drift_turns_the_cabin_while_the_arm_moves():
    q_pos, _ = run(machine(make_effect("cabin_drift", rate_per_arm_speed=0.08)), [0, 0.8, -0.8, 0], 100)
    q_neg, _ = run(machine(make_effect("cabin_drift", rate_per_arm_speed=-0.08)), [0, 0.8, -0.8, 0], 100)
    q_nom, _ = run(machine(), [0, 0.8, -0.8, 0], 100)
    assert q_pos[-1, 0] > 0.02 and q_neg[-1, 0] < -0.02 and abs(q_nom[-1, 0]) < 1e-3


def test_hanging_mass_changes_the_pendulum_period():
    def period(mass):
        sim = machine(make_effect("hanging_mass", gripper_mass_kg=mass), passive_viscous_per_s=0.0, passive_coulomb_rad_per_s2=0.0)
        sim.data.qpos[4] += 0.3
        q, _ = run(sim, np.zeros(4), 600)
        x = q[:, 4] - np.mean(q[:, 4])
        ups = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
        return np.mean(np.diff(ups)) * 0.01

    # arm held rigid by its cylinders: 400 -> 839 -> 2000 kg gives 2.02 -> 2.09 -> 2.13 s
    assert period(2000.0) > period(839.0) * 1.01 > period(400.0) * 1.02


def test_imu_latency_delays_and_noise_perturbs_the_passive_measurement():
    sim = machine(make_effect("imu_passive", latency_s=0.1))
    run(sim, [0, 0, 0, 1.0], 60)
    true_hist = []
    for _ in range(50):
        sim.step(np.zeros(4), False)
        true_hist.append(sim.data.qpos[4])
        if len(true_hist) > 10:
            assert sim.q[4] == pytest.approx(true_hist[-11], abs=1e-12)
        assert sim.q[1] == sim.data.qpos[1]  # encoders unaffected
    noisy = machine(make_effect("imu_passive", angle_noise_rad=0.01))
    errs = []
    for _ in range(400):
        noisy.step(np.zeros(4), False)
        errs.append(noisy.q[4] - noisy.data.qpos[4])
    assert np.std(errs) == pytest.approx(0.01, rel=0.15)


def test_grasp_offset_moves_the_held_payload():
    sim = machine(make_effect("grasp_offset", forward_m=0.2, up_m=-0.1))
    pos, _ = sim.payload_state()
    centre = forward_kinematics(np, sim.data.qpos, sim.data.qvel).gripper_centre
    assert np.linalg.norm(pos - centre) == pytest.approx(np.hypot(0.2, 0.1), abs=1e-9)


def test_payload_drag_shortens_the_flight_and_zero_drag_matches_the_ballistic_solution():
    p0, v0 = np.array([6.0, 0.0, 3.0]), np.array([6.0, 0.0, 2.0])
    t_hit = float(ballistic_impact_time(np, p0, v0, 0.12))
    _, _, _, t_num, hit0 = integrate_flight(p0, v0, None)
    assert float(t_num) == pytest.approx(t_hit, abs=1e-4)  # linear interpolation within one RK4 step
    np.testing.assert_allclose(hit0[:2], ballistic_position(np, p0, v0, t_hit)[:2], atol=1e-3)
    drag = make_effect("payload_drag", drag_coefficient=1.0)
    _, _, _, _, hit = integrate_flight(p0, v0, drag.flight_accel)
    assert hit0[0] - hit[0] > 0.1
    sim = machine(drag)
    run(sim, [0, -1.0, 0, 1.0], 60)
    while sim.payload_attached:
        sim.step(np.array([0, -1.0, 0, 1.0]), True)
    assert np.linalg.norm(sim.payload_state()[1]) > 1.0
    while sim.impact is None:
        sim.step(np.zeros(4), True)
    r = sim.impact
    free = ballistic_position(np, r.release_pos_m, r.release_vel_mps, ballistic_impact_time(np, r.release_pos_m, r.release_vel_mps, 0.12))
    assert np.hypot(*r.impact_pos_m[:2]) < np.hypot(*free[:2]) - 0.005


def test_profile_json_with_library_and_user_effects_round_trips(tmp_path: Path):
    data = {"name": "quirky", "release_delay_mean_s": 0.3, "hydraulics": {"lag_s": 0.2},
            "effects": [{"effect": "payload_drag", "params": {"drag_coefficient": 0.5}},
                        {"effect": "sim_twin.diagnosis.unmodelled:CrossWind", "params": {"wind_mps": 3.0}}]}
    path = tmp_path / "p.json"
    path.write_text(json.dumps(data))
    prof = RealityProfile.load(path)
    assert [e.name for e in prof.effects] == ["payload_drag", "cross_wind"] and prof.hydraulics.lag_s[0] == 0.2
    again = RealityProfile.from_dict(json.loads(json.dumps(prof.to_dict())))
    assert [e.values for e in again.effects] == [e.values for e in prof.effects]
    assert RealityProfile.from_dict({"name": "old", "release_delay_std_s": 0.0}).effects == []  # old keys still work


def test_example_profiles_load():
    files = sorted((Path(__file__).parent.parent / "sim_twin" / "profiles").glob("*.json"))
    assert files
    for f in files:
        SimulatedMachine(RealityProfile.load(f), seed=0).step(np.zeros(4), False)


@pytest.mark.parametrize("entry, message", [
    ({"effect": "no_such_effect"}, "unknown effect 'no_such_effect'"),
    ({"effect": "nosuchpkg.mod:Thing"}, "cannot import module 'nosuchpkg.mod'"),
    ({"effect": "sim_twin.twin.effects.base:Nope"}, "has no 'Nope'"),
    ({"effect": "sim_twin.twin.effects.base:Param"}, "not a subclass of sim_twin.twin.effects.Effect"),
    ({"effect": "payload_drag", "params": {"cd": 1}}, "unknown parameters ['cd']"),
    ({"effect": "payload_drag", "params": {"drag_coefficient": 9}}, "outside its range"),
    ({"effect": "valve_lag", "params": {"lag_s": float("nan")}}, "must be finite"),
    ({"effekt": "valve_lag"}, "needs an 'effect' key"),
])
def test_bad_effects_fail_with_a_clear_error(entry, message):
    with pytest.raises(ValueError, match=None) as e:
        effect_from_dict(entry)
    assert message in str(e.value)
    with pytest.raises(ValueError):
        RealityProfile.from_dict({"effects": [entry]})


def test_load_effect_returns_the_user_class():
    cls = load_effect("sim_twin.diagnosis.unmodelled:BoomCompliance")
    assert cls.name == "boom_compliance" and cls.spec() == "sim_twin.diagnosis.unmodelled:BoomCompliance"
    q, _ = run(machine(cls(coupling=0.3)), [0, 0, 0, 1.0], 80)
    q_nom, _ = run(machine(), [0, 0, 0, 1.0], 80)
    assert np.max(np.abs(q[:, 1] - q_nom[:, 1])) > 1e-3
