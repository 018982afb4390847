"""The simulated machine process's logic without Zenoh: TwinMachine bookkeeping and one plant
period (valve watchdog, resets, malformed commands)."""

from __future__ import annotations

import numpy as np

from runtime.protocol.messages import GripperCommand, SimReset, ValveCommand, encode
from sim_twin.initial_pose import pose_is_valid
from sim_twin.plant import VALVE_WATCHDOG_S, PlantInbox, TwinMachine, plant_tick
from sim_twin.simulated_machine import SimulatedMachine


def _sample(msg) -> object:
    data = encode(msg) if not isinstance(msg, bytes) else msg

    class _P:
        def to_bytes(self):
            return data

    class _S:
        payload = _P()

    return _S()


def test_reset_keeps_the_cabin_angle_and_counts():
    twin = TwinMachine(SimulatedMachine(seed=0), "m1")
    assert twin.state().q[0] == 0.0 and twin.state().reset_count == 0
    for _ in range(50):
        twin.step(np.array([0.5, 0.0, 0.0, 0.0]), False)  # turn the cabin
    yaw, t_before = twin.sim.q[0], twin.state().stamp_s
    assert yaw > 0.05
    q = twin.apply_reset(SimReset(machine_id="m1", stamp_s=0.0, seed=7))
    assert q[0] == yaw and pose_is_valid(np, q)
    st = twin.state()
    assert st.reset_count == 1 and st.payload_attached and not st.gripper_open and st.simulated
    assert st.stamp_s >= t_before  # the clock keeps running across resets
    q2 = TwinMachine(SimulatedMachine(seed=99), "m1")
    q2.sim.reset(q_active=np.r_[yaw, q[1:4]])
    np.testing.assert_allclose(q2.apply_reset(SimReset(machine_id="m1", stamp_s=0.0, seed=7)), q)  # seeded
    fixed = twin.apply_reset(SimReset(machine_id="m1", stamp_s=0.0, q_active=[0.0, -0.5, 1.6, 0.9]))
    np.testing.assert_allclose(fixed[:4], [0.0, -0.5, 1.6, 0.9])


def test_valve_watchdog_neutralises_stale_commands():
    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1"), PlantInbox("m1")
    inbox.on_valve(_sample(ValveCommand(machine_id="m1", stamp_s=0.0, u=[0.0, 0.0, 0.0, 1.0])))
    t0 = inbox.valve_rx_s
    for k in range(30):
        inbox.valve_rx_s = t0 + 0.01 * k - 0.09  # commands keep arriving, 90 ms old at worst
        plant_tick(twin, inbox, t0 + 0.01 * k)
    assert twin.sim.qd[3] > 0.5 and not inbox.watchdog_tripped  # telescope moves out
    t1 = t0 + 0.3
    for k in range(60):
        plant_tick(twin, inbox, t1 + VALVE_WATCHDOG_S + 0.001 + 0.01 * k)  # stale: neutral
    assert abs(twin.sim.qd[3]) < 0.01 and inbox.watchdog_tripped


def test_commands_for_other_machines_or_malformed_are_dropped():
    inbox = PlantInbox("m1")
    inbox.on_valve(_sample(ValveCommand(machine_id="m2", stamp_s=0.0, u=[1.0, 0.0, 0.0, 0.0])))
    inbox.on_valve(_sample(b'{"u": [NaN, 0, 0, 0]}'))
    inbox.on_gripper(_sample(b"nonsense"))
    assert not np.isfinite(inbox.valve_rx_s) and not inbox.gripper_open


def test_gripper_release_and_one_impact_report():
    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1"), PlantInbox("m1")
    inbox.on_gripper(_sample(GripperCommand(machine_id="m1", stamp_s=0.0, open=True)))
    reports = [r for k in range(300) if (r := plant_tick(twin, inbox, 10.0 + 0.01 * k)[1]) is not None]
    assert len(reports) == 1
    rep = reports[0]
    assert rep.impact_pos_m[2] == 0.0 and rep.opening_stamp_s < rep.impact_stamp_s <= rep.stamp_s + 1e-9
    inbox.on_reset(_sample(SimReset(machine_id="m1", stamp_s=0.0)))
    st, _ = plant_tick(twin, inbox, 20.0)
    assert st.payload_attached and not inbox.gripper_open and st.reset_count == 1
