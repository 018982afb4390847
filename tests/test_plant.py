"""The simulated machine process's logic without Zenoh: TwinMachine bookkeeping and one plant
period (valve watchdog, resets, malformed commands)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from runtime.protocol.messages import GripperCommand, SimReset, ValidationError, ValveCommand, encode
from sim_twin.twin.initial_pose import pose_is_valid
from sim_twin.twin.plant import VALVE_WATCHDOG_S, PlantInbox, plant_tick
from sim_twin.twin.realtime import BEHIND_FAULT_S, RECOVER_S, RealTimeGuard
from sim_twin.twin.simulated_machine import SimulatedMachine
from sim_twin.twin.twin_machine import RELOAD_AFTER_LANDING_S, TwinMachine, run_throw


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
    assert twin.sim.data.qpos[0] == 0.0 and twin.state().reset_count == 0
    for _ in range(50):
        twin.step(np.array([0.5, 0.0, 0.0, 0.0]), False)  # turn the cabin
    yaw, t_before = twin.sim.data.qpos[0], twin.state().stamp_s
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
    inbox.on_valve(_sample(ValveCommand(machine_id="m1", stamp_s=time.monotonic(), u=[0.0, 0.0, 0.0, 1.0])))
    t0 = inbox.valve_rx_s
    for k in range(30):
        inbox.valve_rx_s = t0 + 0.01 * k - 0.09  # commands keep arriving, 90 ms old at worst
        plant_tick(twin, inbox, t0 + 0.01 * k)
    assert twin.sim.qd[3] > 0.5 and not inbox.watchdog_tripped  # telescope moves out
    t1 = t0 + 0.3
    for k in range(100):  # stale: neutral (the valves answer after their delay and lag)
        plant_tick(twin, inbox, t1 + VALVE_WATCHDOG_S + 0.001 + 0.01 * k)
    assert abs(twin.sim.data.qvel[3]) < 0.01 and inbox.watchdog_tripped


def test_commands_for_other_machines_or_malformed_are_dropped():
    inbox = PlantInbox("m1")
    inbox.on_valve(_sample(ValveCommand(machine_id="m2", stamp_s=time.monotonic(), u=[1.0, 0.0, 0.0, 0.0])))
    inbox.on_valve(_sample(b'{"u": [NaN, 0, 0, 0]}'))
    inbox.on_gripper(_sample(b"nonsense"))
    assert not np.isfinite(inbox.valve_rx_s) and not inbox.gripper_open


def test_gripper_release_and_one_impact_report():
    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1"), PlantInbox("m1")
    inbox.on_gripper(_sample(GripperCommand(machine_id="m1", stamp_s=time.monotonic(), open=True)))
    reports = [r for k in range(300) if (r := plant_tick(twin, inbox, 10.0 + 0.01 * k)[1]) is not None]
    assert len(reports) == 1
    rep = reports[0]
    assert rep.impact_pos_m[2] == 0.0 and rep.opening_stamp_s < rep.impact_stamp_s <= rep.stamp_s + 1e-9
    inbox.on_reset(_sample(SimReset(machine_id="m1", stamp_s=0.0)))
    st, _ = plant_tick(twin, inbox, 20.0)
    assert st.payload_attached and not inbox.gripper_open and st.reset_count >= 1


def test_the_plant_reloads_by_itself_a_second_after_the_landing():
    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1"), PlantInbox("m1")
    inbox.on_gripper(_sample(GripperCommand(machine_id="m1", stamp_s=time.monotonic(), open=True)))
    landed_at = None
    for k in range(400):
        st, report = plant_tick(twin, inbox, 10.0 + 0.01 * k)
        if report is not None:
            landed_at = st.stamp_s
            assert st.reset_count == 0  # never while the payload flies
        if st.reset_count:
            break
    assert landed_at is not None and st.reset_count == 1
    assert st.stamp_s - landed_at == pytest.approx(RELOAD_AFTER_LANDING_S, abs=0.02)
    assert st.payload_attached and not st.gripper_open and not inbox.gripper_open
    assert np.all(np.abs(twin.sim.data.qvel) < 1e-6) and pose_is_valid(np, twin.sim.data.qpos)  # loaded, at rest
    for k in range(100):  # and it stays loaded: no second reload
        st, _ = plant_tick(twin, inbox, 20.0 + 0.01 * k)
    assert st.reset_count == 1


def test_run_throw_loads_an_unloaded_twin_first():
    twin = TwinMachine(SimulatedMachine(seed=0), "m1")
    for _ in range(60):
        twin.step(np.zeros(4), True)
    assert not twin.loaded

    class Refusing:
        def start(self, request, state):
            assert state.payload_attached and not state.gripper_open
            return "refused"

    assert run_throw(twin, Refusing(), None) == (None, "refused") and twin.reset_count == 1


def test_only_the_newest_runtime_epoch_drives_the_valves():
    inbox = PlantInbox("m1")

    def valve(u, epoch):
        inbox.on_valve(_sample(ValveCommand(machine_id="m1", stamp_s=time.monotonic(), u=[u, 0.0, 0.0, 0.0], epoch=epoch)))
        return inbox.valve_u[0]

    assert valve(0.1, None) == 0.1  # before any epoch: tools without a claim may drive
    assert valve(0.2, 5) == 0.2 and inbox.epoch == 5
    assert valve(0.3, 7) == 0.3 and inbox.epoch == 7  # a newer runtime takes over
    assert valve(0.4, 5) == 0.3 and valve(0.5, None) == 0.3  # the old one is ignored
    with pytest.raises(ValidationError):
        ValveCommand(machine_id="m1", stamp_s=time.monotonic(), u=[0.0] * 4, epoch=-1)


def test_real_time_guard_faults_and_recovers():
    guard = RealTimeGuard()
    assert guard.update(-0.008, 0.0) is None and guard.update(BEHIND_FAULT_S * 0.9, 0.01) is None
    assert guard.update(0.150, 0.02) == "behind real time by 150 ms"
    assert guard.update(0.060, 0.03) == "behind real time by 150 ms"  # the worst since it began
    t = 0.04
    while t < 0.04 + RECOVER_S - 0.02:
        assert guard.update(-0.005, t) is not None  # kept up, but not long enough yet
        t += 0.01
    assert guard.update(-0.005, 0.04 + RECOVER_S) is None
    assert guard.update(0.170, 2.0) == "behind real time by 170 ms"


def test_a_faulted_plant_holds_the_valves_neutral_and_says_why():
    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1"), PlantInbox("m1")
    inbox.on_valve(_sample(ValveCommand(machine_id="m1", stamp_s=time.monotonic(), u=[0.0, 0.0, 0.0, 1.0])))
    speeds = []
    for fault in ("behind real time by 150 ms", None):
        twin.fault = fault
        for k in range(40):  # the nominal valves answer after 0.10 s delay + 0.16 s lag
            inbox.valve_rx_s = 1.0 + 0.01 * k
            st, _ = plant_tick(twin, inbox, 1.0 + 0.01 * k)
        speeds.append(abs(st.qd[3]))
        assert st.machine_fault == fault
    assert speeds[0] < 0.05 < 0.5 < speeds[1]  # neutral while faulted, the command once it clears


def test_a_machine_at_rest_outside_the_envelope_stays_there():
    """No teleport: the runtime's return to the ready pose (tests/test_return_to_ready.py) is
    the way back, as on a real machine."""
    from sim_twin.twin.plant import REST_TICKS

    twin, inbox = TwinMachine(SimulatedMachine(seed=0), "m1"), PlantInbox("m1")
    twin.sim.reset(q_active=np.array([0.0, -0.5, 1.6, 1.8]))  # telescope at its end, loaded
    for k in range(REST_TICKS + 10):
        st, _ = plant_tick(twin, inbox, 0.01 * k)
    assert twin.reset_count == 0 and st.payload_attached and not st.gripper_open
    assert st.q[3] == pytest.approx(1.8, abs=0.01) and inbox.resting


def test_the_in_process_twin_runs_without_zenoh():
    """Evaluation, site matrices and previews drive the twin in process: they import nothing of
    Zenoh (a GPU machine training with its site-matrix gate beside it has no Zenoh installed)."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] == 'zenoh': raise ImportError('zenoh is not installed here')\n"
        "sys.meta_path.insert(0, Block())\n"
        "from sim_twin.twin.twin_machine import TwinMachine, run_throw\n"
        "import sim_twin.evaluation.evaluate, sim_twin.evaluation.matrix, sim_twin.preview.preview\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]
