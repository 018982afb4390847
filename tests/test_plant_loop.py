"""The plant's real-time loop (sim_twin.twin.plant._loop) with stand-in publishers, without Zenoh: a
resting machine sleeps between its 20 Hz publications, a command wakes it at once, and a resting
plant that falls behind real time still says so."""

from __future__ import annotations

import threading
import time

import numpy as np

import sim_twin.twin.plant as plant
from runtime.protocol.messages import GripperCommand, MachineState, ValveCommand, decode
from sim_twin.twin.plant import PlantInbox
from sim_twin.twin.twin_machine import TwinMachine
from sim_twin.twin.simulated_machine import SimulatedMachine
from tests.conftest import wait_for
from tests.test_plant import _sample


class Pub:
    """Collects what the loop publishes; ``stall_s``: the next put while resting sleeps this long."""

    def __init__(self, inbox: PlantInbox):
        self.inbox, self.states, self.stall_s = inbox, [], 0.0

    def put(self, payload: bytes) -> None:
        self.states.append(decode(MachineState, payload))
        if self.stall_s and self.inbox.resting:
            stall, self.stall_s = self.stall_s, 0.0
            time.sleep(stall)


def _running_loop(monkeypatch):
    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1", clock=time.monotonic), PlantInbox("m1")
    ticks = []
    real_tick = plant.plant_tick
    monkeypatch.setattr(plant, "plant_tick", lambda *a: (ticks.append(time.monotonic()), real_tick(*a))[1])
    pub, stop = Pub(inbox), threading.Event()
    th = threading.Thread(target=plant._loop, args=(twin, inbox, pub, Pub(inbox), stop), daemon=True)
    th.start()
    return twin, inbox, pub, ticks, stop, th


def test_resting_loop_sleeps_between_publications_and_a_command_wakes_it(monkeypatch):
    twin, inbox, pub, ticks, stop, th = _running_loop(monkeypatch)
    try:
        wait_for(lambda: inbox.resting, 20, "plant at rest")
        t0, n0, s0 = time.monotonic(), len(ticks), len(pub.states)
        time.sleep(1.0)  # on a loaded host this thread may wake late: the rate is per second of the real window
        rest_ticks, rest_states, window_s = len(ticks) - n0, len(pub.states) - s0, time.monotonic() - t0
        assert rest_ticks <= 30 * window_s, (rest_ticks, window_s)  # 20 per second (100 before)
        assert rest_states >= 3 and rest_states >= rest_ticks - 1  # each resting wake publishes
        inbox.on_valve(_sample(ValveCommand(machine_id="m1", stamp_s=time.monotonic(), u=[0.0] * 4)))
        assert not inbox.wake.is_set()  # neutral valves (the runtime's 20 Hz feed) leave it resting
        inbox.on_valve(_sample(ValveCommand(machine_id="m1", stamp_s=time.monotonic(), u=[0.0, 0.0, 0.0, 1.0])))
        wait_for(lambda: not inbox.resting, 5, "plant awake")
        n1 = len(ticks)
        while len(ticks) - n1 < 20:  # keep the command fresh (valve watchdog) while it moves
            inbox.on_valve(_sample(ValveCommand(machine_id="m1", stamp_s=time.monotonic(), u=[0.0, 0.0, 0.0, 1.0])))
            time.sleep(0.01)
        assert not inbox.resting and abs(twin.sim.qd[3]) > 0.0
    finally:
        stop.set()
        th.join(5)


def test_gripper_change_wakes_a_resting_plant_and_a_repeat_does_not(monkeypatch):
    inbox = PlantInbox("m1")
    inbox.on_gripper(_sample(GripperCommand(machine_id="m1", stamp_s=0.0, open=False)))
    assert not inbox.wake.is_set()
    inbox.on_gripper(_sample(GripperCommand(machine_id="m1", stamp_s=time.monotonic(), open=True)))
    assert inbox.wake.is_set()


def test_a_resting_plant_that_falls_behind_says_so(monkeypatch):
    twin, inbox, pub, ticks, stop, th = _running_loop(monkeypatch)
    try:
        # at rest and keeping time: on a loaded host the loop's first ticks may fall behind on their own
        # (a fault it then clears, tests/test_plant.py::test_real_time_guard_faults_and_recovers); wait that out
        wait_for(lambda: inbox.resting and len(pub.states) >= 5 and all(s.machine_fault is None for s in pub.states[-5:]),
                 20, "plant at rest, no fault")
        n0 = len(pub.states)
        pub.stall_s = 0.3  # the loop thread stalls 300 ms (a starved process)
        wait_for(lambda: any((s.machine_fault or "").startswith("behind real time") for s in pub.states[n0:]), 5,
                 "real-time fault published")
        worst = max(int(s.machine_fault.split()[-2]) for s in pub.states[n0:] if s.machine_fault)
        assert worst >= 200, worst
    finally:
        stop.set()
        th.join(5)
    assert np.isfinite(twin.sim.q).all()
