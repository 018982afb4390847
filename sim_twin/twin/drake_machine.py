"""The machine in a second physics engine: Drake (pydrake) instead of MuJoCo.

The paper evaluated its policies in a simulator other than the one it trained in; here every
figure otherwise comes from the MuJoCo model the policies were trained on. :class:`DrakeMachine`
is the same machine built independently of MuJoCo's dynamics: Drake's ``MultibodyPlant`` reads
the URDF that :mod:`sim_twin.twin.urdf` exports from the MJCF (same kinematics, masses and inertias),
and Drake's own multibody dynamics, joint damping, joint limits, contact and discrete solver
(SAP, "lagged" contact approximation) move it. What is not physics engine is shared with the
MuJoCo machine (:class:`sim_twin.twin.simulated_machine.SimulatedMachine`), so that only the physics
differs:

* the hydraulic valve model (:class:`sim_twin.twin.hydraulics.ValveModel`: dead band, transport delay,
  lag, rate limit) and the cylinder stage (:func:`runtime.dynamics.hydraulics.cylinder_step`) at
  100 Hz, and the runtime's own controller and policy (whoever drives :meth:`DrakeMachine.step`:
  runtime.executor in evaluation and in the runtime process);
* the gripper's opening delay (the profile's release delay), the payload's release at the
  gripper centre and its flight (:func:`runtime.ballistics.ground_impact` drag-free, or
  :func:`sim_twin.twin.effects.payload.integrate_flight` with the profile's flight effects: payload
  drag, wind);
* the reality profile's effects outside the rigid-body model (valve parameters, setpoint
  disturbances, passive friction values, release delay, grasp offset, flight, measurement and
  impact measurement). Effects that edit the MuJoCo model (``model`` hook: hanging mass) have no
  Drake counterpart here and are refused.

Choices of ours (CHOSEN), each the paper's number or Drake's default where one exists:

* **integrator and step**: Drake's discrete ``MultibodyPlant`` at its default configuration
  (``MultibodyPlantConfig()``: 1 ms step, SAP solver with the "lagged" contact approximation,
  hydroelastic-with-fallback contact). CHOSEN: Drake's defaults; the MuJoCo twin steps 10 ms
  (implicitfast). Valves, cylinder and measurements stay at the machine's 100 Hz.
* **the cylinders**: each active joint is a Drake joint actuator with Drake's implicit PD
  controller (``PdControllerGains``) tracking the oil column of :func:`cylinder_step`: desired
  position the oil column moving through the period at the flow the valves let through (from
  ``x_ref`` at the period's start to its end), desired velocity that flow, ``d`` = the MJCF
  velocity servo's ``kv`` and ``p`` = ``kv * HOLD_GAIN_PER_S``; the same servo law the MuJoCo twin applies as a
  velocity actuator with the hold term in its setpoint, but solved implicitly every 1 ms by
  Drake. CHOSEN: the twin's gains, no effort limit (a cylinder's force is not limited before its
  relief valve, which the rate limit stands for).
* **passive joint friction** (paper eq. (1): upsilon 0.03 1/s, eta 0.1 rad/s^2, identified by the
  paper): the viscous part is Drake's own joint damping (``RevoluteJoint.SetDamping``, treated
  implicitly by the solver), the Coulomb part a generalised force evaluated every Drake step
  (:func:`runtime.dynamics.friction.passive_friction_force` with zero viscous term) because
  Drake's MultibodyPlant has no joint Coulomb friction. Both converted from the paper's
  accelerations with the twin's effective inertias (runtime.dynamics.model.passive_inertia), so
  both engines get the same friction values. CHOSEN: the conversion, and tanh smoothing at
  0.01 rad/s as in the twin.
* **contact**: the ground (a 60 x 60 m box with its top at z = 0) and the gripper (a 0.9 x 0.9 x
  1.0 m box, the MJCF's gripper geom) collide, with Drake's default point-contact parameters (penetration
  allowance 1 mm) and Coulomb friction 0.5 (CHOSEN: steel on soil). The MuJoCo twin has no
  contact (its geoms do not collide): a gripper at the ground there is only a clearance
  violation, in Drake it also rests on the ground.
* **the payload's flight**: drag-free under the nominal profile, as the twin's (CHOSEN: so that a
  nominal comparison of the engines measures the machine's physics, not a drag only one of them
  has); a profile with ``payload_drag`` (a ball's Cd ~0.5) or ``wind`` flies with them
  (:func:`sim_twin.twin.effects.payload.integrate_flight`), e.g. ``slinger plant --engine drake
  --profile P``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from runtime.ballistics import GRAVITY_MPS2, ballistic_position, ground_impact
from runtime.dynamics.friction import passive_friction_force
from runtime.dynamics.hydraulics import HOLD_GAIN_PER_S, cylinder_step
from runtime.machine import ACTIVE_JOINTS, JOINT_LOWER, JOINT_NAMES, JOINT_UPPER, NUM_ACTIVE, PASSIVE_JOINTS, hanging_pitch
from runtime.observation import PHYSICS_PERIOD_S
from sim_twin.twin.effects.payload import GRIPPER_CENTRE_LOCAL_M, integrate_flight
from sim_twin.twin.hydraulics import ValveModel
from sim_twin.twin.initial_pose import sample_pose
from sim_twin.twin.model import passive_inertia
from sim_twin.twin.profile import RealityProfile
from sim_twin.twin.simulated_machine import Impact, MachineReadout

GROUND_FRICTION = 0.5
"""Coulomb friction of the gripper on the ground (CHOSEN: steel on soil)."""
GROUND_BOX_M = (60.0, 60.0, 1.0)
"""The ground: a box with its top face at z = 0 (the MJCF's 60 x 60 m ground plane)."""
GRIPPER_BOX_M = (0.9, 0.9, 1.0)
"""The gripper's collision box (the MJCF's gripper geom, half sizes 0.45, 0.45, 0.5), centred at
the gripper centre."""


@lru_cache(maxsize=1)
def machine_urdf() -> str:
    """The machine's URDF text, exported from the MJCF by :func:`sim_twin.twin.urdf.export_urdf`."""
    from sim_twin.twin.model import load_model
    from sim_twin.twin.urdf import export_urdf

    return export_urdf(load_model())


@lru_cache(maxsize=1)
def servo_gains() -> np.ndarray:
    """(4,) the MJCF velocity servos' kv (N m s/rad, N s/m) in ACTIVE_JOINTS order."""
    from sim_twin.twin.model import load_model

    return np.asarray(load_model().actuator_gainprm[:NUM_ACTIVE, 0], dtype=float).copy()


@dataclass
class TrueState:
    """The true joint state, under the names the MuJoCo machine's callers read
    (``sim.data.qpos`` / ``sim.data.qvel``: sim_twin.twin.twin_machine, sim_twin.twin.plant).

    Attributes:
        qpos: (6,) joint positions in JOINT_NAMES order, rad / m.
        qvel: (6,) joint velocities, rad/s / m/s.
    """

    qpos: np.ndarray
    qvel: np.ndarray


def _oil_column_system():
    """A Drake LeafSystem: the desired state (4 positions, 4 velocities) of the cylinders' PD
    actuators at the current time: the oil column of the period, ``x0 + flow * (t - t0)`` moving
    at the flow the valves let through, and that flow. Set once per 10 ms period (:meth:`set`),
    evaluated at every Drake step: the oil flows during the period, so a joint is not pulled to the
    period's end position from its start (a held position target would make the sampled joint
    speed ripple at 100 Hz and read ~4 % low at the period's end)."""
    from pydrake.systems.framework import BasicVector, LeafSystem

    class OilColumn(LeafSystem):
        def __init__(self):
            super().__init__()
            self.x0, self.flow, self.t0 = np.zeros(NUM_ACTIVE), np.zeros(NUM_ACTIVE), 0.0
            self.DeclareVectorOutputPort("desired_state", BasicVector(2 * NUM_ACTIVE), self._calc)

        def set(self, x0: np.ndarray, flow: np.ndarray, t0: float) -> None:
            self.x0, self.flow, self.t0 = np.array(x0, dtype=float), np.array(flow, dtype=float), float(t0)

        def _calc(self, context, output):
            dt = min(max(context.get_time() - self.t0, 0.0), PHYSICS_PERIOD_S)
            output.SetFromVector(np.concatenate([self.x0 + self.flow * dt, self.flow]))

    return OilColumn()


def _coulomb_system(plant, q_index: np.ndarray, v_index: np.ndarray, inertia: np.ndarray):
    """A Drake LeafSystem: plant state in, generalised forces (nv,) out: the passive joints'
    Coulomb friction (paper eq. (1), eta term; tanh-smoothed as the twin's)."""
    from pydrake.systems.framework import BasicVector, LeafSystem

    nx, nv = plant.num_multibody_states(), plant.num_velocities()
    passive = v_index[NUM_ACTIVE:]

    class PassiveCoulomb(LeafSystem):
        def __init__(self):
            super().__init__()
            self.coulomb = 0.0
            self.state_in = self.DeclareVectorInputPort("state", BasicVector(nx))
            self.DeclareVectorOutputPort("force", BasicVector(nv), self._calc)

        def _calc(self, context, output):
            x = self.state_in.Eval(context)
            f = np.zeros(nv)
            qd = x[plant.num_positions() + passive]
            f[passive] = passive_friction_force(np, qd, inertia, 0.0, self.coulomb)
            output.SetFromVector(f)

    return PassiveCoulomb()


class DrakeMachine(MachineReadout):
    """The machine in Drake behind the interface of
    :class:`sim_twin.twin.simulated_machine.SimulatedMachine` (what TwinMachine, the plant process,
    evaluation and dataset generation use): :meth:`reset`, :meth:`set_state`, :meth:`step` (one
    10 ms period), ``q``/``qd`` (measured), ``data`` (true state), ``gripper_open``,
    ``payload_attached``, ``impact``, :meth:`payload_state`, ``rng``, ``time_s``.

    Args:
        profile: reality profile (default nominal); effects with a ``model`` hook are refused.
        seed: seed of the release-delay jitter, random start poses and measurement noise.
        time_step_s: Drake's discrete step, s (default: Drake's default, 1 ms); a divisor of the
            10 ms period. The step-size study of the engine gap sets 0.01 (the twin's step).

    Raises:
        ValueError: the profile has an effect that edits the MuJoCo model.
        ImportError: pydrake is not installed (the ``drake`` extra).
    """

    def __init__(self, profile: RealityProfile | None = None, seed: int | None = None, time_step_s: float | None = None):
        from pydrake.geometry import Box
        from pydrake.math import RigidTransform
        from pydrake.multibody.parsing import Parser
        from pydrake.multibody.plant import AddMultibodyPlant, CoulombFriction, MultibodyPlantConfig
        from pydrake.multibody.tree import PdControllerGains
        from pydrake.systems.analysis import Simulator
        from pydrake.systems.framework import DiagramBuilder

        self.profile = profile or RealityProfile()
        self.effects = self.profile.stack()
        if self.effects.has("model"):
            raise ValueError("the Drake machine cannot apply effects that edit the MuJoCo model (e.g. hanging_mass)")
        builder = DiagramBuilder()
        self.config = MultibodyPlantConfig()  # CHOSEN: Drake's defaults (module doc)
        if time_step_s is not None:
            periods = PHYSICS_PERIOD_S / time_step_s
            if not (time_step_s > 0 and abs(periods - round(periods)) < 1e-9):
                raise ValueError(f"time_step_s must divide the {PHYSICS_PERIOD_S} s period, got {time_step_s}")
            self.config.time_step = float(time_step_s)
        plant, scene_graph = AddMultibodyPlant(self.config, builder)
        Parser(plant).AddModelsFromString(machine_urdf(), "urdf")
        plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("machine"))
        friction = CoulombFriction(GROUND_FRICTION, GROUND_FRICTION)
        ground = RigidTransform(np.array([0.0, 0.0, -GROUND_BOX_M[2] / 2]))  # type: ignore[arg-type]  # pydrake stub
        plant.RegisterCollisionGeometry(plant.world_body(), ground, Box(*GROUND_BOX_M), "ground", friction)
        gripper = plant.GetBodyByName("gripper")
        plant.RegisterCollisionGeometry(gripper, RigidTransform(np.array(GRIPPER_CENTRE_LOCAL_M)),  # type: ignore[arg-type]  # pydrake stub
                                        Box(*GRIPPER_BOX_M), "gripper", friction)
        joints = [plant.GetJointByName(n) for n in JOINT_NAMES]
        for name, joint, kv in zip(ACTIVE_JOINTS, joints, servo_gains()):
            act = plant.AddJointActuator(name, joint)
            act.set_controller_gains(PdControllerGains(p=kv * HOLD_GAIN_PER_S, d=kv))
        self._inertia = passive_inertia()
        plant.Finalize()
        self._q_index = np.array([j.position_start() for j in joints])
        self._v_index = np.array([j.velocity_start() for j in joints])
        coulomb = _coulomb_system(plant, self._q_index, self._v_index, self._inertia)
        builder.AddSystem(coulomb)
        builder.Connect(plant.get_state_output_port(), coulomb.state_in)
        builder.Connect(coulomb.get_output_port(0), plant.get_applied_generalized_force_input_port())
        self._oil = _oil_column_system()
        builder.AddSystem(self._oil)
        builder.Connect(self._oil.get_output_port(0), plant.get_desired_state_input_port(plant.GetModelInstanceByName("material_handler")))
        self._diagram = builder.Build()
        self._plant, self._coulomb, self._scene_graph = plant, coulomb, scene_graph
        self._passive_joints = [plant.GetJointByName(n) for n in PASSIVE_JOINTS]
        self._gripper = gripper
        self._simulator = Simulator(self._diagram)
        self._context = self._simulator.get_mutable_context()
        self._pctx = plant.GetMyMutableContextFromRoot(self._context)
        self._cctx = coulomb.GetMyMutableContextFromRoot(self._context)
        plant.get_actuation_input_port().FixValue(self._pctx, np.zeros(plant.num_actuated_dofs()))

        self.valves = ValveModel(self.effects.hydraulics(self.profile.hydraulics))
        self.rng = np.random.default_rng(seed)
        p = self.profile
        self._delay_mean_s, self._delay_std_s = self.effects.release_delay(p.release_delay_mean_s, p.release_delay_std_s)
        viscous, coulomb_acc = self.effects.passive_friction(p.passive_viscous_per_s, p.passive_coulomb_rad_per_s2)
        for joint, inertia in zip(self._passive_joints, self._inertia):
            joint.SetDamping(self._pctx, float(viscous * inertia))  # Drake's own joint damping
        coulomb.coulomb = float(coulomb_acc)
        self._grasp_offset = self.effects.grasp_offset()
        self._fx_setpoint = self.effects.has("setpoint")
        self._fx_flight = self.effects.has("flight_accel")
        self._fx_measure = self.effects.has("measure")
        self._meas_rng = np.random.default_rng(None if seed is None else [int(seed), 1])
        self._impact_noise_m = float(p.sensing.impact_noise_m)
        self._lower, self._upper = JOINT_LOWER[:NUM_ACTIVE], JOINT_UPPER[:NUM_ACTIVE]
        self.data = TrueState(np.zeros(6), np.zeros(6))
        self.reset()

    # --- state ------------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        """Simulated seconds since the last reset."""
        return self._steps * PHYSICS_PERIOD_S

    def gripper_point(self, local_m=GRIPPER_CENTRE_LOCAL_M) -> tuple[np.ndarray, np.ndarray]:
        """Position (3,) m and velocity (3,) m/s in the machine frame of a point fixed in the
        gripper frame at ``local_m`` (3,) m, from Drake's kinematics of the current state."""
        from pydrake.multibody.tree import JacobianWrtVariable

        plant, ctx, frame = self._plant, self._pctx, self._gripper.body_frame()
        p = np.asarray(local_m, dtype=float).reshape(3, 1)
        pos = plant.CalcPointsPositions(ctx, frame, p, plant.world_frame())[:, 0]
        jac = plant.CalcJacobianTranslationalVelocity(ctx, JacobianWrtVariable.kV, frame, p, plant.world_frame(), plant.world_frame())
        return pos.copy(), jac @ plant.GetVelocities(ctx)

    def _grasp(self) -> tuple[np.ndarray, np.ndarray]:
        local = np.asarray(GRIPPER_CENTRE_LOCAL_M, dtype=float)
        if self._grasp_offset is not None:
            local = local + self._grasp_offset
        return self.gripper_point(local)

    def payload_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(pos (3,), vel (3,)) of the payload: the grasp point while held, else its flight."""
        if self._release is None:
            return self._grasp()
        ts, ps, vs = self._flight
        assert self._impact is not None  # set with _release (_open_payload)
        t = min(self.time_s, self._impact.impact_time_s) - self._release[2]
        pos = np.array([np.interp(t, ts, ps[:, i]) for i in range(3)])
        vel = np.zeros(3) if self._landed else np.array([np.interp(t, ts, vs[:, i]) for i in range(3)])
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
        if q_active is None:
            q = sample_pose(self.rng, cabin_turn=cabin_turn)
        else:
            q = np.zeros(6)
            q[:4] = np.asarray(q_active, dtype=float)
            q[4] = hanging_pitch(q[:4])
        self.valves.reset()
        self._x_ref = np.clip(q[:NUM_ACTIVE], self._lower, self._upper)
        self._write_state(q, np.zeros(6))
        self._attached, self._opened, self._landed = True, False, False
        self._open_at: float | None = None
        self._release: tuple[np.ndarray, np.ndarray, float] | None = None
        self._flight: tuple[np.ndarray, np.ndarray, np.ndarray] = (np.zeros(1), np.zeros((1, 3)), np.zeros((1, 3)))
        self._impact: Impact | None = None
        if self._fx_measure:
            n = self.effects.history_steps()
            self._hist_q = np.repeat(self.data.qpos[None].copy(), n, axis=0)
            self._hist_qd = np.repeat(self.data.qvel[None].copy(), n, axis=0)
            self._measure()
        return q

    def set_state(self, q, qd) -> None:
        """Re-initialise (as :meth:`reset`: valves neutral, payload held) at the true joint
        state q, qd (6,) (rad, m, rad/s, m/s); measurement effects see it as held since long."""
        q, qd = np.asarray(q, dtype=float), np.asarray(qd, dtype=float)
        self.reset(q_active=q[:4])
        self._write_state(q, qd)
        if self._fx_measure:
            self._hist_q[:] = self.data.qpos
            self._hist_qd[:] = self.data.qvel
            self._measure()

    def _write_state(self, q: np.ndarray, qd: np.ndarray) -> None:
        self._steps = 0
        self._context.SetTime(0.0)
        x = np.zeros(self._plant.num_multibody_states())
        x[self._q_index] = q
        x[self._plant.num_positions() + self._v_index] = qd
        self._plant.SetPositionsAndVelocities(self._pctx, x)
        self._oil.set(self._x_ref, np.zeros(NUM_ACTIVE), 0.0)
        self._simulator.Initialize()
        self._read_state()

    def _read_state(self) -> None:
        x = self._plant.GetPositionsAndVelocities(self._pctx)
        self.data.qpos = x[self._q_index].copy()
        self.data.qvel = x[self._plant.num_positions() + self._v_index].copy()

    def step(self, valve_u: np.ndarray, gripper_open_cmd: bool) -> None:
        """Advance 10 ms: valves and cylinders once, then Drake to the end of the period.

        Args:
            valve_u: (4,) valve commands in [-1, 1] (clipped by the valve model).
            gripper_open_cmd: the gripper-open command; its rising edge starts the opening
                delay, sampled from the profile's release delay (mean, std).
        """
        self._command_gripper(gripper_open_cmd)
        setpoint = self.valves.step(valve_u)
        if self._fx_setpoint:
            setpoint = self.effects.setpoint(setpoint, self.data.qpos.copy(), self.data.qvel.copy())
        x_old = self._x_ref
        self._x_ref, _ = cylinder_step(np, x_old, setpoint, self.data.qpos[:NUM_ACTIVE], self._lower, self._upper, PHYSICS_PERIOD_S)
        moved = (self._x_ref - x_old) / PHYSICS_PERIOD_S  # the flow that moved the oil column this period
        self._oil.set(x_old, moved, self.time_s)
        self._steps += 1
        self._simulator.AdvanceTo(self.time_s)
        self._read_state()
        self._after_physics()

    def _measure(self) -> None:
        self._meas_q, self._meas_qd = self.effects.measure(self._hist_q, self._hist_qd, PHYSICS_PERIOD_S, self._meas_rng)

    def _open_payload(self) -> None:
        p0, v0 = self._grasp()
        t0 = self.time_s
        if self._fx_flight:
            ts, ps, vs, t_hit, hit = integrate_flight(p0, v0, self.effects.flight_accel)
            self._flight, t_fall = (ts, ps, vs), float(t_hit)
        else:
            hit, t_fall = ground_impact(p0, v0)
            ts = np.linspace(0.0, t_fall, max(2, int(np.ceil(t_fall / 0.01)) + 1))
            t = ts[:, None]
            self._flight = (ts, ballistic_position(np, p0, v0, t), v0 + t * np.array([0.0, 0.0, -GRAVITY_MPS2]))
        self._released(p0, v0, t0, hit, t_fall)

