"""The simulated machine: the CPU MuJoCo twin driven through the hydraulic valve model, with the
gripper's opening delay and the payload's flight, plus the effects of its reality profile
(:mod:`sim_twin.twin.effects`: valve parameters, setpoint disturbances, passive friction, masses,
release delay, grasp offset, flight drag, measurement latency and noise). It stands in for the hardware; the Zenoh
process around it is :mod:`sim_twin.twin.plant`, and evaluation and previews drive it directly.

One :meth:`SimulatedMachine.step` is one 10 ms physics period. Closed valves hold the load and
the joint ends are hard stops (:func:`sim_twin.twin.hydraulics.cylinder_step`), however many steps run
with neutral valves (e.g. while the plant process is stalled).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from runtime.machine import JOINT_LOWER, JOINT_UPPER, NUM_ACTIVE, forward_kinematics
from sim_twin.twin.effects.payload import grasp_point, integrate_flight
from sim_twin.twin.hydraulics import ValveModel, cylinder_step
from sim_twin.twin.initial_pose import sample_pose
from sim_twin.twin.model import (
    PAYLOAD_RADIUS_M,
    fresh_model,
    passive_inertia,
    passive_inertia_of,
)
from sim_twin.twin.physics import (
    ballistic_impact_time,
    ballistic_position,
    passive_friction_force,
)
from sim_twin.twin.profile import RealityProfile


@dataclass
class Impact:
    """Payload flight summary; positions in the machine frame (m), times in simulated seconds.
    ``impact_pos_m`` is the measured landing spot (true one + the profile's impact noise)."""

    impact_pos_m: np.ndarray
    opening_time_s: float
    impact_time_s: float
    release_pos_m: np.ndarray
    release_vel_mps: np.ndarray


def _shifted(hist: np.ndarray, newest: np.ndarray) -> np.ndarray:
    """A new (N, 6) history: ``newest`` (6,) in row 0, ``hist``'s rows 0..N-2 in rows 1..N-1."""
    out = np.empty_like(hist)
    out[1:] = hist[:-1]
    out[0] = newest
    return out


class MachineReadout:
    """What a simulated machine reports, and how it keeps its gripper opening, release and landing,
    whatever engine moves it (:class:`SimulatedMachine`: MuJoCo; :class:`sim_twin.twin.drake_machine.DrakeMachine`:
    Drake).

    A subclass sets, in its constructor and ``reset``: ``data`` (``qpos`` (6,) rad, ``qvel`` (6,) rad/s),
    ``effects``, ``rng``, ``_meas_rng``, ``_fx_measure``, ``_delay_mean_s``, ``_delay_std_s``, ``_impact_noise_m``,
    ``_hist_q``/``_hist_qd`` (measurement history, newest first), ``_meas_q``/``_meas_qd``, ``_open_at``, ``_attached``,
    ``_opened``, ``_landed``, ``_release`` and ``_impact``; it provides ``time_s``, ``_measure`` and ``_open_payload``.
    """

    data: Any
    effects: Any
    rng: np.random.Generator
    _meas_rng: np.random.Generator
    _fx_measure: bool
    _delay_mean_s: float
    _delay_std_s: float
    _impact_noise_m: float
    _hist_q: np.ndarray
    _hist_qd: np.ndarray
    _meas_q: np.ndarray
    _meas_qd: np.ndarray
    _open_at: float | None
    _attached: bool
    _opened: bool
    _landed: bool
    _release: tuple[np.ndarray, np.ndarray, float] | None
    _impact: Impact | None

    @property
    def time_s(self) -> float:
        """Simulated seconds (the subclass's clock)."""
        raise NotImplementedError

    def _measure(self) -> None:
        """Update ``_meas_q``/``_meas_qd`` from the history (the subclass's physics period)."""
        raise NotImplementedError

    def _open_payload(self) -> None:
        """Release the payload now (the subclass's grasp point and flight)."""
        raise NotImplementedError

    @property
    def q(self) -> np.ndarray:
        """(6,) measured joint positions (the true ones unless a measurement effect is on)."""
        return self._meas_q.copy() if self._fx_measure else self.data.qpos.copy()

    @property
    def qd(self) -> np.ndarray:
        """(6,) measured joint velocities (the true ones unless a measurement effect is on)."""
        return self._meas_qd.copy() if self._fx_measure else self.data.qvel.copy()

    @property
    def gripper_open(self) -> bool:
        """The gripper has opened (the payload is free)."""
        return self._opened

    @property
    def payload_attached(self) -> bool:
        return self._attached

    @property
    def impact(self) -> Impact | None:
        """Set once the payload has hit the ground."""
        return self._impact if self._landed else None

    def _command_gripper(self, gripper_open_cmd: bool) -> None:
        """The open command's rising edge starts the opening delay, sampled from the profile's release
        delay (mean, std; clipped at 0)."""
        if gripper_open_cmd and self._attached and self._open_at is None:
            self._open_at = self.time_s + max(0.0, self.rng.normal(self._delay_mean_s, self._delay_std_s))

    def _after_physics(self) -> None:
        """After one physics period: the measurement effects' history, the opening once its delay has
        passed, the landing once the flight's impact time has come."""
        if self._fx_measure:
            # newest first, a new array each period (as np.roll would give, at a fraction of its
            # cost: the twin's per-step overhead is what a preview's rollouts spend their time on)
            self._hist_q = _shifted(self._hist_q, self.data.qpos)
            self._hist_qd = _shifted(self._hist_qd, self.data.qvel)
            self._measure()
        if self._open_at is not None and self._attached and self.time_s >= self._open_at - 1e-9:
            self._open_payload()
        if self._impact is not None and not self._landed and self.time_s >= self._impact.impact_time_s:
            self._landed = True

    def _released(self, p0: np.ndarray, v0: np.ndarray, t0: float, hit: np.ndarray, t_fall: float) -> None:
        """Record the release at ``t0`` s from ``p0`` (3,) m with ``v0`` (3,) m/s, landing ``t_fall`` s later at
        the true spot ``hit`` (3,) m; the stored landing spot is the measured one (the effects' calibration
        biases, sim_twin.twin.effects.sensing.ImpactBias, plus the profile's impact noise, SensorParams)."""
        hit = np.array(self.effects.measure_impact(hit), dtype=float)
        if self._impact_noise_m > 0:
            hit[:2] = hit[:2] + self._meas_rng.normal(0.0, self._impact_noise_m, 2)
        self._attached, self._opened = False, True
        self._release = (p0, v0, t0)
        self._impact = Impact(hit, t0, t0 + t_fall, p0, v0)


class SimulatedMachine(MachineReadout):
    """CPU twin + hydraulics + payload.

    Args:
        profile: reality profile (default: nominal machine).
        seed: seed of the release-delay jitter and of random initial poses.
    """

    def __init__(self, profile: RealityProfile | None = None, seed: int | None = None):
        self.profile = profile or RealityProfile()
        self.effects = self.profile.stack()
        self.model = fresh_model()
        if self.effects.has("model"):
            self.effects.model(self.model)
        self.data = mujoco.MjData(self.model)
        # the inertia is computed in this machine's own data (reset() below clears it: mj_resetData)
        self._inertia = passive_inertia_of(self.model, self.data) if self.effects.has("model") else passive_inertia()
        self.valves = ValveModel(self.effects.hydraulics(self.profile.hydraulics))
        self.rng = np.random.default_rng(seed)
        p = self.profile
        self._delay_mean_s, self._delay_std_s = self.effects.release_delay(p.release_delay_mean_s, p.release_delay_std_s)
        self._viscous, self._coulomb = self.effects.passive_friction(p.passive_viscous_per_s, p.passive_coulomb_rad_per_s2)
        self._grasp_offset = self.effects.grasp_offset()
        self._fx_setpoint = self.effects.has("setpoint")
        self._fx_flight = self.effects.has("flight_accel")
        self._fx_measure = self.effects.has("measure")
        self._meas_rng = np.random.default_rng(None if seed is None else [int(seed), 1])
        self._impact_noise_m = float(p.sensing.impact_noise_m)
        self.reset()

    # --- state ------------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        return float(self.data.time)

    def payload_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(pos (3,), vel (3,)) of the payload: the gripper centre while held, else its flight."""
        if self._release is None:
            if self._grasp_offset is not None:
                return grasp_point(self.data.qpos, self.data.qvel, self._grasp_offset)
            pts = forward_kinematics(np, self.data.qpos, self.data.qvel)
            return pts.gripper_centre, pts.gripper_centre_vel
        p0, v0, t0 = self._release
        if self._flight is not None:
            ts, ps, vs = self._flight
            t = min(self.time_s - t0, self._impact_time_s() - t0)
            pos = np.array([np.interp(t, ts, ps[:, i]) for i in range(3)])
            vel = np.zeros(3) if self._landed else np.array([np.interp(t, ts, vs[:, i]) for i in range(3)])
            return pos, vel
        t = min(self.time_s - t0, self._impact_time_s() - t0)
        pos = ballistic_position(np, p0, v0, t)
        vel = v0 + np.array([0.0, 0.0, -9.81]) * t
        if self._landed:
            vel = np.zeros(3)
        return pos, vel

    # --- control ----------------------------------------------------------------------------
    def reset(self, q_active: np.ndarray | None = None, cabin_turn: float | None = 0.0) -> np.ndarray:
        """Re-initialise at rest with the gripper hanging plumb and a payload in the gripper.

        Args:
            q_active: (4,) pose, or None for a random collision-free pose (sim_twin.twin.initial_pose).
            cabin_turn: cabin angle for a random pose (rad), or None for a random one.

        Returns:
            (6,) the initial joint positions.
        """
        mujoco.mj_resetData(self.model, self.data)
        if q_active is None:
            q = sample_pose(self.rng, cabin_turn=cabin_turn)
        else:
            q = np.zeros(6)
            q[:4] = np.asarray(q_active, dtype=float)
            q[4] = -(q[1] + q[2])
        self.data.qpos[:] = q
        mujoco.mj_forward(self.model, self.data)
        self.valves.reset()
        self._x_ref = np.clip(q[:NUM_ACTIVE], JOINT_LOWER[:NUM_ACTIVE], JOINT_UPPER[:NUM_ACTIVE])
        self._attached, self._opened, self._landed = True, False, False
        self._open_at: float | None = None
        self._release: tuple[np.ndarray, np.ndarray, float] | None = None
        self._flight: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._impact: Impact | None = None
        if self._fx_measure:
            n = self.effects.history_steps()
            self._hist_q = np.repeat(self.data.qpos[None].copy(), n, axis=0)
            self._hist_qd = np.repeat(self.data.qvel[None].copy(), n, axis=0)
            self._measure()
        return q

    def set_state(self, q, qd) -> None:
        """Re-initialise (as :meth:`reset`: valves neutral, payload held) at the true joint
        state q, qd (6,) (rad, m, rad/s, m/s), e.g. a preview's start; measurement effects see
        it as held since long."""
        self.reset(q_active=np.asarray(q, dtype=float)[:4])
        self.data.qpos[:] = q
        self.data.qvel[:] = qd
        mujoco.mj_forward(self.model, self.data)
        if self._fx_measure:
            self._hist_q[:] = self.data.qpos
            self._hist_qd[:] = self.data.qvel
            self._measure()

    def step(self, valve_u: np.ndarray, gripper_open_cmd: bool) -> None:
        """Advance 10 ms.

        Args:
            valve_u: (4,) valve commands in [-1, 1] (clipped by the valve model).
            gripper_open_cmd: the gripper-open command; its rising edge starts the opening
                delay, sampled from the profile's release delay (mean, std).
        """
        self._command_gripper(gripper_open_cmd)
        setpoint = self.valves.step(valve_u)
        if self._fx_setpoint:
            setpoint = self.effects.setpoint(setpoint, self.data.qpos.copy(), self.data.qvel.copy())
        self._x_ref, self.data.ctrl[:] = cylinder_step(
            np, self._x_ref, setpoint, self.data.qpos[:NUM_ACTIVE], JOINT_LOWER[:NUM_ACTIVE], JOINT_UPPER[:NUM_ACTIVE], float(self.model.opt.timestep)
        )
        self.data.qfrc_applied[4:6] = passive_friction_force(
            np,
            self.data.qvel[4:6],
            self._inertia,
            self._viscous,
            self._coulomb,
        )
        mujoco.mj_step(self.model, self.data)
        self._after_physics()

    def _impact_time_s(self) -> float:
        """The released payload's impact time, s (twin clock).

        Raises:
            RuntimeError: no payload was released (callers check ``_release`` first).
        """
        if self._impact is None:
            raise RuntimeError("impact time asked before the payload was released")
        return self._impact.impact_time_s

    def _measure(self) -> None:
        self._meas_q, self._meas_qd = self.effects.measure(self._hist_q, self._hist_qd, float(self.model.opt.timestep), self._meas_rng)

    def _open_payload(self) -> None:
        if self._grasp_offset is not None:
            p0, v0 = grasp_point(self.data.qpos, self.data.qvel, self._grasp_offset)
        else:
            pts = forward_kinematics(np, self.data.qpos, self.data.qvel)
            p0, v0 = pts.gripper_centre.copy(), pts.gripper_centre_vel.copy()
        t0 = self.time_s
        if self._fx_flight:
            ts, ps, vs, t_hit, hit = integrate_flight(p0, v0, self.effects.flight_accel)
            self._flight = (ts, ps, vs)
            t_fall = float(t_hit)
        else:
            t_fall = float(ballistic_impact_time(np, p0, v0, PAYLOAD_RADIUS_M))
            hit = ballistic_position(np, p0, v0, t_fall)
        hit[2] = 0.0
        self._released(p0, v0, t0, hit, t_fall)
