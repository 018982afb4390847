"""The machine in Drake (sim_twin.twin.drake_machine): the same model as the MuJoCo twin, moved by
another engine, with the shared valves, cylinders, release and flight."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from sim_twin.twin.drake_machine import DrakeMachine
from sim_twin.twin.effects import make_effect
from sim_twin.twin.profile import RealityProfile
from sim_twin.twin.simulated_machine import SimulatedMachine

POSE = [0.0, -0.6, 1.5, 0.9]


@pytest.fixture(scope="module")
def drake():
    return DrakeMachine(seed=1)


def test_drake_model_has_the_twins_kinematics_and_mass_matrix(drake):
    sim = SimulatedMachine(seed=1)
    rng = np.random.default_rng(0)
    for _ in range(4):
        q = np.array([rng.uniform(-2, 2), rng.uniform(-1.2, 0.3), rng.uniform(0.7, 2.6), rng.uniform(0, 1.7),
                      rng.uniform(-2, 1), rng.uniform(-0.6, 0.6)])
        qd = rng.normal(size=6) * 0.4
        drake.set_state(q, qd)
        sim.set_state(q, qd)
        p_d, v_d = drake.payload_state()
        p_m, v_m = sim.payload_state()
        np.testing.assert_allclose(p_d, p_m, atol=1e-9)
        np.testing.assert_allclose(v_d, v_m, atol=1e-6)
        m_mj = np.zeros((6, 6))
        mujoco.mj_fullM(sim.model, sim.data, m_mj)
        m_dr = drake._plant.CalcMassMatrix(drake._pctx)[np.ix_(drake._v_index, drake._v_index)]  # noqa: SLF001
        np.testing.assert_allclose(m_dr, m_mj, rtol=1e-9, atol=1e-6)


def test_closed_valves_hold_the_arm_and_the_gripper_swings_like_the_twins(drake):
    sim = SimulatedMachine(seed=1)
    q0 = np.array([*POSE, -0.9 + 0.3, 0.2])
    drake.set_state(q0, np.zeros(6))
    sim.set_state(q0, np.zeros(6))
    for _ in range(200):
        drake.step(np.zeros(4), False)
        sim.step(np.zeros(4), False)
    np.testing.assert_allclose(drake.data.qpos[:4], q0[:4], atol=1e-3)  # no sag at neutral valves
    assert np.ptp([drake.data.qpos[4], q0[4]]) > 0.05  # it did swing
    np.testing.assert_allclose(drake.data.qpos[4:], sim.data.qpos[4:], atol=0.02)


def test_valve_commands_move_the_joints_like_the_twins(drake):
    sim = SimulatedMachine(seed=1)
    drake.reset(q_active=POSE)
    sim.reset(q_active=POSE)
    u = np.array([0.5, 0.6, -0.5, 0.7])
    for _ in range(100):
        drake.step(u, False)
        before = sim.data.qpos[:4].copy()
        sim.step(u, False)
    moved = drake.data.qpos[:4] - np.array(POSE)
    assert np.all(np.abs(moved) > 0.05)
    # the twin's semi-implicit 10 ms step puts its joints one period ahead of the oil column;
    # Drake's follow the column: Drake now is where the twin was one period ago
    np.testing.assert_allclose(drake.data.qpos[:4], before, atol=1.5e-3)
    assert np.abs(drake.data.qpos[:4] - sim.data.qpos[:4]).max() > 3e-3


def test_passive_friction_is_drakes_joint_damping_with_the_papers_values(drake):
    from sim_twin.twin.model import passive_inertia

    for joint, inertia in zip(drake._passive_joints, passive_inertia()):  # noqa: SLF001
        assert joint.GetDamping(drake._pctx) == pytest.approx(0.03 * inertia)  # noqa: SLF001
    assert drake._coulomb.coulomb == pytest.approx(0.1)  # noqa: SLF001


def test_release_after_the_opening_delay_and_drag_shortens_the_flight():
    shots = {}
    for name, effects in (("free", []), ("drag", [make_effect("payload_drag", drag_coefficient=0.5)])):
        m = DrakeMachine(RealityProfile(release_delay_std_s=0.0, effects=effects), seed=3)
        m.reset(q_active=POSE)
        for _ in range(150):  # swing boom and telescope up and out, then open
            m.step(np.array([0.0, -1.0, 0.0, 1.0]), False)
        for k in range(400):
            m.step(np.array([0.0, -1.0, 0.0, 1.0]), True)
            if m.gripper_open and "open_at" not in shots.get(name, {}):
                shots[name] = {"open_at": k}
            if m.impact is not None:
                break
        assert m.impact is not None
        shots[name]["impact"] = m.impact
    assert shots["free"]["open_at"] * 0.01 == pytest.approx(0.258, abs=0.011)
    free, drag = shots["free"]["impact"], shots["drag"]["impact"]
    np.testing.assert_allclose(free.release_pos_m, drag.release_pos_m, atol=1e-9)
    assert np.linalg.norm(drag.impact_pos_m[:2] - free.release_pos_m[:2]) < np.linalg.norm(free.impact_pos_m[:2] - free.release_pos_m[:2]) - 0.01


def test_a_model_editing_effect_is_refused():
    with pytest.raises(ValueError, match="hanging_mass"):
        DrakeMachine(RealityProfile(effects=[make_effect("hanging_mass", gripper_mass_kg=1000.0)]))


def test_the_deployed_2d_policy_lands_near_its_target_in_drake():
    from sim_twin.evaluation.evaluate import throw_batch

    rows = throw_batch("policies/throw2d.onnx", "2d", 8.5, [0], engine="drake")
    assert rows[0]["status"] == "landed", rows
    assert abs(rows[0]["downrange_error_m"]) < 0.5 and abs(rows[0]["crossrange_error_m"]) < 0.5


def test_a_full_valve_gives_the_twins_steady_joint_speed_at_every_period_end(drake):
    """The oil column moves during the period (sim_twin.twin.drake_machine._oil_column_system): the
    speed sampled at each period's end is the flow's, not ~4 % below it as with a held target."""
    sim = SimulatedMachine(seed=0)
    for m in (drake, sim):
        m.reset(q_active=[0.0, -0.6, 1.5, 0.3])
    for _ in range(120):
        drake.step(np.array([0.0, 0.0, 0.0, 1.0]), False)
        sim.step(np.array([0.0, 0.0, 0.0, 1.0]), False)
    assert drake.data.qvel[3] == pytest.approx(0.75, abs=0.003)
    assert drake.data.qvel[3] == pytest.approx(sim.data.qvel[3], abs=0.002)


def test_the_step_must_divide_the_period():
    with pytest.raises(ValueError, match="divide"):
        DrakeMachine(time_step_s=0.003)
