"""The simulated machine behaves like hydraulics: closed valves hold the load (no sag or drift at
neutral valves, also over a minute and while the plant process is stalled) and the joint ends
are hard stops (no telescope past its end, no gripper sinking towards the ground)."""

from __future__ import annotations

import numpy as np
import pytest

from runtime.machine import JOINT_LOWER, JOINT_UPPER, forward_kinematics
from sim_twin.twin.hydraulics import cylinder_step
from sim_twin.twin.plant import PlantInbox, plant_tick
from sim_twin.twin.twin_machine import TwinMachine
from sim_twin.twin.simulated_machine import SimulatedMachine

POSES = {
    "extended": [0.0, -0.2, 1.2, 1.7],  # telescope near its end, long lever on the boom
    "low": [0.5, -0.9, 2.2, 0.4],
}


def _centre(sim):
    return forward_kinematics(np, sim.data.qpos, sim.data.qvel).gripper_centre


@pytest.mark.parametrize("pose", POSES)
def test_closed_valves_hold_the_load_for_a_minute(pose):
    sim = SimulatedMachine(seed=0)
    q0 = sim.reset(q_active=np.array(POSES[pose]))
    for _ in range(3000):
        sim.step(np.zeros(4), False)
    q30, z30 = sim.data.qpos.copy(), _centre(sim)[2]
    for _ in range(3000):
        sim.step(np.zeros(4), False)
    assert np.all(np.abs(sim.data.qpos[:4] - q0[:4]) < 1e-3), sim.data.qpos[:4] - q0[:4]  # static deflection only
    assert np.all(np.abs(sim.data.qpos[:4] - q30[:4]) < 1e-6)  # and no drift at all
    assert abs(_centre(sim)[2] - z30) < 1e-5


def test_stalled_plant_holds_the_arm():
    """The runtime's last command was 'extend'; then the plant loop stalls for 20 s (the next
    ticks see a stale command): the watchdog sets the valves neutral and the arm stays put."""
    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1"), PlantInbox("m1")
    twin.sim.reset(q_active=np.array(POSES["extended"]))
    inbox.valve_u, inbox.valve_rx_s = np.array([0.0, -0.3, 0.0, 0.4]), 0.0
    for k in range(5):
        plant_tick(twin, inbox, 0.01 * k)
    for k in range(200):  # the ticks that follow the stall: ~1 s later the settled arm is held
        plant_tick(twin, inbox, 20.0 + 0.01 * k)
    q_settled = twin.sim.data.qpos.copy()
    for k in range(1800):
        plant_tick(twin, inbox, 22.0 + 0.01 * k)
    assert np.abs(twin.sim.data.qpos[:4] - q_settled[:4]).max() < 1e-6
    assert twin.sim.data.qpos[3] <= JOINT_UPPER[3]


def test_joint_ends_are_hard_stops_and_can_be_left():
    sim = SimulatedMachine(seed=0)
    sim.reset(q_active=np.array([0.0, -1.2, 2.6, 1.5]))
    for _ in range(500):  # boom down, dipper in, telescope out, all valves fully open for 5 s
        sim.step(np.array([0.0, -1.0, 1.0, 1.0]), False)
    lo, hi = JOINT_LOWER[:4], JOINT_UPPER[:4]
    q = sim.data.qpos
    assert q[1] >= lo[1] - 1e-3 and q[2] <= hi[2] + 1e-3 and q[3] <= hi[3] + 1e-3
    assert _centre(sim)[2] > 0.5  # the gripper stays above ground
    for _ in range(100):  # back off: the stop does not stick
        sim.step(np.array([0.0, 1.0, -1.0, -1.0]), False)
    assert q[1] > lo[1] + 0.05 and q[2] < hi[2] - 0.05 and q[3] < hi[3] - 0.05


def test_cylinder_step_stops_at_the_ends_and_holds():
    lo, hi = JOINT_LOWER[:4], JOINT_UPPER[:4]
    x = np.array([0.0, 0.43, 1.0, 1.79])
    x1, sp = cylinder_step(np, x, np.array([1.0, 1.0, 0.0, 1.0]), x, lo, hi, 0.01)
    np.testing.assert_allclose(x1, [0.01, 0.44, 1.0, 1.8])  # cabin unlimited, boom/telescope stop
    np.testing.assert_allclose(sp, [1.0, 1.0, 0.0, 1.0] * np.array([1, 1, 0, 1]) + 10.0 * (x1 - x))
    _, sp_hold = cylinder_step(np, x, np.zeros(4), x - np.array([0, 0.001, 0, 0]), lo, hi, 0.01)
    assert sp_hold[1] > 0 and np.all(sp_hold[[0, 2, 3]] == 0)  # sagged joint is pulled back
