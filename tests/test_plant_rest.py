"""A simulated machine at rest costs little: with neutral valves and every joint still it is no
longer integrated (its state is re-stamped, published at 20 Hz), and any command wakes it."""

from __future__ import annotations

import time

import numpy as np

from runtime.protocol.messages import GripperCommand, ValveCommand, encode
from sim_twin.twin.plant import REST_TICKS, PlantInbox, plant_tick
from sim_twin.twin.twin_machine import TwinMachine
from sim_twin.twin.simulated_machine import SimulatedMachine


class _Sample:
    def __init__(self, msg):
        self.payload = type("P", (), {"to_bytes": lambda _self, b=encode(msg): b})()


def test_resting_machine_is_not_integrated_and_wakes_on_a_command():
    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1", clock=time.monotonic), PlantInbox("m1")
    for k in range(REST_TICKS + 20):
        plant_tick(twin, inbox, 0.01 * k)
    assert inbox.resting
    sim_t, q = twin.sim.time_s, twin.sim.q.copy()
    stamps = [plant_tick(twin, inbox, 1.0 + 0.01 * k)[0].stamp_s for k in range(30)]
    assert twin.sim.time_s == sim_t and np.array_equal(twin.sim.q, q)  # nothing integrated
    assert all(b > a for a, b in zip(stamps, stamps[1:]))  # but the state is fresh
    inbox.on_valve(_Sample(ValveCommand(machine_id="m1", stamp_s=time.monotonic(), u=[0.0, 0.0, 0.0, 1.0])))
    for k in range(30):
        inbox.valve_rx_s = 2.0 + 0.01 * k
        st, _ = plant_tick(twin, inbox, 2.0 + 0.01 * k)
    assert not inbox.resting and twin.sim.time_s > sim_t and st.qd[3] > 0.1  # the telescope moves out


def test_a_falling_payload_keeps_the_machine_awake():
    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1"), PlantInbox("m1")
    for k in range(REST_TICKS + 20):
        plant_tick(twin, inbox, 0.01 * k)
    assert inbox.resting
    inbox.on_gripper(_Sample(GripperCommand(machine_id="m1", stamp_s=time.monotonic(), open=True)))
    reports = [r for k in range(300) if (r := plant_tick(twin, inbox, 5.0 + 0.01 * k)[1]) is not None]
    assert len(reports) == 1 and reports[0].impact_pos_m[2] == 0.0
